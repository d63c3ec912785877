"""Robustness sweep: does any front end run away on data nobody tuned it for?

    nice -n 10 .venv/bin/python benchmarks/robustness.py [--cases urban-vlp16 urban-strip ...]
        [--configs improved_floam floam] [--frames N] [--json FILE]

One row per data x front end, every run in its own process, through the whole pipeline
(``slam.run.run_one``, what ``slam run`` does):

- frames written, messages skipped (damaged, out-of-order stamps), frames the front end
  rejected (implausible registration) and frames with tracking lost;
- APE RMSE (SE(3)-aligned, m) and as % of the path length;
- the largest per-frame step error (m: |relative translation - ground truth's| between
  consecutive written frames; where the ground truth is another estimator, as on the real
  KITTI-raw scans, small_gicp's scan-to-scan GICP, the step error is against that);
- the largest drift while the vehicle stands still (m: over each stretch of >= 1 s in which
  the ground truth moves < 2 cm per frame, |estimated displacement - true displacement|
  between its first and last frame), and how many such stops there were;
- ``RAN AWAY`` when, by a physical rule, the estimate left the vehicle: a step error above
  0.5 m (5 m/s off at 10 Hz: more than a car's braking changes the speed in one frame), an
  APE above 5 % of the path (on paths of >= 20 m), a drift above 0.5 m over a stop, or
  fewer than half the messages written.

Data (``--cases``; simulated sequences come from the cache, ``slam.sim.cache``):
urban-{vlp16,hdl32,hdl64,os128} (the car-speed drive with stops at junctions; hdl64 has no
ring/time fields, KITTI-style), urban-strip (the vlp16 bag rewritten without ring and time:
an ``xyzi`` driver), urban-jitter (header stamps jittered by up to +-20 ms), urban-drop5
(every 5th message dropped), urban-gap20 (2 s of messages missing: a stalled driver),
urban-swap (every 10th pair of messages recorded in swapped order), urban-reversed (the
header stamps run backwards), urban-zerostamps (header stamps all 0: a driver that does
not set them), urban-clockback (the header clock steps back 2.55 s at message 200),
urban-glitch (one header stamp 100 s ahead), urban-empty3 (the first three clouds empty),
urban-partial1 (the first cloud only the sweep's last 36 degrees), urban-nan30 (30 % of
every cloud NaN), urban-truncated (the bag cut at 60 % of its bytes, no index); the
rewritten bags are recorded 50-60 ms after each scan's true stamp, in the variant's
message order, so that a run on the record time is judged too; park, plaza, corridor, kitti
(the 22 real KITTI-raw HDL-64E scans, a folder of PCD files) and pair (the real HDL-32E scan
pair and its reference transform).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import tarfile
import tempfile
from pathlib import Path

from slam.bench.degrade import VARIANTS, rewrite_bag, truncate_bag
from slam.bench.robustness import (
    URBAN_SENSORS,
    cell,
    kitti_reference,
    pair_case,
    run_case,
    sequence_of,
)

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
STOP_TEXT = 90  # characters of the stop reason in the table
SCENES = ("park", "plaza", "corridor")
ALL_CASES = (
    [f"urban-{s}" for s in URBAN_SENSORS]
    + [f"urban-{v}" for v in (*VARIANTS, "truncated")]
    + list(SCENES)
    + ["kitti", "pair"]
)


def table(rows: list[dict]) -> str:
    lines = [
        "| data | front end | frames / msgs | skipped | rejected / lost | APE RMSE (m) "
        "| APE % path | max step err (m) | max stop drift (m) (stops) | ran away | stopped |",
        "|" + "---|" * 11,
    ]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['config']} | {r.get('frames')} / {r.get('messages')} "
            f"| {cell(r.get('skipped'))} | {cell(r.get('rejected'))} / {cell(r.get('lost'))} "
            f"| {cell(r.get('ape_rmse'))} | {cell(r.get('ape_pct'), 2)} "
            f"| {cell(r.get('step_err_max'))} "
            f"| {cell(r.get('stop_drift_max'))} ({cell(r.get('stops'))}) "
            f"| {r.get('ran_away') or 'no'} | {(r.get('stopped_by') or '-')[:STOP_TEXT]} |"
        )
    return "\n".join(lines)


def parse_args() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="+", default=list(ALL_CASES), help=" ".join(ALL_CASES))
    ap.add_argument("--configs", nargs="+", default=["improved_floam", "floam"])
    ap.add_argument("--frames", type=int, default=300, help="frames of park/plaza/corridor")
    ap.add_argument(
        "--urban-frames", type=int, default=400, help="frames of the urban drive (0: whole)"
    )
    ap.add_argument("--max-frames", type=int, help="process only the first N messages")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="KEY=V")
    ap.add_argument("--json", help="also write the rows here")
    return ap.parse_args()


def run_in_process(ctx, job: dict) -> dict:
    """One job in a fresh process; a crash is a finding too (a row), not the sweep's end."""
    with ctx.Pool(1) as pool:
        try:
            return pool.apply(run_case if job["case"] != "pair" else _pair_job, (job,))
        except Exception as exc:  # a crash is a finding too: keep the sweep going
            return {"case": job["case"], "config": job["config"], "ran_away": repr(exc)}


def case_input(case: str, args: argparse.Namespace, tmp: Path, kitti: dict) -> dict:
    """The input fields of a case's jobs (bag, gt or reference, stamp map); the KITTI-raw
    scans are unpacked once into ``tmp`` (remembered in ``kitti``)."""
    if case == "kitti":
        if not kitti:
            with tarfile.open(DATA / "kitti_raw_drive" / "data_1.tar.xz", "r:xz") as tar:
                tar.extractall(tmp / "kitti", filter="data")
            kitti["bag"] = tmp / "kitti" / "data_1"
            kitti["ref"] = kitti_reference(kitti["bag"], tmp / "kitti_ref.npy")
        return {"bag": str(kitti["bag"]), "reference": str(kitti["ref"])}
    if case == "pair":
        return {}
    bag, gt = sequence_of(case, args.frames, args.urban_frames or None)
    variant = case.split("-", 1)[1] if case.startswith("urban-") else ""
    extra = {}
    if variant in VARIANTS:
        bag, stamp_map = rewrite_bag(bag, tmp / f"{case}.bag", variant)
        extra["stamp_map"] = str(stamp_map)
    elif variant == "truncated":
        bag = truncate_bag(bag, tmp / f"{case}.bag")
    return {**extra, "bag": str(bag), "gt": str(gt)}


def main() -> None:
    args = parse_args()
    ctx = mp.get_context("spawn")
    rows: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="robustness_") as tmp:
        tmp = Path(tmp)
        kitti: dict = {}
        for case in args.cases:
            base = {"case": case, "overrides": args.overrides, "frames": args.max_frames}
            base.update(case_input(case, args, tmp, kitti))
            for c in args.configs:
                job = {**base, "config": c, "out": str(tmp / f"{case}-{c}")}
                rows.append(run_in_process(ctx, job))
                print(json.dumps(rows[-1]), flush=True)
    print(table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


def _pair_job(job: dict) -> dict:
    return pair_case(job["config"], DATA / "scan_pair")


if __name__ == "__main__":
    main()
