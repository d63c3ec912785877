"""A cache of simulated sequences, so the demo and the tests generate each one only once.

Location: ``$SLAM_CACHE/sim`` if SLAM_CACHE is set, else ``~/.cache/pyslam-graph/sim``.
A sequence lives in ``<scene>-<frames|full>-<seed>-<hash>``; the hash covers the
arguments, the sensor model, :data:`SIM_VERSION` and the source files that shape that
scene (:func:`slam.sim.registry.scene_sources`), so any change to them regenerates it and
a new scene or a change to another scene's module does not; stale sequences are pruned
when a new one is written. Written into a
temporary folder and renamed: readers never see a half-written sequence, and concurrent
writers are safe.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from slam.errors import InputError
from slam.sim.lidar import LidarModel
from slam.sim.registry import SCENES, scene_sources
from slam.sim.sensors import DEFAULT_SENSOR, get_sensor
from slam.sim.simulate import (
    META_NAME,
    SimResult,
    effective_model,
    load_result,
    model_dict,
    simulate,
)

SIM_VERSION = 1  # bump when the simulated data change meaning


def cache_root() -> Path:
    """Folder holding cached sequences."""
    env = os.environ.get("SLAM_CACHE")
    base = Path(env).expanduser() if env else Path.home() / ".cache" / "pyslam-graph"
    return base / "sim"


_STAMP_NAME = "cache.json"


def _code_digest(scene: str) -> str:
    return f"{SIM_VERSION}-{_source_digest(scene)}"


def prune_stale(root: Path) -> list[Path]:
    """Remove cached sequences made by another simulator version or another source of
    their own scene, and those of the old cache layout (no scene in the stamp); returns
    them. Sequences of other scenes whose sources did not change are kept, and so are
    those of scenes this process does not know (written by newer code running beside)."""
    removed = []
    for folder in root.iterdir():
        stamp = folder / _STAMP_NAME
        if folder.name.startswith(".") or not stamp.is_file():
            continue
        try:
            meta = json.loads(stamp.read_text())
        except (OSError, ValueError):
            meta = {}
        scene = meta.get("scene")
        if scene is not None and scene not in SCENES:
            continue  # a scene registered by newer code than this process runs: not ours
        if scene is None or meta.get("digest") != _code_digest(scene):
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
    return removed


def _source_digest(scene: str) -> str:
    """sha1 of the slam/sim files that shape ``scene`` (:func:`scene_sources`)."""
    h = hashlib.sha1()
    here = Path(__file__).parent
    for name in sorted(scene_sources(scene)):
        h.update(name.encode())
        h.update((here / name).read_bytes())
    return h.hexdigest()


def sequence_key(
    scene: str,
    *,
    frames: int | None,
    fmt: str,
    seed: int,
    pedestrians: bool,
    model: LidarModel | None = None,
    sensor: str = DEFAULT_SENSOR,
) -> str:
    """Folder name of a sequence in the cache; the key holds the effective sensor model
    (the scene's version of ``sensor`` when ``model`` is None). Sensors other than the
    default VLP-16 are named in the folder and the key (their driver layout differs)."""
    get_sensor(sensor)
    if scene not in SCENES:
        raise InputError(f"unknown scene {scene!r}; choose one of {sorted(SCENES)}")
    spec = {
        "version": SIM_VERSION,
        "source": _source_digest(scene),
        "scene": scene,
        "frames": frames,
        "fmt": fmt,
        "seed": seed,
        "pedestrians": pedestrians,
        "model": model_dict(effective_model(scene, model, sensor)),
    }
    name = scene
    if sensor != DEFAULT_SENSOR:
        spec["sensor"] = sensor
        name = f"{scene}-{sensor}"
    digest = hashlib.sha1(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:10]
    return f"{name}-{'full' if frames is None else frames}-{seed}-{digest}"


def ensure_sequence(
    scene: str,
    *,
    frames: int | None = None,
    fmt: str = "ros1",
    seed: int = 0,
    pedestrians: bool = True,
    cache_dir: Path | None = None,
    model: LidarModel | None = None,
    sensor: str = DEFAULT_SENSOR,
    progress: Callable[[int, int], None] | None = None,
) -> SimResult:
    """The cached sequence for these arguments, simulating it first when missing.

    sensor: "vlp16" (default), "hdl32", "hdl64" or "os128" (:mod:`slam.sim.sensors`);
    progress(done, total) as in :func:`simulate` (only called when simulating)."""
    root = Path(cache_dir) if cache_dir is not None else cache_root()
    key = sequence_key(
        scene,
        frames=frames,
        fmt=fmt,
        seed=seed,
        pedestrians=pedestrians,
        model=model,
        sensor=sensor,
    )
    final = root / key
    if (final / META_NAME).is_file():
        return load_result(final)
    root.mkdir(parents=True, exist_ok=True)
    prune_stale(root)
    tmp = Path(tempfile.mkdtemp(prefix=f".{key}.", dir=root))
    try:
        os.chmod(tmp, 0o755)
        simulate(
            scene,
            tmp,
            frames=frames,
            fmt=fmt,
            seed=seed,
            pedestrians=pedestrians,
            model=model,
            sensor=sensor,
            progress=progress,
        )
        (tmp / _STAMP_NAME).write_text(json.dumps({"digest": _code_digest(scene), "scene": scene}))
        if final.exists() and not (final / META_NAME).is_file():
            shutil.rmtree(final, ignore_errors=True)  # a broken leftover
        try:
            os.rename(tmp, final)
        except OSError:
            if not (final / META_NAME).is_file():  # pragma: no cover - unexpected
                raise
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return load_result(final)
