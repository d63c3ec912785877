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
from slam.sim.registry import SCENES, scene_sensor
from slam.sim.scene import Scene
from slam.sim.sensors import DEFAULT_SENSOR, SensorSpec, driver_order, get_sensor
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

    @property
    def sensor(self) -> str:
        """Name of the simulated sensor (:data:`slam.sim.sensors.SENSORS`)."""
        return str(self.meta.get("sensor", DEFAULT_SENSOR))

    def read_ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        """stamps (N,) s and poses (N,4,4) T_world_sensor."""
        return read_tum(self.ground_truth)


def model_dict(model: LidarModel) -> dict[str, Any]:
    """The model's fields for sim.json and cache keys; an unset elevation table is left out,
    so that the older sequences keep their keys' contents and their sim.json."""
    values = dataclasses.asdict(model)
    if values.get("elevations_deg") is None:
        values.pop("elevations_deg", None)
    return values


def make_scene(scene: str, *, seed: int = 0, pedestrians: bool = True) -> Scene:
    """Build a named scene; InputError lists the valid names."""
    if scene not in SCENES:
        raise InputError(f"unknown scene {scene!r}; choose one of {sorted(SCENES)}")
    return SCENES[scene].load()(seed, pedestrians=pedestrians)


def effective_model(
    scene: Scene | str, model: LidarModel | None = None, sensor: str = DEFAULT_SENSOR
) -> LidarModel:
    """The LiDAR model a scene (object or name) is simulated with: ``model`` if given, else
    the named ``sensor`` (:mod:`slam.sim.sensors`) as the scene uses it: for the default
    VLP-16 the scene's own model (e.g. the realistic one of ``park``), for another sensor
    its realistic variant when the scene's own model is realistic, else its ideal one."""
    if model is not None:
        return model
    if isinstance(scene, str):
        return scene_sensor(scene, sensor)
    own = getattr(scene, "sensor", None)
    if sensor == DEFAULT_SENSOR:
        return own or LidarModel()
    return get_sensor(sensor).model(realistic=own is not None and own.has_calibration_error)


def _driver_convention(
    scan: Scan, truth: ScanTruth, beams: int, spec: SensorSpec
) -> tuple[Scan, ScanTruth]:
    """The sweep in the point order and ring numbering its driver publishes."""
    if not (spec.row_major or spec.ring_top_first):
        return scan, truth
    order, ring = driver_order(scan.ring.astype(np.int64), truth.column, beams, spec)
    out = scan.select(order)
    out.ring = ring
    per_point = {
        f.name: getattr(truth, f.name)[order]
        for f in dataclasses.fields(truth)
        if f.name != "T_world_sensor_columns" and getattr(truth, f.name) is not None
    }
    return out, dataclasses.replace(truth, **per_point)


def _compensated(scan: Scan, truth: ScanTruth) -> Scan:
    """The sweep with every point moved from the sensor frame at its firing time to the
    sensor frame at the sweep start (KITTI's motion compensation, with the true motion)."""
    T = truth.T_world_sensor_columns
    T_start_columns = np.linalg.inv(T[0]) @ T  # (columns, 4, 4)
    Tc = T_start_columns[truth.column]
    moved = np.einsum("nij,nj->ni", Tc[:, :3, :3], scan.xyz) + Tc[:, :3, 3]
    return dataclasses.replace(scan, xyz=moved, time=None)  # no firing time left to deskew


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
    sensor: str = DEFAULT_SENSOR,
) -> Iterator[Scan] | Iterator[tuple[Scan, ScanTruth]]:
    """Yield the ``frames`` scans of a drive (deterministic for a seed); with ``with_truth``
    yield (Scan, ScanTruth) pairs. sensor: a name of :data:`slam.sim.sensors.SENSORS`
    (its driver's point order and ring numbering); model: default the scene's version of
    that sensor (see :func:`effective_model`)."""
    spec = get_sensor(sensor)
    model = effective_model(scene, model, sensor)
    rng = np.random.default_rng([seed, 7])
    for i, stamp in enumerate(frame_stamps(frames, model)):
        scan, truth = published_scan(scene, float(stamp), model, spec, rng)
        scan.index = i
        yield (scan, truth) if with_truth else scan


def published_scan(
    scene: Scene, stamp: float, model: LidarModel, spec: SensorSpec, rng: np.random.Generator
) -> tuple[Scan, ScanTruth]:
    """The sweep at header ``stamp`` (s) as ``spec``'s driver publishes it (point order,
    ring numbering, motion compensation), with its truth."""
    scan, truth = simulate_scan_truth(
        scene,
        lambda times: scene.pose_at(np.asarray(times) - STAMP0),
        stamp,
        model,
        rng,
        time_offset=STAMP0,
    )
    scan, truth = _driver_convention(scan, truth, model.beams, spec)
    if spec.motion_compensated:
        scan = _compensated(scan, truth)
    return scan, truth


def bag_path(out: Path, scene: str, fmt: str) -> Path:
    return out / (f"{scene}.bag" if fmt == "ros1" else scene)


def _reported(
    scans: Iterator[Scan], frames: int, progress: Callable[[int, int], None] | None
) -> Iterator[Scan]:
    """The scans, calling progress(done, frames) after each one is consumed."""
    for i, scan in enumerate(scans):
        yield scan
        if progress is not None:
            progress(i + 1, frames)


def _sim_meta(
    scene: str,
    world: Scene,
    model: LidarModel,
    spec: SensorSpec,
    frames: int,
    total: int,
    seed: int,
    fmt: str,
    pedestrians: bool,
    bag: Path,
    sensor: str,
) -> dict[str, Any]:
    """The sim.json of a simulated sequence: what was simulated, with which sensor and model,
    and the scene's loop radii (m), lap length (m) and sensor height (m)."""
    meta = {
        "scene": scene,
        "description": world.description,
        "frames": frames,
        "full_frames": total,
        "seed": seed,
        "fmt": fmt,
        "pedestrians": pedestrians,
        "topic": spec.topic,
        "frame_id": spec.frame_id,
        "stamp0": STAMP0,
        "bag": bag.name,
        "ground_truth": GT_NAME,
        "loop_max_radius": world.loop_max_radius,
        "revisit_radius": world.revisit_radius,
        "lap_length_m": world.trajectory.loop_length,
        "sensor_height_m": world.trajectory.height,
        "model": model_dict(model),
    }
    if sensor != DEFAULT_SENSOR:  # older sequences' sim.json stay as they were
        meta.update(sensor=sensor, layout=spec.layout, sensor_description=spec.description)
    return meta


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
    sensor: str = DEFAULT_SENSOR,
) -> SimResult:
    """Simulate ``scene`` into the folder ``out``; ``frames`` truncates the drive.

    sensor: a name of :data:`slam.sim.sensors.SENSORS` ("vlp16", "hdl32", "hdl64",
    "os128"): its optics and its driver's layout, topic, frame and point order.
    model: the LiDAR model, default the scene's version of ``sensor``
    (:func:`effective_model`). progress(done, total) is called after each frame.
    Overwrites an earlier bag there.
    """
    from slam.io.bag_writer import FORMATS, write_pointcloud_bag

    if fmt not in FORMATS:
        raise InputError(f"unknown bag format {fmt!r}; choose one of {list(FORMATS)}")
    spec = get_sensor(sensor)
    world = make_scene(scene, seed=seed, pedestrians=pedestrians)
    model = effective_model(world, model, sensor)
    total = full_frames(world, model)
    if frames is None:
        frames = total
    if not 1 <= frames <= total:
        raise InputError(f"scene {scene!r} has {total} frames; frames={frames} is out of range")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    bag = bag_path(out, scene, fmt)

    scans = iter_scans(world, frames, seed=seed, model=model, sensor=sensor)
    write_pointcloud_bag(
        bag,
        _reported(scans, frames, progress),
        topic=spec.topic,
        frame_id=spec.frame_id,
        fmt=fmt,
        layout=spec.layout,
        overwrite=True,
    )
    stamps = frame_stamps(frames, model)
    gt = out / GT_NAME
    write_tum(gt, stamps, world.pose_at(stamps - STAMP0))
    meta = _sim_meta(scene, world, model, spec, frames, total, seed, fmt, pedestrians, bag, sensor)
    (out / META_NAME).write_text(json.dumps(meta, indent=2))
    return SimResult(bag, gt, frames, scene, fmt, seed, spec.topic, meta)


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
