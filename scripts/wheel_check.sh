#!/usr/bin/env bash
# Build a wheel, install it (non-editable) in a fresh venv outside the checkout, and run the
# default commands there: the built-in recipes must come from the wheel, not from configs/.
set -euo pipefail
cd "$(dirname "$0")/.."
repo=$(pwd)
PY=${PYTHON:-python3}
work=$(mktemp -d /tmp/slam-wheel-XXXXXX)
trap 'rm -rf "$work"' EXIT

echo "wheel check: building the wheel" >&2
.venv/bin/python -m pip wheel -q --no-deps --wheel-dir "$work/dist" "$repo" 2>&1 | grep -v "^WARNING" >&2 || true
wheel=$(ls "$work"/dist/pyslam_graph-*.whl)
# list first, then search: `unzip | grep -q` under pipefail fails when grep stops reading
# early and unzip gets SIGPIPE (more likely the more files the wheel holds)
listing=$(unzip -l "$wheel")
if ! grep -q "slam/configs/improved_floam.yaml" <<<"$listing"; then
  echo "wheel check: $wheel does not carry slam/configs/*.yaml" >&2
  exit 1
fi
echo "wheel check: installing $(basename "$wheel") in a fresh venv" >&2
"$PY" -m venv "$work/venv"
"$work/venv/bin/python" -m pip install -q "$wheel" 2>&1 | grep -v "^WARNING" >&2 || true
cd "$work"  # outside the checkout: nothing of the source tree is importable from here
export SLAM_CACHE="$work/cache"
"$work/venv/bin/slam" configs
"$work/venv/bin/slam" simulate corridor "$work/sim" --frames 40
bag=$(ls "$work"/sim/*.bag)
"$work/venv/bin/slam" run "$bag" --out "$work/run" --quiet
for f in trajectory.tum trajectory.kitti odometry.tum map.pcd graph.g2o metrics.json config.yaml; do
  [ -s "$work/run/$f" ] || { echo "wheel check: $f missing after slam run" >&2; exit 1; }
done
frames=$(grep -vc "^#" "$work/run/trajectory.tum")
[ "$frames" -eq 40 ] || { echo "wheel check: $frames poses, expected 40" >&2; exit 1; }
echo "wheel check passed: configs, simulate and run work from the installed wheel" >&2
