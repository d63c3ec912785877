"""``slam view RUN_DIR``: a finished run's outputs in the Rerun viewer (or an .rrd file).

Read from the run folder's files only (names fixed by DESIGN.md): ``map.pcd`` / ``map.ply``
as ``world/map`` coloured by height; ``trajectory.tum`` (optimised) and ``odometry.tum``
(front end) as ``world/trajectory/optimised`` and ``world/trajectory/odometry``; the accepted
loops of ``loops.csv`` as edges between the optimised positions (``world/loops``) and
between the odometry positions (``world/loops_odometry``), their scans found by stamp; and
the sensor moving along the optimised trajectory on the ``frame`` timeline.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from slam.errors import InputError
from slam.viz.birdseye import CMAP, map_file, read_map_points
from slam.viz.rerun_view import LOOP_COLOR, ODOM_COLOR, OPT_COLOR, decimate, import_rerun

MAX_MAP_POINTS = 2_000_000  # decimated beyond this (every k-th point)


def height_colors(z: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 colours of heights ``z`` (m), 1st-99th percentile over the colour map."""
    import matplotlib

    if len(z) == 0:
        return np.zeros((0, 3), dtype=np.uint8)
    lo, hi = np.percentile(z, [1.0, 99.0])
    t = np.clip((z - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    rgba = matplotlib.colormaps[CMAP](t)
    return (rgba[:, :3] * 255).astype(np.uint8)


def accepted_loops(path: Path) -> list[tuple[float, float]]:
    """(stamp_source, stamp_target) s of the accepted rows of a loops.csv."""
    if not path.is_file():
        return []
    with path.open(newline="") as fh:
        return [
            (float(r["stamp_source"]), float(r["stamp_target"]))
            for r in csv.DictReader(fh)
            if r.get("accepted") == "1"
        ]


def _nearest(stamps: np.ndarray, t: float) -> int:
    if len(stamps) < 2:
        return 0
    i = int(np.clip(np.searchsorted(stamps, t), 1, len(stamps) - 1))
    return i - 1 if abs(stamps[i - 1] - t) <= abs(stamps[i] - t) else i


def replay_run(run_dir: Path, rec: Any) -> dict[str, int]:
    """Log the outputs of ``run_dir`` to the recording stream ``rec``; returns counts of
    what was logged (map points, frames, loops)."""
    from slam.io.trajectory import read_tum

    rr = import_rerun()
    run_dir = Path(run_dir)
    traj = run_dir / "trajectory.tum"
    if not traj.is_file():
        raise InputError(
            f"{run_dir} is not a run folder (no trajectory.tum): give the --out "
            "folder of a `slam run`"
        )
    stamps, opt = read_tum(traj)
    odom_path = run_dir / "odometry.tum"
    odom = read_tum(odom_path)[1] if odom_path.is_file() else None
    counts = {"map_points": 0, "frames": len(stamps), "loops": 0}
    mp = map_file(run_dir)
    if mp is not None:
        pts = decimate(read_map_points(mp), MAX_MAP_POINTS)
        rec.log(
            "world/map", rr.Points3D(pts, colors=height_colors(pts[:, 2]), radii=0.05), static=True
        )
        counts["map_points"] = len(pts)
    rec.log(
        "world/trajectory/optimised",
        rr.LineStrips3D([opt[:, :3, 3]], colors=OPT_COLOR, radii=0.1),
        static=True,
    )
    if odom is not None and len(odom) == len(opt):
        rec.log(
            "world/trajectory/odometry",
            rr.LineStrips3D([odom[:, :3, 3]], colors=ODOM_COLOR, radii=0.1),
            static=True,
        )
    pairs = [
        (_nearest(stamps, a), _nearest(stamps, b)) for a, b in accepted_loops(run_dir / "loops.csv")
    ]
    if pairs:
        counts["loops"] = len(pairs)
        for name, poses in (("world/loops", opt), ("world/loops_odometry", odom)):
            if poses is not None and len(poses) == len(opt):
                segs = [poses[[i, j], :3, 3] for i, j in pairs]
                rec.log(name, rr.LineStrips3D(segs, colors=LOOP_COLOR, radii=0.12), static=True)
    for i, T in enumerate(opt):
        rec.set_time("frame", sequence=i)
        rec.set_time("time", duration=float(stamps[i] - stamps[0]))
        rec.log("world/sensor", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
    return counts
