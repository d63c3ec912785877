"""Bird's-eye pictures of a run's map: the highest point of each ground cell coloured by its
height (m), the trajectory on top.

Three pictures, written as PNG for the report (:func:`map_images`): the map file of the
run (``map.pcd`` / ``map.ply``) under the optimised trajectory; for runs that closed
loops, the keyframe clouds placed by the front end's poses beside the same clouds placed by
the optimised poses (the map before and after loop closure, loop edges in red); and a 2D
run's occupancy image (``map.pgm``) pixel for pixel as map_server reads it. The map is
rasterised with numpy (one max per cell), so a map of millions of points draws in well under
a second, unlike a scatter plot.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slam.errors import InputError

log = logging.getLogger(__name__)

MAP_PNG = "map_birdseye.png"
MAP_LOOPS_PNG = "map_before_after_loops.png"
MAP_PGM_PNG = "map_pgm.png"
PIXELS = 900  # raster cells along the longer side of the view
MARGIN = 25.0  # m of map shown around the trajectory (a LiDAR sees ~50-100 m)
MIN_CELL = 0.15  # m: the finest raster cell (sparse maps of small places stay legible)
ZOOM_HALF = 20.0  # m: half the side of the zoom on a revisit
ZOOM_CELL = 0.1  # m
CMAP = "viridis"
TRAJ_COLOR = "tab:red"
LOOP_COLOR = "#ff00ff"
DPI = 100


@dataclass(frozen=True)
class Grid:
    """A ground raster: lower-left corner (x0, y0) m, square cells of ``cell`` m, nx x ny."""

    x0: float
    y0: float
    cell: float
    nx: int
    ny: int

    @classmethod
    def around(
        cls,
        xy: np.ndarray,
        margin: float = MARGIN,
        pixels: int = PIXELS,
        points: np.ndarray | None = None,
    ) -> Grid:
        """The grid covering the positions ``xy`` (N, 2) m plus ``margin`` m on every side,
        shrunk to the extent of ``points`` (0.5-99.5th percentile) when they are given."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        xy = xy[np.all(np.isfinite(xy), axis=1)]
        if len(xy) == 0:
            raise InputError("no finite trajectory position to frame the map picture")
        lo, hi = xy.min(axis=0) - margin, xy.max(axis=0) + margin
        if points is not None and len(points) > 10:
            p_lo, p_hi = np.percentile(np.asarray(points)[:, :2], [0.5, 99.5], axis=0)
            lo = np.minimum(np.maximum(lo, p_lo - 1.0), xy.min(axis=0) - 1.0)
            hi = np.maximum(np.minimum(hi, p_hi + 1.0), xy.max(axis=0) + 1.0)
        cell = max(float((hi - lo).max()) / pixels, MIN_CELL)
        nx, ny = (np.ceil((hi - lo) / cell).astype(int) + 1).tolist()
        return cls(float(lo[0]), float(lo[1]), cell, nx, ny)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(left, right, bottom, top) m, as matplotlib's ``imshow(extent=...)`` takes it."""
        return (
            self.x0,
            self.x0 + self.nx * self.cell,
            self.y0,
            self.y0 + self.ny * self.cell,
        )


class HeightRaster:
    """The highest z (m) of the points that fell in each cell of a :class:`Grid`."""

    def __init__(self, grid: Grid):
        self.grid = grid
        self._top = np.full(grid.nx * grid.ny, -np.inf)

    def add(self, points: np.ndarray) -> None:
        """Add (N, >=3) world points (m); points outside the grid are left out."""
        p = np.asarray(points)
        if len(p) == 0:
            return
        g = self.grid
        ix = np.floor((p[:, 0] - g.x0) / g.cell)
        iy = np.floor((p[:, 1] - g.y0) / g.cell)
        ok = (ix >= 0) & (ix < g.nx) & (iy >= 0) & (iy < g.ny) & np.isfinite(p[:, 2])
        flat = iy[ok].astype(np.int64) * g.nx + ix[ok].astype(np.int64)
        np.maximum.at(self._top, flat, p[ok, 2].astype(float))

    def image(self) -> np.ndarray:
        """(ny, nx) heights, row 0 at the bottom (y0); NaN where no point fell."""
        top = self._top.reshape(self.grid.ny, self.grid.nx)
        return np.where(np.isfinite(top), top, np.nan)

    @property
    def filled(self) -> int:
        """Number of cells holding at least one point."""
        return int(np.isfinite(self._top).sum())


def height_limits(images: Iterable[np.ndarray]) -> tuple[float, float]:
    """Colour range (m): 1st to 99th percentile of the filled cells of all ``images`` (a
    lamp pole or a stray point does not wash out the colours of the rest)."""
    values = np.concatenate([im[np.isfinite(im)] for im in images] or [np.zeros(0)])
    if len(values) == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(values, [1.0, 99.0])
    return float(lo), float(max(hi, lo + 0.1))


def draw_map(
    ax: Any,
    raster: HeightRaster,
    limits: tuple[float, float],
    trajectory_xy: np.ndarray | None = None,
    loops: np.ndarray | None = None,
) -> Any:
    """Draw ``raster`` on ``ax`` (x east, y north, equal scale), the trajectory (N, 2) on top
    and loop edges (M, 2, 2) m; returns the image artist (for a colour bar)."""
    image = ax.imshow(
        raster.image(),
        origin="lower",
        extent=raster.grid.extent,
        cmap=CMAP,
        vmin=limits[0],
        vmax=limits[1],
        interpolation="nearest",
    )
    if trajectory_xy is not None and len(trajectory_xy):
        ax.plot(*np.asarray(trajectory_xy).T, color="white", lw=3.0, alpha=0.8)
        ax.plot(*np.asarray(trajectory_xy).T, color=TRAJ_COLOR, lw=1.3, label="trajectory")
    if loops is not None and len(loops):
        from matplotlib.collections import LineCollection

        edges = LineCollection(np.asarray(loops), colors=LOOP_COLOR, linewidths=1.6)
        edges.set_label(f"loop closures ({len(loops)})")
        ax.add_collection(edges)
    ax.set_xlim(raster.grid.extent[:2])
    ax.set_ylim(raster.grid.extent[2:])
    ax.set_aspect("equal")
    ax.set_facecolor("#f4f4f4")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    return image


def birdseye_figure(points: np.ndarray, trajectory_xy: np.ndarray, title: str = "Map"):
    """One bird's-eye view of ``points`` (N, 3) m coloured by height, trajectory on top."""
    import matplotlib.pyplot as plt

    grid = Grid.around(trajectory_xy, points=points)
    raster = HeightRaster(grid)
    raster.add(points)
    height = float(np.clip(8.0 * grid.ny / grid.nx, 3.0, 8.0)) + 1.0  # inches, map + title
    fig = plt.figure(figsize=(10.0, height), dpi=DPI, layout="constrained")
    ax = fig.add_subplot(111)
    image = draw_map(ax, raster, height_limits([raster.image()]), trajectory_xy)
    fig.colorbar(image, ax=ax, shrink=0.8, label="height of the highest point (m)")
    ax.set_title(f"{title}: {len(points)} points seen from above")
    ax.legend(loc="upper right", frameon=True)
    return fig


def before_after_figure(
    rows: Sequence[tuple[HeightRaster, HeightRaster, str]],
    odom_xy: np.ndarray,
    opt_xy: np.ndarray,
    loops_before: np.ndarray,
    loops_after: np.ndarray,
):
    """The keyframe clouds placed by the front end's poses (left) and by the optimised ones
    (right), one row per (before, after, what) raster pair (the whole map, a zoom on a
    revisit), same colours throughout: what loop closure did to the map."""
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(16.0, 7.0 * len(rows)), dpi=DPI, layout="constrained")
    axes = np.asarray(fig.subplots(len(rows), 2)).reshape(len(rows), 2)
    limits = height_limits([im.image() for before, after, _ in rows for im in (before, after)])
    for (before, after, what), (left, right) in zip(rows, axes, strict=True):
        draw_map(left, before, limits, odom_xy, loops_before)
        image = draw_map(right, after, limits, opt_xy, loops_after)
        left.set_title(f"{what} before loop closure (odometry poses)")
        right.set_title(f"{what} after loop closure (optimised poses)")
    for ax in axes[0]:
        ax.legend(loc="upper right", frameon=True)
    fig.colorbar(image, ax=list(axes.ravel()), shrink=0.6, label="height of the highest point (m)")
    return fig


def save_png(fig: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, format="png", dpi=DPI)
    finally:
        plt.close(fig)
    return path


# --------------------------------------------------------------------------- run files


def read_map_points(path: Path) -> np.ndarray:
    """(N, 3) float32 points of a run's map file (.pcd read with numpy, .ply with open3d)."""
    if path.suffix.lower() == ".pcd":
        from slam.io.pcd import read_pcd_columns

        try:
            _, cols = read_pcd_columns(path.read_bytes(), str(path))
            return np.column_stack([cols["x"], cols["y"], cols["z"]]).astype(np.float32)
        except NotImplementedError:  # binary_compressed: open3d reads it
            pass
    import open3d as o3d

    return np.asarray(o3d.io.read_point_cloud(str(path)).points, dtype=np.float32)


def map_file(run_dir: Path) -> Path | None:
    """The run's map file (map.pcd or map.ply), or None."""
    for name in ("map.pcd", "map.ply"):
        if (run_dir / name).is_file():
            return run_dir / name
    return None


def loop_pairs(pipeline: Any) -> list[tuple[int, int]]:
    """Keyframe ids of every loop edge in a finished pipeline's graph (a verified loop that
    a consistency check still held back is not one: metrics.json's ``loops_closed``)."""
    return [(int(a), int(b)) for a, b in pipeline.state.loop_pairs]


def loop_positions(pipeline: Any) -> list[tuple[np.ndarray, np.ndarray]]:
    """Optimised positions (3,) of the two keyframes of every loop edge in the graph."""
    est = pipeline.state.estimates
    return [
        (est[a][:3, 3].copy(), est[b][:3, 3].copy())
        for a, b in loop_pairs(pipeline)
        if a in est and b in est
    ]


def _edges(poses: dict[int, np.ndarray], pairs: Sequence[tuple[int, int]]) -> np.ndarray:
    segs = [(poses[a][:2, 3], poses[b][:2, 3]) for a, b in pairs if a in poses and b in poses]
    return np.asarray(segs, dtype=float).reshape(-1, 2, 2)


def keyframe_maps(
    pipeline: Any, grid: Grid | None = None
) -> tuple[HeightRaster, HeightRaster, np.ndarray, np.ndarray]:
    """The keyframe clouds rasterised at their odometry poses and at their optimised poses
    on ``grid`` (default: around both trajectories), and the odometry / optimised positions
    of every frame (N, 2)."""
    st = pipeline.state
    odom_xy = np.stack(st.odom_poses)[:, :2, 3]
    opt_xy = st.trajectory()[:, :2, 3]
    if grid is None:  # framed by the trajectories and a sample of both maps
        sample = [
            np.asarray(kf.cloud[::50], dtype=float) @ T[:3, :3].T + T[:3, 3]
            for kf in st.keyframes
            for T in (kf.pose_odom, st.estimates.get(kf.id, kf.pose_odom))
        ]
        grid = Grid.around(np.vstack([odom_xy, opt_xy]), points=np.vstack(sample))
    before, after = HeightRaster(grid), HeightRaster(grid)
    for kf in st.keyframes:
        cloud = np.asarray(kf.cloud, dtype=float)
        for raster, T in ((before, kf.pose_odom), (after, st.estimates.get(kf.id, kf.pose_odom))):
            raster.add(cloud @ T[:3, :3].T + T[:3, 3])
    return before, after, odom_xy, opt_xy


def zoom_grid(pipeline: Any, pairs: Sequence[tuple[int, int]], half: float = ZOOM_HALF) -> Grid:
    """A fine grid (``half`` m around) on the loop keyframe that loop closure moved most: a
    revisit, where the odometry map shows the two passes apart."""
    st = pipeline.state
    kfs = {kf.id: kf for kf in st.keyframes}
    ids = [k for pair in pairs for k in pair if k in kfs and k in st.estimates]
    moved = [np.linalg.norm(kfs[k].pose_odom[:2, 3] - st.estimates[k][:2, 3]) for k in ids]
    centre = st.estimates[ids[int(np.argmax(moved))]][:2, 3]
    return Grid.around(centre[None, :], margin=half, pixels=int(2 * half / ZOOM_CELL))


def loop_map_figure(pipeline: Any):
    """:func:`before_after_figure` of a finished pipeline (the whole map and a zoom on the
    revisit loop closure moved most), or None without accepted loops."""
    pairs = loop_pairs(pipeline)
    st = pipeline.state
    if not pairs or not st.keyframes:
        return None
    before, after, odom_xy, opt_xy = keyframe_maps(pipeline)
    g = before.grid  # the zoom: a fifth of the map's side (small rooms), at most 40 m
    half = min(ZOOM_HALF, max(3.0, 0.1 * g.cell * max(g.nx, g.ny)))
    zoom_before, zoom_after, _, _ = keyframe_maps(pipeline, zoom_grid(pipeline, pairs, half))
    odom_kf = {kf.id: kf.pose_odom for kf in st.keyframes}
    rows = [(before, after, "Map"), (zoom_before, zoom_after, f"Zoom ({2 * half:.0f} m)")]
    return before_after_figure(
        rows, odom_xy, opt_xy, _edges(odom_kf, pairs), _edges(st.estimates, pairs)
    )


def pgm_png(pgm: Path, png: Path) -> Path:
    """The occupancy image ``pgm`` (map_server's P5) as a grey PNG, pixel for pixel."""
    import matplotlib.pyplot as plt

    from slam.io.grid_map import read_pgm

    png.parent.mkdir(parents=True, exist_ok=True)
    grey = read_pgm(pgm)
    plt.imsave(png, np.repeat(grey[:, :, None], 3, axis=2), format="png")  # RGB: no colour map
    return png


def grid_figure(pgm: Path, trajectory_xy: np.ndarray):
    """A 2D run's occupancy grid (``map.pgm`` placed by its ``map.yaml``: resolution and
    origin, m) with the trajectory on top, axes in metres."""
    import matplotlib.pyplot as plt

    from slam.io.grid_map import read_pgm

    meta = {}
    for line in pgm.with_suffix(".yaml").read_text().splitlines():
        key, _, value = line.partition(":")
        meta[key.strip()] = value.strip()
    res = float(meta["resolution"])
    ox, oy = (float(v) for v in meta["origin"].strip("[]").split(",")[:2])
    grey = read_pgm(pgm)
    rows, cols = grey.shape
    extent = (ox, ox + cols * res, oy, oy + rows * res)
    fig = plt.figure(figsize=(10.0, 9.0), dpi=DPI, layout="constrained")
    ax = fig.add_subplot(111)
    ax.imshow(grey, cmap="gray", vmin=0, vmax=255, extent=extent, interpolation="nearest")
    ax.plot(trajectory_xy[:, 0], trajectory_xy[:, 1], "-", color="tab:blue", lw=1.0,
            label="trajectory (optimised)")  # fmt: skip
    pad = 2.0
    (x0, y0), (x1, y1) = trajectory_xy.min(axis=0) - pad, trajectory_xy.max(axis=0) + pad
    occupied = np.argwhere(grey < 100)  # walls: (row, col)
    if len(occupied):
        xs = ox + (occupied[:, 1] + 0.5) * res
        ys = oy + (rows - occupied[:, 0] - 0.5) * res
        x0, x1 = min(x0, xs.min() - pad), max(x1, xs.max() + pad)
        y0, y1 = min(y0, ys.min() - pad), max(y1, ys.max() + pad)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("$x$ (m)")
    ax.set_ylabel("$y$ (m)")
    ax.set_title(f"{pgm.name}: occupancy grid at {100 * res:.0f} cm (black: walls, grey: unseen)")
    ax.legend(loc="upper right", frameon=True)
    return fig


def map_images(run_dir: Path, pipeline: Any = None, plots: Path | None = None) -> list[Path]:
    """Write the map pictures of a finished run into ``plots`` (default ``run_dir/plots``):
    the map file under the optimised trajectory (a 2D run: its occupancy grid in metres),
    the map before / after loop closure (when ``pipeline`` is given and closed loops) and
    ``map.pgm`` as it is. Returns the PNGs; a
    picture that cannot be drawn is logged and left out (a picture never loses a run)."""
    from slam.io.trajectory import read_tum

    run_dir = Path(run_dir)
    plots = Path(plots) if plots is not None else run_dir / "plots"
    out: list[Path] = []
    mp, traj = map_file(run_dir), run_dir / "trajectory.tum"
    try:
        pgm = run_dir / "map.pgm"
        if pgm.is_file() and pgm.with_suffix(".yaml").is_file() and traj.is_file():
            _, poses = read_tum(traj)  # a 2D run: its map is the grid, not heights
            out.append(save_png(grid_figure(pgm, poses[:, :2, 3]), plots / MAP_PNG))
        elif mp is not None and traj.is_file():
            _, poses = read_tum(traj)
            fig = birdseye_figure(read_map_points(mp), poses[:, :2, 3], title=mp.name)
            out.append(save_png(fig, plots / MAP_PNG))
        if pipeline is not None:
            fig = loop_map_figure(pipeline)
            if fig is not None:
                out.append(save_png(fig, plots / MAP_LOOPS_PNG))
        if (run_dir / "map.pgm").is_file():
            out.append(pgm_png(run_dir / "map.pgm", plots / MAP_PGM_PNG))
    except (InputError, ValueError, OSError) as exc:
        log.warning("map picture not drawn: %s", exc)
    return out
