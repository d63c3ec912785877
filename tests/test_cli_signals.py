"""A run started with SIGINT ignored (a background job of a non-interactive shell) can still
be stopped by `kill -INT`, keeping its outputs, as Ctrl-C does in the foreground; also when
the signal arrives while numba compiles a kernel (a cold cache compiles in the first frames:
the run stops after the frame in hand, never inside compiled code)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

from slam.cli import main


def test_main_restores_an_ignored_interrupt(capsys):
    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        assert main(["configs"]) == 0
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, before)


def test_kill_int_stops_a_background_run_and_keeps_its_frames(tmp_path):
    from slam.sim.cache import ensure_sequence

    bag = ensure_sequence("corridor", frames=300).bag
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "slam.cli", "-v", "run", str(bag), "--config", "floam",
           "--out", str(out), "--quiet", "--set", "output.write_map=false"]  # fmt: skip
    proc = subprocess.Popen(
        cmd,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    seen = []
    for line in proc.stderr:  # the beam table is logged after the first scans
        seen.append(line.decode())
        if "sensor:" in seen[-1]:
            break
    assert proc.poll() is None, "".join(seen)
    time.sleep(1.5)  # some frames done (floam: ~70 frames/s on 2 cores)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, "".join(seen) + err.decode()
    frames = (out / "trajectory.tum").read_text().splitlines()
    assert 0 < len(frames) < 300
