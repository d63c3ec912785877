"""2D occupancy grids written in the ROS ``map_server`` format: ``map.pgm`` (8-bit, row 0
at the top: occupied 0, free 254, unknown 205) and ``map.yaml`` (image, resolution in m
per cell, origin = world position of the lower-left cell's corner, thresholds)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam.mapping.grid2d import OccupancyGrid

OCCUPIED, FREE, UNKNOWN = 0, 254, 205
OCCUPIED_THRESH, FREE_THRESH = 0.65, 0.196


def map_image(grid: OccupancyGrid) -> np.ndarray:
    """(rows, cols) uint8 image of the grid, row 0 at the top (largest y)."""
    p = grid.probability()
    img = np.full(p.shape, UNKNOWN, dtype=np.uint8)
    img[p > OCCUPIED_THRESH] = OCCUPIED
    img[p < FREE_THRESH] = FREE
    return img[::-1].copy()


def write_map_server(grid: OccupancyGrid, out: str | Path, name: str = "map") -> list[Path]:
    """``<out>/<name>.pgm`` and ``<out>/<name>.yaml``; returns both paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    img = map_image(grid)
    pgm, yaml = out / f"{name}.pgm", out / f"{name}.yaml"
    rows, cols = img.shape
    pgm.write_bytes(f"P5\n{cols} {rows}\n255\n".encode() + img.tobytes())
    ox, oy = (float(v) for v in grid.origin)
    yaml.write_text(
        f"image: {pgm.name}\n"
        f"resolution: {grid.cfg.resolution:.6f}\n"
        f"origin: [{ox:.6f}, {oy:.6f}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n"
    )
    return [pgm, yaml]


def read_pgm(path: str | Path) -> np.ndarray:
    """The image of a binary PGM (P5, 8-bit) as (rows, cols) uint8."""
    data = Path(path).read_bytes()
    parts = data.split(maxsplit=4)
    if parts[0] != b"P5":
        raise ValueError(f"{path}: not a binary PGM")
    cols, rows, _ = int(parts[1]), int(parts[2]), int(parts[3])
    return np.frombuffer(parts[4][: rows * cols], dtype=np.uint8).reshape(rows, cols)


def region_corrections(pipeline) -> dict[int, np.ndarray]:
    """World-frame correction (x, y, theta) of each regional map: optimised pose o
    odometry pose^-1 of the keyframe that closed it (its ``region_left``); the region the
    run ended in takes the last keyframe's."""
    from slam.mapping.grid2d import compose2d, inverse2d, matrix_to_pose2

    st = pipeline.state
    out: dict[int, np.ndarray] = {}
    last = None
    for kf in st.keyframes:
        if kf.id not in st.estimates:
            continue
        corr = compose2d(
            matrix_to_pose2(st.estimates[kf.id]), inverse2d(matrix_to_pose2(kf.pose_odom))
        )
        region = -1 if kf.region is None else kf.region.left
        if region >= 0:
            out[region] = corr
        last = corr
    if last is not None:
        for region in getattr(pipeline.frontend, "regions", {}):
            out.setdefault(region, last)
    return out


def write_region_map(pipeline, out: str | Path) -> list[Path]:
    """``map.pgm`` + ``map.yaml`` of a 2D run whose front end keeps regional maps
    (``global_grid``): the regional maps fused at their optimised placement, or, when the
    front end keeps visits (``visit_grid``), the visits' hits at their optimised keyframe
    poses. [] otherwise."""
    frontend = pipeline.frontend
    if not hasattr(frontend, "global_grid") or not pipeline.state.keyframes:
        return []
    visits = getattr(frontend, "visit_grid", None)
    grid = visits(pipeline.state.estimates) if callable(visits) else None
    if grid is not None:  # the visit graph: the visits re-fused at their optimised poses
        return write_map_server(grid, out) if grid.data.size else []
    placements = getattr(frontend, "region_placements", None)
    corrections = placements(pipeline.state.estimates) if callable(placements) else None
    if corrections is None:  # else each map placed by the keyframe that opened it
        corrections = region_corrections(pipeline)
    grid = frontend.global_grid(corrections)
    if grid.data.size == 0:
        return []
    return write_map_server(grid, out)
