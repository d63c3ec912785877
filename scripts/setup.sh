#!/usr/bin/env bash
# Create .venv and install the package with its dependencies (idempotent).
# Installs libusb-1.0 (open3d needs it) with apt-get when it is missing.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

# grep without -q reads all of ldconfig's output: with -q it exits at the first match, ldconfig
# dies of SIGPIPE and pipefail reports the library as missing
need_lib() { ! ldconfig -p 2>/dev/null | grep "$1" >/dev/null; }
missing=()
need_lib "libusb-1.0.so.0" && missing+=(libusb-1.0-0)
need_lib "libgomp.so.1" && missing+=(libgomp1)
if [ ${#missing[@]} -gt 0 ]; then
  echo "installing system libraries: ${missing[*]}" >&2
  SUDO=""
  [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
fi

if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
stamp=.venv/.installed-$(sha1sum pyproject.toml | cut -c1-12)
if [ ! -f "$stamp" ]; then
  echo "installing pyslam-graph and its dependencies into .venv (first time: 1-3 min)..." >&2
  .venv/bin/python -m pip install -q --upgrade pip >/dev/null 2>&1 || true
  # pip's and setuptools' own chatter (editable-install warnings of the build backend) goes
  # to a log that is shown only when the install fails
  log=.venv/install.log
  if ! .venv/bin/python -m pip install -q --disable-pip-version-check -e ".[dev,viz]" >"$log" 2>&1; then
    cat "$log" >&2
    echo "error: installing the package failed (log above, kept in $log)" >&2
    exit 1
  fi
  .venv/bin/python -c "import gtsam, open3d, rosbags, evo, small_gicp, rerun"
  touch "$stamp"
fi
