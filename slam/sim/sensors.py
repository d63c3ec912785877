"""Named LiDAR models with their drivers' conventions: VLP-16, HDL-32E, HDL-64E, OS1-128.

A :class:`SensorSpec` pairs the optics (:class:`~slam.sim.lidar.LidarModel`: beams,
elevation table, columns, ranges) with what the driver publishes: the PointCloud2 layout
of :data:`slam.io.pointcloud2.LAYOUTS`, the topic and frame, the point order and the ring
numbering. The simulator then writes bags like the real recordings users bring:

- ``vlp16``: Velodyne VLP-16, 16 beams +-15 deg, 1800 columns at 10 Hz (0.2 deg);
  velodyne_pointcloud layout (x y z intensity ring time, 22 bytes), column-major firing
  order, ring 0 at the bottom. The default, bit-identical to the older simulator.
- ``hdl32``: Velodyne HDL-32E, 32 beams uniform from -30.67 to +10.67 deg (1.33 deg),
  2172 columns at 10 Hz (0.166 deg, ~69k rays: the datasheet's 695k points/s); velodyne
  layout with ring and time.
- ``hdl64``: Velodyne HDL-64E S2 as KITTI-converted bags have it (kitti2bag): 64 beams in
  two blocks, upper 32 from +2 to -8.33 deg (1/3 deg apart) and lower 32 from -8.87 to
  -24.9 deg (~1/2 deg), 2083 columns at 10 Hz (0.17 deg, ~133k rays); x y z intensity
  only (layout ``xyzi``, 16 bytes: no ring, no per-point time), points ordered scan line
  by scan line from the top beam down, as in the KITTI .bin files, and motion-compensated
  to the sweep start like KITTI's scans (the real KITTI-raw scans register best without
  any further deskewing).
- ``os128``: Ouster OS1-128, 128 beams uniform over +-22.5 deg (0.35 deg), 1024 columns
  at 10 Hz (~131k rays); ouster_ros layout (48-byte points, ``t`` uint32 ns from the scan
  start, ``ring`` uint16, ``range`` mm), row-major like the driver's organised cloud, ring
  0 = the TOP beam (Ouster numbers beams from the highest elevation down).

Each spec has an ideal variant (range noise and spurious returns only, like the default
:class:`LidarModel`) and a realistic one (per-beam calibration errors, range noise
growing with range, mixed pixels), chosen by the scene (see
:func:`slam.sim.registry.scene_sensor`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from slam.errors import InputError
from slam.sim.lidar import LidarModel

DEFAULT_SENSOR = "vlp16"


@dataclass(frozen=True)
class SensorSpec:
    """A named sensor: optics + driver conventions.

    layout: PointCloud2 layout name. topic / frame_id: where its driver publishes.
    row_major: points ordered ring by ring (each a full turn) instead of column by column.
    ring_top_first: ring 0 is the highest beam (Ouster) instead of the lowest (Velodyne).
    motion_compensated: the published points are expressed in the sensor frame at the sweep
    start (the header stamp), as KITTI publishes its scans, instead of at their firing time.
    ideal / realistic: build the LidarModel without / with the realism error sources.
    """

    name: str
    description: str
    layout: str
    topic: str
    frame_id: str
    ideal: Callable[[], LidarModel]
    realistic: Callable[[], LidarModel]
    row_major: bool = False
    ring_top_first: bool = False
    motion_compensated: bool = False

    def model(self, realistic: bool = False) -> LidarModel:
        """The sensor's LidarModel (a fresh object), with or without the realism errors."""
        return self.realistic() if realistic else self.ideal()


def hdl64_elevations() -> tuple[float, ...]:
    """(64,) ascending elevations (deg) of the HDL-64E S2 as in KITTI: the lower block of 32
    beams from -24.9 to -8.87 deg (~0.52 deg apart), the upper block from -8.33 to +2 deg
    (1/3 deg apart)."""
    lower = np.linspace(-24.9, -8.87, 32)
    upper = np.linspace(-8.33, 2.0, 32)
    return tuple(float(round(x, 4)) for x in np.concatenate([lower, upper]))


_HDL32 = dict(beams=32, fov_deg=(-30.67, 10.67), columns=2172, max_range=100.0, min_range=0.5)
_HDL64 = dict(
    beams=64,
    fov_deg=(-24.9, 2.0),
    columns=2083,
    max_range=120.0,
    min_range=0.9,
    elevations_deg=hdl64_elevations(),
)
_OS128 = dict(beams=128, fov_deg=(-22.5, 22.5), columns=1024, max_range=120.0, min_range=0.5)

SENSORS: dict[str, SensorSpec] = {
    "vlp16": SensorSpec(
        "vlp16",
        "Velodyne VLP-16: 16 beams +-15 deg, 1800 columns, ring + time",
        "velodyne",
        "/velodyne_points",
        "velodyne",
        LidarModel,
        LidarModel.realistic,
    ),
    "hdl32": SensorSpec(
        "hdl32",
        "Velodyne HDL-32E: 32 beams -30.67..+10.67 deg, 2172 columns, ring + time",
        "velodyne",
        "/velodyne_points",
        "velodyne",
        lambda: LidarModel(**_HDL32),
        # Datasheet accuracy +-2 cm: 1 cm + 0.2 mm/m (1-sigma).
        lambda: LidarModel.realistic(range_sigma=0.01, **_HDL32),
    ),
    "hdl64": SensorSpec(
        "hdl64",
        "Velodyne HDL-64E (KITTI): 64 beams +2..-24.9 deg in two blocks, 2083 columns, "
        "x y z intensity only",
        "xyzi",
        "/kitti/velo/pointcloud",
        "velo_link",
        lambda: LidarModel(**_HDL64),
        # Glennie & Lichti 2010: the factory calibration of an HDL-64E S2 leaves errors of
        # ~0.1-0.2 deg and a few cm per laser; range accuracy < 2 cm.
        lambda: LidarModel.realistic(
            range_sigma=0.012, calib_elevation_deg=0.12, calib_range_m=0.025, **_HDL64
        ),
        row_major=True,
        motion_compensated=True,
    ),
    "os128": SensorSpec(
        "os128",
        "Ouster OS1-128: 128 beams +-22.5 deg, 1024 columns, t in ns, 48-byte points",
        "ouster",
        "/ouster/points",
        "os_sensor",
        lambda: LidarModel(**_OS128),
        # OS1 precision 1.5-5 cm (1-sigma grows with range); one lens for all beams, so
        # smaller per-beam angle errors than a Velodyne's separately mounted lasers.
        lambda: LidarModel.realistic(
            range_sigma=0.015,
            range_sigma_per_m=0.0003,
            calib_elevation_deg=0.05,
            calib_azimuth_deg=0.05,
            calib_range_m=0.01,
            **_OS128,
        ),
        row_major=True,
        ring_top_first=True,
    ),
}


def get_sensor(name: str) -> SensorSpec:
    """The named sensor; InputError lists the valid names."""
    try:
        return SENSORS[name]
    except KeyError:
        raise InputError(f"unknown sensor {name!r}; choose one of {sorted(SENSORS)}") from None


def driver_order(ring: np.ndarray, column: np.ndarray, beams: int, spec: SensorSpec):
    """Point order and published ring numbers of a sweep under ``spec``'s driver
    conventions: (order (N,) index into the simulator's column-major points, ring (N,)
    int16 as published). ``ring`` (N,) 0 = bottom, ``column`` (N,) firing column."""
    published = (beams - 1 - ring) if spec.ring_top_first else ring
    if spec.row_major:
        top_down = beams - 1 - ring  # KITTI and Ouster rows go from the top beam down
        order = np.lexsort((column, top_down))
    else:
        order = np.arange(len(ring))
    return order, np.asarray(published[order], dtype=np.int16)
