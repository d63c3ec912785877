"""Simulate a drive through a scene and write it as a real bag plus TUM ground truth.

Output folder ``out``: the bag (``<scene>.bag`` for ROS1, a ``<scene>/`` ROS2 folder for
ros2/mcap), ``ground_truth.tum`` (T_world_sensor at each scan's header stamp = sweep
start) and ``sim.json`` (scene, model, seed, hints such as the loop-closure radius).
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from slam.errors import InputError
from slam.io.trajectory import read_tum, write_tum
from slam.sim.lidar import LidarModel, ScanTruth, simulate_scan_truth
from slam.sim.scene import Scene
from slam.sim.scenes import SCENES, scene_sensor
from slam.types import Scan

STAMP0 = 1_700_000_000.0  # header stamp of the first sweep (s since the epoch)
TOPIC = "/velodyne_points"
FRAME_ID = "velodyne"
GT_NAME = "ground_truth.tum"
META_NAME = "sim.json"


@dataclass
class SimResult:
    """Where a simulated sequence lives. ``bag`` is a file (ros1) or a folder (ros2/mcap)."""

    bag: Path
    ground_truth: Path
    frames: int
    scene: str = ""
    fmt: str = "ros1"
    seed: int = 0
    topic: str = TOPIC
    meta: dict[str, Any] = dataclasses.field(default_factory=dict)

    def read_ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        """stamps (N,) s and poses (N,4,4) T_world_sensor."""
        return read_tum(self.ground_truth)


def make_scene(scene: str, *, seed: int = 0, pedestrians: bool = True) -> Scene:
    """Build a named scene; InputError lists the valid names."""
    if scene not in SCENES:
        raise InputError(f"unknown scene {scene!r}; choose one of {sorted(SCENES)}")
    return SCENES[scene](seed, pedestrians=pedestrians)


def effective_model(scene: Scene | str, model: LidarModel | None = None) -> LidarModel:
    """The LiDAR model a scene (object or name) is simulated with: ``model`` if given, else
    the scene's own sensor (e.g. the realistic VLP-16 of ``park``), else the default."""
    if model is not None:
        return model
    if isinstance(scene, str):
        return scene_sensor(scene)
    return getattr(scene, "sensor", None) or LidarModel()


def full_frames(scene: Scene, model: LidarModel) -> int:
    """Number of complete sweeps within the scene's drive."""
    return int(np.floor((scene.duration - model.period) / model.period + 1e-9)) + 1


def frame_stamps(n: int, model: LidarModel) -> np.ndarray:
    """(n,) header stamps (s): sweep starts at the sensor rate from STAMP0."""
    return STAMP0 + np.arange(n) * model.period


def iter_scans(
    scene: Scene,
    frames: int,
    *,
    seed: int = 0,
    model: LidarModel | None = None,
    with_truth: bool = False,
) -> Iterator[Scan] | Iterator[tuple[Scan, ScanTruth]]:
    """Yield the ``frames`` scans of a drive (deterministic for a seed); with ``with_truth``
    yield (Scan, ScanTruth) pairs. model: default the scene's sensor (see
    :func:`effective_model`)."""
    model = effective_model(scene, model)
    rng = np.random.default_rng([seed, 7])

    def pose_at(times: np.ndarray) -> np.ndarray:
        return scene.pose_at(np.asarray(times) - STAMP0)

    for i, stamp in enumerate(frame_stamps(frames, model)):
        scan, truth = simulate_scan_truth(
            scene, pose_at, float(stamp), model, rng, time_offset=STAMP0
        )
        scan.index = i
        yield (scan, truth) if with_truth else scan


def bag_path(out: Path, scene: str, fmt: str) -> Path:
    return out / (f"{scene}.bag" if fmt == "ros1" else scene)


def simulate(
    scene: str,
    out: Path,
    *,
    frames: int | None = None,
    fmt: str = "ros1",
    seed: int = 0,
    pedestrians: bool = True,
    model: LidarModel | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> SimResult:
    """Simulate ``scene`` into the folder ``out``; ``frames`` truncates the drive.

    model: the LiDAR model, default the scene's own (:func:`effective_model`).
    progress(done, total) is called after each frame. Overwrites an earlier bag there.
    """
    from slam.io.bag_writer import FORMATS, write_pointcloud_bag

    if fmt not in FORMATS:
        raise InputError(f"unknown bag format {fmt!r}; choose one of {list(FORMATS)}")
    world = make_scene(scene, seed=seed, pedestrians=pedestrians)
    model = effective_model(world, model)
    total = full_frames(world, model)
    if frames is None:
        frames = total
    if not 1 <= frames <= total:
        raise InputError(f"scene {scene!r} has {total} frames; frames={frames} is out of range")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    bag = bag_path(out, scene, fmt)

    def scans() -> Iterator[Scan]:
        for i, scan in enumerate(iter_scans(world, frames, seed=seed, model=model)):
            yield scan
            if progress is not None:
                progress(i + 1, frames)

    write_pointcloud_bag(
        bag, scans(), topic=TOPIC, frame_id=FRAME_ID, fmt=fmt, layout="velodyne", overwrite=True
    )
    stamps = frame_stamps(frames, model)
    gt = out / GT_NAME
    write_tum(gt, stamps, world.pose_at(stamps - STAMP0))
    meta = {
        "scene": scene,
        "description": world.description,
        "frames": frames,
        "full_frames": total,
        "seed": seed,
        "fmt": fmt,
        "pedestrians": pedestrians,
        "topic": TOPIC,
        "frame_id": FRAME_ID,
        "stamp0": STAMP0,
        "bag": bag.name,
        "ground_truth": GT_NAME,
        "loop_max_radius": world.loop_max_radius,
        "revisit_radius": world.revisit_radius,
        "lap_length_m": world.trajectory.loop_length,
        "sensor_height_m": world.trajectory.height,
        "model": dataclasses.asdict(model),
    }
    (out / META_NAME).write_text(json.dumps(meta, indent=2))
    return SimResult(bag, gt, frames, scene, fmt, seed, TOPIC, meta)


def load_result(folder: Path) -> SimResult:
    """The SimResult of a folder written by :func:`simulate`."""
    folder = Path(folder)
    meta_path = folder / META_NAME
    if not meta_path.is_file():
        raise InputError(f"{folder} holds no simulated sequence ({META_NAME} missing)")
    meta = json.loads(meta_path.read_text())
    return SimResult(
        folder / meta["bag"],
        folder / meta["ground_truth"],
        int(meta["frames"]),
        meta["scene"],
        meta["fmt"],
        int(meta["seed"]),
        meta["topic"],
        meta,
    )
