"""The ground truth of a run: read and checked before the first scan is processed, and
put in the run's sensor frame when the input knows the convention of its poses file.

KITTI odometry poses (``poses.txt``, 12 numbers per line) are left-camera poses; the LiDAR
trajectory a run writes is compared with T_velo0_velo = Tr^-1 P Tr, ``Tr`` from the
sequence's calib.txt (``KittiSource.camera_to_lidar``). Without that conversion APE
positions agree to the lever arm, but RPE compares camera with LiDAR motion (metres off).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from slam.eval.metrics import EvalOptions, EvalResult, evaluate_named, read_for_eval


@dataclass
class GroundTruth:
    """Reference poses of a run. stamps: s, None = paired with the estimate by index;
    poses: (N,4,4) in the frame of the run's trajectory when ``notes`` say so; notes: how
    they were taken (one line); warnings: why they may not fit the run."""

    path: Path
    stamps: np.ndarray | None
    poses: np.ndarray
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def read_ground_truth(path: str | Path, source: Any = None) -> GroundTruth:
    """Read and check a TUM or KITTI ground-truth file (InputError naming the file and
    line of what is wrong) for a run on ``source`` (``slam.io.source.open_source``).

    Stamp-less (KITTI) poses for a KITTI sequence are converted from the left camera to
    the LiDAR frame (or a warning says why not), and take the scans' stamps when there is
    one pose per scan, so that a window (--start, --max-frames) or a skipped file still
    pairs each pose with its scan.
    """
    path = Path(path)
    stamps, poses = read_for_eval(path)
    truth = GroundTruth(path, stamps, poses)
    to_lidar = getattr(source, "camera_to_lidar", None)
    if stamps is not None or to_lidar is None:
        return truth
    how = []
    lidar = to_lidar(poses)
    if lidar is None:
        truth.warnings.append(
            f"{path}: KITTI poses are of the left camera, and there is no "
            f"{source.calib_file} with the LiDAR transform Tr to convert them: RPE and "
            "rotation errors compare camera with LiDAR motion (metres off); put the "
            "sequence's calib.txt there"
        )
    else:
        truth.poses = lidar
        how.append(f"KITTI camera poses taken to the LiDAR frame (Tr of {source.calib_file})")
    if len(source.stamps) == len(poses):
        truth.stamps = np.asarray(source.stamps, dtype=float).copy()
        how.append("paired with the scans by their stamps")
    if how:
        truth.notes.append(f"ground truth {path}: " + ", ".join(how))
    return truth


def kitti_truth_in_lidar(truth: GroundTruth, calib: str | Path | None = None) -> GroundTruth:
    """``slam eval`` of a LiDAR trajectory against stamp-less (KITTI) camera poses: taken to
    the LiDAR frame with the ``Tr`` of ``calib`` (default: a calib.txt beside the poses
    file), else a warning. Poses with stamps (TUM) are returned as they are."""
    from slam.errors import InputError
    from slam.io.kitti import camera_poses_to_lidar, read_calib_tr

    if truth.stamps is not None:
        return truth
    given = calib is not None
    calib = Path(calib) if given else truth.path.parent / "calib.txt"
    if not calib.is_file():
        if given:
            raise InputError(f"calibration file not found: {calib}")
        truth.warnings.append(
            f"{truth.path}: KITTI poses are of the left camera; with no {calib} (or --calib) "
            "RPE and rotation errors compare camera with LiDAR motion (metres off)"
        )
        return truth
    tr = read_calib_tr(calib)
    if tr is None:
        raise InputError(f"{calib} has no 'Tr:' line (the LiDAR-to-camera transform)")
    truth.poses = camera_poses_to_lidar(truth.poses, tr)
    truth.notes.append(
        f"ground truth {truth.path}: KITTI camera poses taken to the LiDAR frame (Tr of {calib})"
    )
    return truth


def evaluate_truth(
    est_path: str | Path, truth: GroundTruth, options: EvalOptions | None = None
) -> EvalResult:
    """APE/RPE of a trajectory file against ground truth read by ``read_ground_truth``;
    its notes and warnings lead the result's notes."""
    est_stamps, est_poses = read_for_eval(est_path)
    result = evaluate_named(
        (est_stamps, est_poses, str(est_path)),
        (truth.stamps, truth.poses, str(truth.path)),
        options,
    )
    result.notes[:0] = [*truth.notes, *truth.warnings]
    return result
