"""False loops of a run against the ground truth: every loop edge of ``graph.g2o`` checked
(``slam.bench.loop_audit``: false when its constraint is more than ``--max-trans`` m or
``--max-rot-deg`` deg from the true relative pose of its keyframes).

    .venv/bin/python benchmarks/loop_audit.py RUN_DIR GT.tum [--max-trans 1 --max-rot-deg 3]
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict
from pathlib import Path

from slam.bench.loop_audit import audit, summary


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run_dir", type=Path)
    ap.add_argument("gt", type=Path)
    ap.add_argument("--max-trans", type=float, default=1.0)
    ap.add_argument("--max-rot-deg", type=float, default=3.0)
    ap.add_argument("--json", action="store_true", help="one JSON object per loop")
    a = ap.parse_args(argv)
    checks = audit(a.run_dir, a.gt, a.max_trans, a.max_rot_deg)
    for c in checks:
        if a.json:
            print(json.dumps(asdict(c)))
        else:
            flag = "FALSE" if c.false else "ok"
            print(
                f"{c.target:5d} -> {c.source:5d}  apart {c.true_distance:5.1f} m  "
                f"err {c.err_trans:6.2f} m {c.err_rot_deg:5.2f} deg  chi2 {c.chi2:9.1f}  "
                f"sigma_max {c.sigma_max:5.2f} m  {flag}"
            )
    print(json.dumps(summary(checks)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
