"""Unseen-data sweep: every 3D front end with its default recipe on data nobody tuned for.

    nice -n 10 .venv/bin/python benchmarks/unseen_sweep.py [--cases urban:1:hdl64 ...]
        [--configs improved_floam floam improved_floam_loop lego_lpb lego_loam]
        [--frames N] [--json FILE] [--set KEY=V ...]

Cases ``SCENE:SEED:SENSOR[:strip][@FRAMES]``: a simulated sequence (``ensure_sequence``,
cached) of another seed of a scene (for ``urban`` the seed redraws the buildings, the
street furniture, the parked cars, the pedestrians and the traffic, the suspension wobble
and the sensor noise; the route and its speeds stay) or the ``street`` scene (a straight
880 m drive at 15 m/s with a 440 m wide avenue of few features and junction stops, made
for this sweep: ``slam.sim.street``) or the ``highway`` scene (a straight 2 km motorway from
rest to 25 m/s with guard rails and open verges: ``slam.sim.highway``), with one of the
simulated sensors (vlp16, hdl32, hdl64, os128). ``:strip`` rewrites the bag without ring
and time fields (an ``xyzi`` driver, ``slam.bench.degrade.rewrite_bag``); ``@N`` its first
N frames (default ``--frames``). ``kitti``: the 22 real KITTI-raw HDL-64E scans (no ground
truth: the step error is against small_gicp's scan-to-scan GICP chained); ``pair``: the
real HDL-32E scan pair against its reference transform (front end only, two frames).

One row per case x config, every run in its own process through ``slam run``'s pipeline
with the recipe's defaults: APE RMSE (SE(3)-aligned) and max, the KITTI
drift (devkit segments, scaled on short paths), the largest per-frame step
error and the frame it is at, frames rejected / with tracking lost, frames/s as a ratio to
the same case's ``floam`` run of this sweep (same data, same load), and ``RAN AWAY`` when
the APE is above 2 % of the path (paths of >= 20 m) or a step error above 0.5 m
(``slam.bench.robustness.STEP_LIMIT``).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

from slam.bench.degrade import rewrite_bag
from slam.bench.robustness import (
    STEP_LIMIT,
    cell,
    kitti_reference,
    pair_case,
    run_case,
    step_errors,
)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CONFIGS = ("improved_floam", "floam", "improved_floam_loop", "lego_lpb", "lego_loam")
CASES = (  # the most telling first: the rows print as they come
    "urban:1:hdl64",
    "urban:1:vlp16",
    "street:0:vlp16@300",
    "urban:1:vlp16:strip",
    "urban:1:os128",
    "urban:1:hdl32",
    "kitti",
    "pair",
    "street:0:hdl64@300",
    "urban:1:os128:strip",
    "urban:1:hdl32:strip",
    "highway:0:hdl64@300",
)
APE_LIMIT_PCT = 2.0  # % of the path
FPS_REFERENCE = "floam"


def parse_case(case: str, frames: int) -> dict:
    """``SCENE:SEED:SENSOR[:strip][@N]`` -> its parts (kitti / pair as they are)."""
    name, _, n = case.partition("@")
    if name in ("kitti", "pair"):
        return {"case": case, "kind": name}
    parts = name.split(":")
    if len(parts) not in (3, 4) or (len(parts) == 4 and parts[3] != "strip"):
        raise SystemExit(f"case {case!r}: expected SCENE:SEED:SENSOR[:strip][@FRAMES]")
    return {
        "case": case,
        "kind": "sim",
        "scene": parts[0],
        "seed": int(parts[1]),
        "sensor": parts[2],
        "strip": len(parts) == 4,
        "frames": int(n) if n else frames,
    }


def ran_away(row: dict) -> str:
    """Why a row ran away by this sweep's rule ("" when it did not)."""
    why = []
    path, ape = row.get("path_m"), row.get("ape_rmse")
    if path and ape is not None and path >= 20.0 and 100.0 * ape / path > APE_LIMIT_PCT:
        why.append(f"APE {100.0 * ape / path:.1f} % of path")
    if (row.get("step_err_max") or 0.0) > STEP_LIMIT:
        why.append(f"step error {row['step_err_max']:.2f} m")
    if row.get("error"):
        why.append(row["error"])
    return "; ".join(why)


def _run(job: dict) -> dict:
    """One config on one input (fresh process): robustness.py's pipeline run plus where
    the worst step is, the APE max and the frames/s."""
    row = run_case(job)
    out = Path(job["out"])
    metrics = out / "metrics.json"
    if metrics.exists():
        m = json.loads(metrics.read_text())
        row["fps"] = m.get("frames_per_second")
        row["sensor_model"] = m.get("sensor")
    if job.get("gt") and (out / "trajectory.tum").exists() and row.get("frames", 0) >= 3:
        from slam.eval.metrics import evaluate

        res = evaluate(out / "trajectory.tum", Path(job["gt"]))
        st = step_errors(res.est_poses, res.gt_poses)
        row["ape_max"] = res.ape_trans["max"]
        row["drift_pct"] = (res.kitti or {}).get("t_rel_pct")
        row["step_at"] = int(np.argmax(st)) + 1 if len(st) else None
    return row


def _pair(job: dict) -> dict:
    return pair_case(job["config"], DATA / "scan_pair")


def _sim_input(spec: dict, tmp: Path) -> tuple[Path, Path]:
    from slam.sim.cache import ensure_sequence

    seq = ensure_sequence(
        spec["scene"], sensor=spec["sensor"], seed=spec["seed"], frames=spec["frames"]
    )
    bag, gt = Path(seq.bag), Path(seq.ground_truth)
    if spec["strip"]:
        name = spec["case"].replace(":", "-").replace("@", "-")
        bag, _ = rewrite_bag(bag, tmp / f"{name}.bag", "strip")
    return bag, gt


def table(rows: list[dict]) -> str:
    lines = [
        "| data | front end | frames | rejected / lost | APE RMSE / max (m) | APE % path "
        "| KITTI drift % | max step err (m) @frame | frames/s (x floam) | ran away |",
        "|" + "---|" * 10,
    ]
    for r in rows:
        ape = f"{cell(r.get('ape_rmse'))} / {cell(r.get('ape_max'))}"
        pct = r.get("ape_pct")
        fps = r.get("fps")
        ratio = r.get("fps_ratio")
        speed = "-" if fps is None else f"{fps:.2f}" + (f" (x{ratio:.2f})" if ratio else "")
        lines.append(
            f"| {r['case']} | {r['config']} | {r.get('frames')} "
            f"| {cell(r.get('rejected'))} / {cell(r.get('lost'))} | {ape} | {cell(pct, 2)} "
            f"| {cell(r.get('drift_pct'), 2)} "
            f"| {cell(r.get('step_err_max'))} @{cell(r.get('step_at'))} | {speed} "
            f"| {r.get('ran_away') or 'no'} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(CASES))
    ap.add_argument("--configs", nargs="+", default=list(CONFIGS))
    ap.add_argument("--frames", type=int, default=150, help="frames of a case without @N")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="KEY=V")
    ap.add_argument("--json", help="also write the rows here")
    args = ap.parse_args()
    specs = [parse_case(c, args.frames) for c in args.cases]
    ctx = mp.get_context("spawn")
    rows: list[dict] = []
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="unseen_") as tmp:
        tmp = Path(tmp)
        for spec in specs:
            base = {"case": spec["case"], "overrides": args.overrides}
            if spec["kind"] == "kitti":
                with tarfile.open(DATA / "kitti_raw_drive" / "data_1.tar.xz", "r:xz") as tar:
                    tar.extractall(tmp / "kitti", filter="data")
                folder = tmp / "kitti" / "data_1"
                ref = kitti_reference(folder, tmp / "kitti_ref.npy")
                base.update(bag=str(folder), reference=str(ref))
            elif spec["kind"] == "sim":
                bag, gt = _sim_input(spec, tmp)
                base.update(bag=str(bag), gt=str(gt), frames=spec["frames"])
            case_rows = []
            for c in args.configs:
                job = {**base, "config": c, "out": str(tmp / f"{len(rows)}-{c}")}
                with ctx.Pool(1) as pool:
                    try:
                        fn = _pair if spec["kind"] == "pair" else _run
                        row = pool.apply(fn, (job,))
                    except Exception as exc:  # a crash is a finding: keep the sweep going
                        row = {"case": spec["case"], "config": c, "error": repr(exc)[:200]}
                row["ran_away"] = ran_away(row)
                case_rows.append(row)
                rows.append(row)
                print(json.dumps(row), flush=True)
            ref_fps = next((r.get("fps") for r in case_rows if r["config"] == FPS_REFERENCE), None)
            for r in case_rows:
                if ref_fps and r.get("fps"):
                    r["fps_ratio"] = r["fps"] / ref_fps
    print(table(rows))
    print(f"\nsweep wall time {time.perf_counter() - t_start:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
