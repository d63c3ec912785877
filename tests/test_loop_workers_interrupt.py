"""Ctrl-C reaches the whole process group, the loop-verification workers too: they ignore it
(from their spawn on, while they still import), the run stops after the frame in hand and
writes every output, with no traceback of a worker. Linux: the workers are found in /proc."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from slam.sim.cache import ensure_sequence

FRAMES = 300


def _workers(parent: int) -> list[int]:
    """The multiprocessing children of ``parent`` (the loop-verification workers)."""
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            ppid = int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
            if ppid == parent and b"spawn_main" in (proc / "cmdline").read_bytes():
                pids.append(int(proc.name))
        except (OSError, ValueError, IndexError):
            continue
    return pids


def _sigint_settled(pid: int) -> bool:
    """True once the process has a disposition of its own for SIGINT (caught: Python's
    handler; ignored) or blocks it: past the bare start of a new interpreter, where the
    signal's default action ends a process before Python can say anything."""
    try:
        status = (Path("/proc") / str(pid) / "status").read_text().splitlines()
    except OSError:
        return False
    masks = dict(line.split(":\t") for line in status if line.startswith("Sig"))
    bit = 1 << (signal.SIGINT - 1)
    return any(int(masks[k], 16) & bit for k in ("SigBlk", "SigIgn", "SigCgt"))


def test_ctrl_c_to_the_process_group_of_a_loop_run_keeps_its_outputs(tmp_path):
    bag = ensure_sequence("corridor", frames=FRAMES).bag
    out = tmp_path / "run"
    # exclude_recent 5: the workers start at the first keyframe (not ~16 keyframes in)
    cmd = [sys.executable, "-m", "slam.cli", "-v", "run", str(bag),
           "--config", "improved_floam_loop", "--out", str(out), "--quiet",
           "--set", "output.write_map=false",
           "--set", "factors.loop_closure.search.exclude_recent=5"]  # fmt: skip
    proc = subprocess.Popen(
        cmd,
        start_new_session=True,  # its own process group, as a terminal's foreground job
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    seen = []
    try:
        for line in proc.stderr:
            seen.append(line.decode())
            if "worker process(es) started" in seen[-1]:
                break
        deadline = time.monotonic() + 60
        while not ((workers := _workers(proc.pid)) and all(_sigint_settled(p) for p in workers)):
            assert proc.poll() is None and time.monotonic() < deadline, "".join(seen)
            time.sleep(0.02)
        # the worker imports, waits or verifies: Ctrl-C as a terminal sends it, to every process
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    log = "".join(seen) + err.decode()
    assert proc.returncode == 130, log
    assert "Traceback" not in log and "KeyboardInterrupt" not in log, log
    assert "stopping after this frame" in log
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["stopped_by"] == "interrupted (Ctrl-C)"
    rows = [r for r in (out / "trajectory.tum").read_text().splitlines() if not r.startswith("#")]
    assert 0 < metrics["frames"] < FRAMES
    assert len(rows) == metrics["frames"]
    assert (out / "loops.csv").is_file()
    assert (out / "graph.g2o").is_file()
