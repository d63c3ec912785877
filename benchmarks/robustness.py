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

import numpy as np

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
STEP_LIMIT = 0.5  # m per frame
APE_LIMIT_PCT = 5.0  # % of the path
STOP_LIMIT = 0.5  # m over one stop
STILL_STEP = 0.02  # m per frame: below this the ground truth stands still
MIN_STOP_S = 1.0  # s
STOP_TEXT = 90  # characters of the stop reason in the table

URBAN_SENSORS = ("vlp16", "hdl32", "hdl64", "os128")
VARIANTS = (
    "strip", "jitter", "drop5", "gap20", "swap", "reversed", "zerostamps", "clockback",
    "glitch", "empty3", "partial1", "nan30",
)  # fmt: skip
GAP_AT = 150  # the first message of gap20's 2 s stall (a third into shorter bags)
JUMP_AT = 200  # where clockback's clock steps back, glitch's stamp jumps (or half-way)
SCENES = ("park", "plaza", "corridor")
ALL_CASES = (
    [f"urban-{s}" for s in URBAN_SENSORS]
    + [f"urban-{v}" for v in (*VARIANTS, "truncated")]
    + list(SCENES)
    + ["kitti", "pair"]
)


# ------------------------------------------------------------------ measures
def step_errors(est: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """|relative translation - ground truth's| of each consecutive pair of poses (m)."""
    if len(est) < 2:
        return np.zeros(0)
    rel_e = np.linalg.inv(est[:-1]) @ est[1:]
    rel_g = np.linalg.inv(gt[:-1]) @ gt[1:]
    return np.linalg.norm(rel_e[:, :3, 3] - rel_g[:, :3, 3], axis=1)


def stops(stamps: np.ndarray, gt: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each stretch of >= MIN_STOP_S in which the ground truth moves
    less than STILL_STEP per frame."""
    if len(gt) < 2:
        return []
    still = np.linalg.norm(np.diff(gt[:, :3, 3], axis=0), axis=1) < STILL_STEP
    out, i = [], 0
    while i < len(still):
        if not still[i]:
            i += 1
            continue
        j = i
        while j < len(still) and still[j]:
            j += 1
        if stamps[j] - stamps[i] >= MIN_STOP_S:
            out.append((i, j))
        i = j
    return out


def stop_drift(stamps: np.ndarray, est: np.ndarray, gt: np.ndarray) -> tuple[float, int]:
    """Largest |estimated - true displacement| over a stop (m) and the number of stops."""
    spans = stops(stamps, gt)
    worst = 0.0
    for i, j in spans:
        de = (np.linalg.inv(est[i]) @ est[j])[:3, 3]
        dg = (np.linalg.inv(gt[i]) @ gt[j])[:3, 3]
        worst = max(worst, float(np.linalg.norm(de - dg)))
    return worst, len(spans)


def verdict(row: dict) -> dict:
    """Add ``ape_pct`` and the ``ran_away`` flag (with the rule that fired) to a row."""
    why = []
    path, ape = row.get("path_m"), row.get("ape_rmse")
    if path and ape is not None:
        row["ape_pct"] = 100.0 * ape / path
        if path >= 20.0 and row["ape_pct"] > APE_LIMIT_PCT:
            why.append(f"APE {row['ape_pct']:.1f} % of path")
    if (row.get("step_err_max") or 0.0) > STEP_LIMIT:
        why.append(f"step error {row['step_err_max']:.2f} m")
    if (row.get("stop_drift_max") or 0.0) > STOP_LIMIT:
        why.append(f"stop drift {row['stop_drift_max']:.2f} m")
    if row.get("messages") and row["frames"] < 0.5 * row["messages"]:
        why.append(f"{row['frames']} of {row['messages']} messages written")
    row["ran_away"] = "; ".join(why)
    return row


# ------------------------------------------------------------------ data
def rewrite_bag(src_bag: Path, out: Path, variant: str, seed: int = 0) -> tuple[Path, Path]:
    """The bag ``src_bag`` rewritten as a ``variant`` (see the module doc), and a .npy of
    (header stamp, true stamp, record time) of its messages (the association with the
    ground truth, whichever clock the run stamps with)."""
    from slam.io.source import open_source
    from slam.types import Scan

    scans = [s for s in open_source(src_bag) if isinstance(s, Scan)]
    rng = np.random.default_rng(seed)
    true = {id(s): float(s.stamp) for s in scans}
    t_sorted = sorted(true.values())
    gap_at, jump_at = min(GAP_AT, len(scans) // 3), min(JUMP_AT, len(scans) // 2)
    layout = "velodyne"
    if variant == "strip":
        layout = "xyzi"
    elif variant == "jitter":
        for s in scans:
            s.stamp = float(s.stamp) + float(rng.uniform(-0.02, 0.02))
    elif variant == "drop5":
        scans = [s for i, s in enumerate(scans) if i % 5 != 4]
    elif variant == "gap20":  # the driver or the recorder stalled for 2 s
        scans = [s for i, s in enumerate(scans) if not gap_at <= i < gap_at + 20]
    elif variant == "swap":
        for k in range(0, len(scans) - 1, 10):
            scans[k], scans[k + 1] = scans[k + 1], scans[k]
    elif variant == "reversed":
        t0, t1 = scans[0].stamp, scans[-1].stamp
        for s in scans:
            s.stamp = t0 + (t1 - float(s.stamp))
    elif variant == "zerostamps":  # a driver that never sets header.stamp
        for s in scans:
            s.stamp = 0.0
    elif variant == "clockback":  # the sensor clock steps back 2.55 s (a PTP correction)
        for s in scans[jump_at:]:
            s.stamp = float(s.stamp) - 2.55  # not onto the earlier stamps: a unique match
    elif variant == "glitch":  # one header stamp 100 s in the future
        scans[jump_at].stamp = float(scans[jump_at].stamp) + 100.0
    elif variant == "empty3":  # the driver starting up: three clouds without a point
        for s in scans[:3]:
            s.xyz, s.intensity, s.ring, s.time = (
                np.zeros((0, 3)), np.zeros(0, np.float32), np.zeros(0, np.int16), np.zeros(0)
            )  # fmt: skip
    elif variant == "partial1":  # the first cloud holds only the sweep's last 36 degrees
        s = scans[0]
        az = np.arctan2(s.xyz[:, 1], s.xyz[:, 0])
        scans[0] = s.select(az > np.pi * 0.8)
        true[id(scans[0])] = true[id(s)]
    elif variant == "nan30":  # an organised driver: 30 % of the points are NaN (no return)
        for s in scans:
            s.xyz = s.xyz.copy()
            s.xyz[rng.random(len(s)) < 0.3] = np.nan
    else:
        raise ValueError(variant)
    # the record time: when the recorder got the message (50-60 ms after its true stamp)
    record = np.array(t_sorted[: len(scans)]) + 0.05 + rng.uniform(0.0, 0.01, len(scans))
    if variant in ("drop5", "gap20"):
        record = np.array(sorted(true[id(s)] for s in scans)) + 0.05
    stamp_map = out.with_suffix(".stamps.npy")
    np.save(
        stamp_map,
        np.array([(float(s.stamp), true[id(s)], r) for s, r in zip(scans, record, strict=True)]),
    )
    return _write_in_record_order(out, scans, layout, record), stamp_map


def _write_in_record_order(out: Path, scans: list, layout: str, record: np.ndarray) -> Path:
    """The scans as a ROS1 bag in the given order: header stamp ``scan.stamp``, record time
    ``record`` (s; the playback order)."""
    from slam.io.bag_writer import POINTCLOUD2, BagWriter
    from slam.io.pointcloud2 import encode_pointcloud2

    with BagWriter(out, "ros1", overwrite=True) as bag:
        bag.add_topic("/velodyne_points", POINTCLOUD2)
        for scan, t in zip(scans, record, strict=True):
            msg = encode_pointcloud2(scan, bag.typestore, frame_id="velodyne", layout=layout)
            bag.write("/velodyne_points", float(t), msg)
    return out


def truncate_bag(src_bag: Path, out: Path, keep: float = 0.6) -> Path:
    """The first ``keep`` of the bytes of ``src_bag`` (a recording killed: no index)."""
    raw = Path(src_bag).read_bytes()
    out.write_bytes(raw[: int(len(raw) * keep)])
    return out


def _sequence(case: str, frames: int | None, urban_frames: int | None) -> tuple[Path, Path]:
    from slam.sim.cache import ensure_sequence

    if case.startswith("urban-"):
        sensor = case.split("-", 1)[1]
        sensor = sensor if sensor in URBAN_SENSORS else "vlp16"
        seq = ensure_sequence("urban", sensor=sensor, frames=urban_frames)
    else:
        seq = ensure_sequence(case, frames=frames)
    return Path(seq.bag), Path(seq.ground_truth)


def true_stamps(stamp_map: np.ndarray, stamps: np.ndarray) -> np.ndarray:
    """The true stamps of a run's trajectory ``stamps`` from ``rewrite_bag``'s map: the
    run stamped with the header clock, the record clock or, having followed a clock step
    (urban-clockback), the true one, whichever column its stamps match best (the nearest
    entry of it; the median distance decides, ties go to the true clock)."""
    best = None
    for col in (1, 0, 2):
        order = np.argsort(stamp_map[:, col], kind="stable")
        ref = stamp_map[order, col]
        k = np.clip(np.searchsorted(ref, stamps), 1, max(len(ref) - 1, 1))
        k -= np.abs(ref[k - 1] - stamps) <= np.abs(ref[k] - stamps)  # the nearest
        err = float(np.median(np.abs(ref[k] - stamps)))
        if best is None or err < best[0]:
            best = (err, stamp_map[order[k], 1])
    return best[1]


# ------------------------------------------------------------------ runs
def _run(job: dict) -> dict:
    """One config on one input through the pipeline (in a fresh process)."""
    from slam.config import load_config
    from slam.errors import InputError
    from slam.eval.metrics import evaluate
    from slam.run import run_one

    config = load_config(job["config"], job.get("overrides") or [])
    if job.get("frames"):
        config.source.max_frames = job["frames"]
    out = Path(job["out"])
    try:
        summary = run_one(Path(job["bag"]), config, out, quiet=True)
    except InputError as exc:  # what `slam run` reports as "error: ..." with exit 2
        row = {"case": job["case"], "config": job["config"], "frames": 0}
        return verdict({**row, "stopped_by": f"error: {exc}"})
    m = json.loads((out / "metrics.json").read_text())
    counts = m.get("frontend_counts") or {}
    messages = summary["frames"] + m.get("messages_skipped", 0)
    if job.get("stamp_map"):  # every message of the bag, also when the run stopped early
        messages = len(np.load(job["stamp_map"]))
    row = {
        "case": job["case"],
        "config": job["config"],
        "messages": messages,
        "frames": summary["frames"],
        "skipped": m.get("messages_skipped", 0),
        "rejected": counts.get("rejected"),
        "lost": counts.get("tracking_lost"),
        "stopped_by": summary.get("stopped_by"),
    }
    if job.get("gt") and summary["frames"] >= 3:
        est = out / "trajectory.tum"
        if job.get("stamp_map"):  # evaluate at the true stamps of the messages
            from slam.io.trajectory import read_tum, write_tum

            stamps, poses = read_tum(est)
            true = true_stamps(np.load(job["stamp_map"]), stamps)
            write_tum(out / "trajectory_true_stamps.tum", true, poses)
            est = out / "trajectory_true_stamps.tum"
        res = evaluate(est, Path(job["gt"]))
        st = step_errors(res.est_poses, res.gt_poses)
        drift, n_stops = stop_drift(res.stamps, res.est_poses, res.gt_poses)
        row.update(
            path_m=round(res.path_length, 1),
            ape_rmse=res.ape_trans["rmse"],
            step_err_max=float(st.max()) if len(st) else 0.0,
            stop_drift_max=drift,
            stops=n_stops,
        )
    elif job.get("reference"):
        from slam.io.trajectory import read_tum

        _, est = read_tum(out / "odometry.tum")
        ref = np.load(job["reference"])
        st = step_errors(est, ref[: len(est)])
        row.update(step_err_max=float(st.max()) if len(st) else 0.0)
    return verdict(row)


def _kitti_reference(folder: Path, out: Path) -> Path:
    """small_gicp's scan-to-scan GICP chained over the KITTI-raw scans (the step reference)."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_real import small_gicp_pair

    from slam.io.folders import cloud_files, read_cloud

    files = cloud_files(folder)
    clouds = [read_cloud(f, index=i, stamp=0.1 * i).xyz for i, f in enumerate(files)]
    poses = [np.eye(4)]
    for a, b in zip(clouds[:-1], clouds[1:], strict=True):
        poses.append(poses[-1] @ small_gicp_pair(a, b))
    np.save(out, np.stack(poses))
    return out


def _pair(config: str) -> dict:
    """The real HDL-32E pair through the front end: error against its reference."""
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_real import motion_error, run_frontend

    from slam.io.folders import read_cloud

    pair = DATA / "scan_pair"
    T_ref = np.loadtxt(pair / "T_target_source.txt")
    tgt = read_cloud(pair / "target.ply", index=0, stamp=0.0)
    src = read_cloud(pair / "source.ply", index=1, stamp=0.1)
    outs, _ = run_frontend([tgt, src], config, [])
    t, r = motion_error(np.linalg.inv(outs[0].pose) @ outs[1].pose, T_ref)
    row = {"case": "pair", "config": config, "messages": 2, "frames": 2}
    row.update(step_err_max=t, pair_rot_deg=r, rejected=int(outs[1].extras.get("rejected", 0)))
    return verdict(row)


def _fmt(v, digits=3):
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def table(rows: list[dict]) -> str:
    lines = [
        "| data | front end | frames / msgs | skipped | rejected / lost | APE RMSE (m) "
        "| APE % path | max step err (m) | max stop drift (m) (stops) | ran away | stopped |",
        "|" + "---|" * 11,
    ]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['config']} | {r.get('frames')} / {r.get('messages')} "
            f"| {_fmt(r.get('skipped'))} | {_fmt(r.get('rejected'))} / {_fmt(r.get('lost'))} "
            f"| {_fmt(r.get('ape_rmse'))} | {_fmt(r.get('ape_pct'), 2)} "
            f"| {_fmt(r.get('step_err_max'))} "
            f"| {_fmt(r.get('stop_drift_max'))} ({_fmt(r.get('stops'))}) "
            f"| {r.get('ran_away') or 'no'} | {(r.get('stopped_by') or '-')[:STOP_TEXT]} |"
        )
    return "\n".join(lines)


def main() -> None:
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
    args = ap.parse_args()
    urban_frames = args.urban_frames or None
    ctx = mp.get_context("spawn")
    rows: list[dict] = []

    def run(job: dict) -> None:
        with ctx.Pool(1) as pool:
            try:
                rows.append(pool.apply(_run if job["case"] != "pair" else _pair_job, (job,)))
            except Exception as exc:  # a crash is a finding too: keep the sweep going
                rows.append({"case": job["case"], "config": job["config"], "ran_away": repr(exc)})
        print(json.dumps(rows[-1]), flush=True)

    with tempfile.TemporaryDirectory(prefix="robustness_") as tmp:
        tmp = Path(tmp)
        kitti = None
        for case in args.cases:
            base = {"case": case, "overrides": args.overrides, "frames": args.max_frames}
            if case == "kitti":
                if kitti is None:
                    with tarfile.open(DATA / "kitti_raw_drive" / "data_1.tar.xz", "r:xz") as tar:
                        tar.extractall(tmp / "kitti", filter="data")
                    kitti = tmp / "kitti" / "data_1"
                    ref = _kitti_reference(kitti, tmp / "kitti_ref.npy")
                base.update(bag=str(kitti), reference=str(ref))
            elif case != "pair":
                bag, gt = _sequence(case, args.frames, urban_frames)
                variant = case.split("-", 1)[1] if case.startswith("urban-") else ""
                if variant in VARIANTS:
                    bag, stamp_map = rewrite_bag(bag, tmp / f"{case}.bag", variant)
                    base["stamp_map"] = str(stamp_map)
                elif variant == "truncated":
                    bag = truncate_bag(bag, tmp / f"{case}.bag")
                base.update(bag=str(bag), gt=str(gt))
            for c in args.configs:
                run({**base, "config": c, "out": str(tmp / f"{case}-{c}")})
    print(table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))


def _pair_job(job: dict) -> dict:
    return _pair(job["config"])


if __name__ == "__main__":
    main()
