"""The named scenes of the simulator: where each is built, which source files shape its
data (the cache key of its sequences covers exactly those, see :mod:`slam.sim.cache`) and
which LiDAR model it is simulated with by default.

A new scene lives in its own module and gets one :class:`SceneEntry` here; adding it does
not change the cache key of any other scene. This module holds names only, no geometry, so
it is not part of any key.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from slam.sim.sensors import DEFAULT_SENSOR, get_sensor

if TYPE_CHECKING:
    from slam.sim.lidar import LidarModel
    from slam.sim.scene import Scene

# Files of slam/sim every 3D sequence depends on (ray casting, meshes, scans, sensor models,
# trajectories, the writer of sequences).
CORE_SOURCES = (
    "geometry.py",
    "lidar.py",
    "scene.py",
    "sensors.py",
    "simulate.py",
    "trajectory.py",
)


@dataclass(frozen=True)
class SceneEntry:
    """builder: ``"module:function"`` called as ``f(seed, pedestrians=...) -> Scene``;
    sources: the slam/sim files (beyond :data:`CORE_SOURCES`) its geometry comes from;
    realistic: simulated with the realism error sources of ``LidarModel.realistic``
    (calibration, range-growing noise, mixed pixels) whatever the sensor."""

    builder: str
    sources: tuple[str, ...]
    realistic: bool = False
    description: str = ""

    def load(self) -> Callable[..., Scene]:
        module, func = self.builder.split(":")
        return getattr(importlib.import_module(module), func)


SCENES: dict[str, SceneEntry] = {
    "corridor": SceneEntry("slam.sim.scenes:corridor", ("scenes.py",)),
    "plaza": SceneEntry("slam.sim.scenes:plaza", ("scenes.py",)),
    "park": SceneEntry("slam.sim.park:park", ("park.py", "scenes.py"), realistic=True),
    "urban": SceneEntry("slam.sim.urban:urban", ("urban.py", "scenes.py"), realistic=True),
    "street": SceneEntry(
        "slam.sim.street:street", ("street.py", "urban.py", "scenes.py"), realistic=True
    ),
    "highway": SceneEntry("slam.sim.highway:highway", ("highway.py", "urban.py"), realistic=True),
    "building": SceneEntry("slam.sim.building:building", ("building.py",), realistic=True),
    "building_loop": SceneEntry(
        "slam.sim.building:building_loop", ("building.py",), realistic=True
    ),
    "building_return": SceneEntry(
        "slam.sim.building_return:building_return",
        ("building.py", "building_return.py"),
        realistic=True,
    ),
    "building_loop_return": SceneEntry(
        "slam.sim.building_return:building_loop_return",
        ("building.py", "building_return.py"),
        realistic=True,
    ),
}


def scene_sources(name: str) -> tuple[str, ...]:
    """The slam/sim files whose code shapes the named scene's sequences."""
    return CORE_SOURCES + SCENES[name].sources


def scene_sensor(name: str, sensor: str = DEFAULT_SENSOR) -> LidarModel:
    """The LiDAR model a scene is simulated with by default: the named ``sensor`` (see
    :mod:`slam.sim.sensors`), with realistic errors for the scenes flagged ``realistic``
    (park, urban), ideal otherwise (for the VLP-16: ``LidarModel.realistic()`` /
    ``LidarModel()``)."""
    entry = SCENES.get(name)
    return get_sensor(sensor).model(realistic=entry is not None and entry.realistic)
