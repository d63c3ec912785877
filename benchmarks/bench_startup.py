"""Where the start-up of a whole ``slam run`` process goes: CPU and wall seconds per phase
(imports, config and plugin loading, opening the input, the numba warm-up, each frame,
writing the outputs) and the CPU of the child processes (loop verification workers).

    .venv/bin/python benchmarks/bench_startup.py BAG [--config NAME] [--frames 5] [--repeat 3]

Every repeat is a fresh process (``os.wait4`` gives its CPU time with its children); the
phases are marked inside it by wrapping ``slam.config.load_config``, ``slam.run._warm_up``,
``slam.pipeline.run_stream``, ``SlamSystem.process`` and ``slam.run._write_all``. CPU time,
not wall time, is the measure on a shared machine. Measured (urban VLP-16, 5 frames, warm
numba cache, load 6 on 2 cores): ``improved_floam_loop`` 7.4-8.1 s CPU of which warm-up 1.3,
loop worker 1.0, the start-in-motion search of frame 2 2.3, imports and config 0.9-1.0;
after the warm-up without the search and the workers started only when a candidate is
near: 4.8-5.6 s CPU (warm-up 0.6, no worker, interpreter exit 0.35).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

CHILD = r"""
import json, resource, sys, time
marks = [("start", time.process_time(), time.perf_counter())]
def mark(name):
    marks.append((name, time.process_time(), time.perf_counter()))
import slam.cli
mark("import slam.cli")
import slam.config, slam.pipeline, slam.run, slam.system
def wrap(mod, name, label):
    f = getattr(mod, name)
    def g(*a, **k):
        mark("before " + label)
        r = f(*a, **k)
        mark(label)
        return r
    setattr(mod, name, g)
wrap(slam.config, "load_config", "config and plugins")
wrap(slam.run, "_warm_up", "warm-up")
wrap(slam.pipeline, "run_stream", "end of the stream")
wrap(slam.run, "_write_all", "outputs")
process = slam.system.SlamSystem.process
count = [0]
def counted(self, *a, **k):
    r = process(self, *a, **k)
    count[0] += 1
    mark(f"frame {count[0]}")
    return r
slam.system.SlamSystem.process = counted
sys.argv = ["slam"] + sys.argv[1:]
try:
    slam.cli.main()
except SystemExit:
    pass
mark("end")
print("PHASES " + json.dumps(marks))
"""


def phases(marks: list) -> list[tuple[str, float, float]]:
    """(phase, CPU s, wall s) between consecutive marks; "before X" marks open phase X."""
    out = []
    for (_, c0, w0), (name, c1, w1) in zip(marks, marks[1:], strict=False):
        label = name.replace("before ", "(") + (")" if name.startswith("before ") else "")
        out.append((label, c1 - c0, w1 - w0))
    return out


def run_once(args: argparse.Namespace, out: str) -> tuple[list, float, float, float]:
    """One fresh process: its phases, its CPU s up to the end of ``main``, the CPU s after
    that (interpreter exit) and of its children, wall s."""
    cmd = [sys.executable, "-c", CHILD, "run", args.bag, "--config", args.config]
    cmd += ["--max-frames", str(args.frames), "--out", out, "--quiet"]
    start = os.times()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    stdout, _ = proc.communicate()
    end = os.times()
    line = next(x for x in stdout.splitlines() if x.startswith("PHASES "))
    cpu = (end.children_user - start.children_user) + (end.children_system - start.children_system)
    marks = json.loads(line[len("PHASES ") :])
    own = marks[-1][1]  # the process's own CPU at its end (from interpreter start)
    return phases(marks), own, cpu - own, end.elapsed - start.elapsed


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("bag")
    ap.add_argument("--config", default="improved_floam_loop")
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f}; {args.config}, {args.frames} frames")
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeat):
            rows, own, children, wall = run_once(args, os.path.join(tmp, str(r)))
            print(f"run {r + 1}: CPU {own + children:.2f} s ({own:.2f} to the end of main + "
                  f"{children:.2f} exit and children), wall {wall:.2f} s")  # fmt: skip
            for label, cpu, w in rows:
                print(f"    {label:22s} CPU {cpu:6.2f}  wall {w:6.2f}")


if __name__ == "__main__":
    main()
