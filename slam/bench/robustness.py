"""The measures of the robustness sweeps (benchmarks/robustness.py, unseen_sweep.py): does a
front end run away on data nobody tuned it for? Step errors against the truth, drift over
the stops the truth makes, the ran-away rule, and one case run through the whole pipeline.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from slam.bench.degrade import true_stamps

STEP_LIMIT = 0.5  # m per frame
APE_LIMIT_PCT = 5.0  # % of the path
STOP_LIMIT = 0.5  # m over one stop
STILL_STEP = 0.02  # m per frame: below this the ground truth stands still
MIN_STOP_S = 1.0  # s
URBAN_SENSORS = ("vlp16", "hdl32", "hdl64", "os128")


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


def sequence_of(case: str, frames: int | None, urban_frames: int | None) -> tuple[Path, Path]:
    from slam.sim.cache import ensure_sequence

    if case.startswith("urban-"):
        sensor = case.split("-", 1)[1]
        sensor = sensor if sensor in URBAN_SENSORS else "vlp16"
        seq = ensure_sequence("urban", sensor=sensor, frames=urban_frames)
    else:
        seq = ensure_sequence(case, frames=frames)
    return Path(seq.bag), Path(seq.ground_truth)


def run_case(job: dict) -> dict:
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


def kitti_reference(folder: Path, out: Path) -> Path:
    """small_gicp's scan-to-scan GICP chained over the KITTI-raw scans (the step reference)."""
    from slam.bench.peers import small_gicp_pair
    from slam.io.folders import cloud_files, read_cloud

    files = cloud_files(folder)
    clouds = [read_cloud(f, index=i, stamp=0.1 * i).xyz for i, f in enumerate(files)]
    poses = [np.eye(4)]
    for a, b in zip(clouds[:-1], clouds[1:], strict=True):
        poses.append(poses[-1] @ small_gicp_pair(a, b))
    np.save(out, np.stack(poses))
    return out


def pair_case(config: str, pair: Path) -> dict:
    """The real HDL-32E pair (folder ``pair``: target.ply, source.ply, T_target_source.txt)
    through the front end: error against its reference."""
    from slam.bench.peers import motion_error, run_frontend
    from slam.io.folders import read_cloud

    T_ref = np.loadtxt(pair / "T_target_source.txt")
    tgt = read_cloud(pair / "target.ply", index=0, stamp=0.0)
    src = read_cloud(pair / "source.ply", index=1, stamp=0.1)
    outs, _ = run_frontend([tgt, src], config, [])
    t, r = motion_error(np.linalg.inv(outs[0].pose) @ outs[1].pose, T_ref)
    row = {"case": "pair", "config": config, "messages": 2, "frames": 2}
    row.update(step_err_max=t, pair_rot_deg=r, rejected=int(outs[1].extras.get("rejected", 0)))
    return verdict(row)


def cell(v, digits=3):
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)
