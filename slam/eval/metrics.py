"""APE / RPE of an estimated trajectory against ground truth, computed by evo.

evo does association (``sync.associate_trajectories``), Umeyama alignment
(``PosePath3D.align``) and the metrics (``metrics.APE``/``metrics.RPE``) exactly as its
``evo_ape``/``evo_rpe`` tools do; this module only chains them and adds the KITTI devkit
drift (:mod:`slam.eval.kitti`). Only ``evo.core`` is imported: it never reads or writes
evo's settings in ``~/.evo`` and never opens a GUI.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
from evo import EvoException
from evo.core import lie_algebra as lie
from evo.core import metrics, sync
from evo.core.trajectory import PoseTrajectory3D

from slam.errors import ConfigError, InputError
from slam.eval.kitti import KITTI_LENGTHS, kitti_metric, kitti_metric_scaled
from slam.io.trajectory import check_rows, data_line_numbers, load_rows, tum_rows_to_poses

ALIGN_CHOICES = ("se3", "sim3", "origin", "none")
RPE_UNITS = ("m", "frames")
log = logging.getLogger(__name__)

STAT_KEYS = ("max", "mean", "median", "min", "rmse", "sse", "std")


@dataclass
class EvalOptions:
    """How to compare two trajectories.

    align: "se3" (evo ``-a``), "sim3" (``-as``), "origin" (``--align_origin``) or "none".
    n_align: align on the first N matched poses (-1: all). max_diff: association tolerance in
    seconds (evo ``--t_max_diff``). rpe_delta/rpe_unit: RPE pair spacing, in metres of path
    ("m", evo ``--delta_unit m``) or frames. kitti_lengths: devkit segment lengths in metres;
    when no segment fits the run, scaled lengths are used instead (``kitti["scaled"]``).
    """

    align: str = "se3"
    n_align: int = -1
    max_diff: float = 0.02
    rpe_delta: float = 1.0
    rpe_unit: str = "m"
    kitti_lengths: tuple[float, ...] = KITTI_LENGTHS
    kitti_step: int = 10

    def __post_init__(self) -> None:
        if self.align not in ALIGN_CHOICES:
            raise ConfigError(f"eval align must be one of {ALIGN_CHOICES}, got {self.align!r}")
        if self.rpe_unit not in RPE_UNITS:
            raise ConfigError(f"eval rpe_unit must be one of {RPE_UNITS}, got {self.rpe_unit!r}")
        if not self.rpe_delta > 0:
            raise ConfigError(f"eval rpe_delta must be > 0, got {self.rpe_delta}")
        if self.rpe_unit == "frames" and float(self.rpe_delta) != int(self.rpe_delta):
            raise ConfigError(f"eval rpe_delta must be whole frames, got {self.rpe_delta}")
        if not self.max_diff >= 0:
            raise ConfigError(f"eval max_diff must be >= 0 s, got {self.max_diff}")
        if self.n_align == 0 or self.n_align < -1:
            raise ConfigError(f"eval n_align must be -1 (all) or > 0, got {self.n_align}")
        self.kitti_lengths = tuple(float(x) for x in self.kitti_lengths)


@dataclass
class EvalResult:
    """Result of one comparison. Errors in metres and degrees.

    ``stamps``/``ape_errors``/``ape_rot_errors``: per matched pose (errors over time).
    ``est_poses``/``gt_poses``: matched poses, est already aligned (N,4,4).
    ``est_indices``: row of each matched pose in the input estimate.
    ``est_full``: every input estimate pose with the alignment applied (for loop plots).
    ``alignment``: the 4x4 Sim(3) applied to the estimate (identity when not aligned).
    ``rpe_*`` are ``None`` when the run is too short for one RPE pair.
    """

    ape_trans: dict
    ape_rot: dict
    rpe_trans: dict | None
    rpe_rot: dict | None
    kitti: dict | None
    n_matched: int
    n_est: int
    n_gt: int
    stamps: np.ndarray
    ape_errors: np.ndarray
    ape_rot_errors: np.ndarray
    est_poses: np.ndarray
    gt_poses: np.ndarray
    est_indices: np.ndarray
    est_full: np.ndarray
    alignment: np.ndarray
    scale: float
    path_length: float
    options: EvalOptions = field(default_factory=EvalOptions)
    notes: list[str] = field(default_factory=list)

    @property
    def errors_over_time(self) -> tuple[np.ndarray, np.ndarray]:
        """(stamps, translational APE per matched pose)."""
        return self.stamps, self.ape_errors

    def to_dict(self, arrays: bool = False) -> dict:
        """JSON-able summary; ``arrays=True`` adds stamps and per-pose APE."""
        out = {
            "ape_trans": self.ape_trans,
            "ape_rot": self.ape_rot,
            "rpe_trans": self.rpe_trans,
            "rpe_rot": self.rpe_rot,
            "kitti": self.kitti,
            "n_matched": self.n_matched,
            "n_est": self.n_est,
            "n_gt": self.n_gt,
            "path_length": self.path_length,
            "scale": self.scale,
            "alignment": self.alignment.tolist(),
            "units": {"ape_trans": "m", "ape_rot": "deg", "rpe_trans": "m", "rpe_rot": "deg"},
            "options": asdict(self.options),
            "notes": list(self.notes),
        }
        out["options"]["kitti_lengths"] = list(self.options.kitti_lengths)
        if arrays:
            out["stamps"] = self.stamps.tolist()
            out["ape_errors"] = self.ape_errors.tolist()
            out["ape_rot_errors"] = self.ape_rot_errors.tolist()
        return out


def _stats(metric: metrics.PE) -> dict:
    stats = metric.get_all_statistics()
    return {k: float(stats[k]) for k in STAT_KEYS}


def read_trajectory(path: str | Path) -> tuple[np.ndarray | None, np.ndarray]:
    """(stamps or None, (N,4,4) poses) from a TUM (8 columns) or KITTI (12 columns) file,
    in file order.

    InputError naming the file and line for a row that is no pose (a value not finite, a
    zero quaternion), and for TUM stamps that are all the same. ``read_for_eval`` also
    puts the poses in time order, as APE/RPE need them.
    """
    rows = _rows(Path(path))
    return (None, _kitti_poses(rows)) if rows.shape[1] == 12 else tum_rows_to_poses(rows)


def read_for_eval(path: str | Path) -> tuple[np.ndarray | None, np.ndarray]:
    """``read_trajectory`` with TUM poses in strictly increasing time, as evaluation needs
    them: stamps that go back are sorted (one warning: a CARMEN run's files keep the log's
    own stamps, a few out of order), a line repeated verbatim is dropped (one warning; evo
    would match either copy), one stamp with two different poses is an InputError naming
    both lines."""
    path = Path(path)
    rows = _rows(path)
    if rows.shape[1] == 12:
        return None, _kitti_poses(rows)
    return tum_rows_to_poses(_time_ordered(rows, path))


def _kitti_poses(rows: np.ndarray) -> np.ndarray:
    """(N,4,4) poses of (N,12) KITTI rows (3x4 row-major)."""
    poses = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    return poses


def _rows(path: Path) -> np.ndarray:
    """The checked rows of a TUM or KITTI trajectory file (see ``read_trajectory``)."""
    rows = load_rows(path, "a TUM or KITTI trajectory")
    if rows.shape[1] not in (8, 12):
        raise InputError(
            f"{path}: {rows.shape[1]} columns; expected 8 (TUM: stamp tx ty tz qx qy qz qw) "
            "or 12 (KITTI: 3x4 pose row-major)"
        )
    check_rows(rows, path)
    stamps = rows[:, 0]
    if rows.shape[1] == 8 and len(stamps) > 1 and np.all(stamps == stamps[0]):
        raise InputError(
            f"{path}: all {len(stamps)} poses have the same stamp {stamps[0]:.9g} s; a TUM "
            "trajectory needs one increasing stamp per pose (first column, seconds)"
        )
    return rows


def _time_ordered(rows: np.ndarray, path: Path) -> np.ndarray:
    """TUM rows sorted by stamp (stable), verbatim repeats dropped; a warning for each
    kind of repair, an InputError naming the lines of one stamp with two poses."""
    step = np.diff(rows[:, 0])
    if np.all(step > 0):
        return rows
    lines = data_line_numbers(path)
    if np.any(step < 0):
        first = int(np.flatnonzero(step < 0)[0]) + 1
        log.warning(
            "%s: %d stamp(s) go back in time (first: line %d); evaluated in time order",
            path, int(np.sum(step < 0)), lines[first],
        )  # fmt: skip
        order = np.argsort(rows[:, 0], kind="stable")
        rows, lines = rows[order], lines[order]
    same = np.diff(rows[:, 0]) == 0
    repeat = np.flatnonzero(same & np.all(rows[1:] == rows[:-1], axis=1)) + 1
    if repeat.size:
        log.warning(
            "%s: %d line(s) repeat another verbatim (first: line %d); dropped",
            path, repeat.size, lines[repeat[0]],
        )  # fmt: skip
        rows, lines = np.delete(rows, repeat, axis=0), np.delete(lines, repeat)
    twice = np.flatnonzero(np.diff(rows[:, 0]) == 0)
    if twice.size:
        i = twice[0] + 1
        raise InputError(
            f"{path}, line {lines[i]}: stamp {rows[i, 0]:.9f} is also the stamp of line "
            f"{lines[i - 1]}, with another pose ({twice.size} such stamp(s)); a TUM "
            "trajectory needs one pose per stamp"
        )
    return rows


def evaluate(
    est_path: str | Path, gt_path: str | Path, options: EvalOptions | None = None
) -> EvalResult:
    """Compare an estimate file with a ground-truth file (TUM or KITTI, by column count).

    TUM files are associated by time (``read_for_eval``); if either file is KITTI (no
    stamps) the poses are paired by index and both files must have the same number of
    poses.
    """
    est_stamps, est_poses = read_for_eval(est_path)
    gt_stamps, gt_poses = read_for_eval(gt_path)
    return evaluate_named(
        (est_stamps, est_poses, str(est_path)), (gt_stamps, gt_poses, str(gt_path)), options
    )


def evaluate_named(
    est: tuple[np.ndarray | None, np.ndarray, str],
    gt: tuple[np.ndarray | None, np.ndarray, str],
    options: EvalOptions | None = None,
) -> EvalResult:
    """``evaluate`` of (stamps or None, poses, name) pairs: without stamps on one side the
    poses are paired by index (an InputError naming both when the counts differ)."""
    (est_stamps, est_poses, est_name), (gt_stamps, gt_poses, gt_name) = est, gt
    if est_stamps is None or gt_stamps is None:
        if len(est_poses) != len(gt_poses):
            raise InputError(
                f"{est_name} ({len(est_poses)} poses) and {gt_name} ({len(gt_poses)} poses): "
                "a KITTI file has no stamps, so both must have one pose per frame"
            )
        stamps = gt_stamps if gt_stamps is not None else est_stamps
        if stamps is None:
            stamps = np.arange(len(gt_poses), dtype=float)
        est_stamps = gt_stamps = stamps
    return evaluate_arrays(est_stamps, est_poses, gt_stamps, gt_poses, options)


def _trajectory(stamps: np.ndarray, poses: np.ndarray, name: str) -> PoseTrajectory3D:
    stamps = np.asarray(stamps, dtype=float).ravel()
    poses = np.asarray(poses, dtype=float)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise InputError(f"{name} poses must be (N,4,4), got {poses.shape}")
    if stamps.shape[0] != poses.shape[0]:
        raise InputError(f"{name}: {stamps.shape[0]} stamps for {poses.shape[0]} poses")
    if poses.shape[0] == 0:
        raise InputError(f"{name} trajectory is empty")
    if not (np.all(np.isfinite(poses)) and np.all(np.isfinite(stamps))):
        raise InputError(f"{name} trajectory contains NaN or inf")
    return PoseTrajectory3D(poses_se3=list(poses), timestamps=stamps, name=name)


def _associate(
    est_stamps: np.ndarray | None,
    est_poses: np.ndarray,
    gt_stamps: np.ndarray | None,
    gt_poses: np.ndarray,
    opt: EvalOptions,
) -> tuple[PoseTrajectory3D, PoseTrajectory3D, PoseTrajectory3D, PoseTrajectory3D]:
    """(estimate, ground truth, matched ground truth, matched estimate) trajectories: the
    poses paired by nearest stamp within ``opt.max_diff`` s (by index without stamps)."""
    if est_stamps is None or gt_stamps is None:
        if len(est_poses) != len(gt_poses):
            raise InputError("without stamps, estimate and ground truth need equal pose counts")
        est_stamps = gt_stamps = np.arange(len(gt_poses), dtype=float)
    traj_est_full = _trajectory(est_stamps, est_poses, "estimate")
    traj_gt_full = _trajectory(gt_stamps, gt_poses, "ground truth")
    try:
        traj_gt, traj_est = sync.associate_trajectories(
            traj_gt_full, traj_est_full, max_diff=opt.max_diff
        )
    except EvoException as exc:
        raise InputError(f"cannot associate estimate with ground truth: {exc}") from exc
    n = traj_est.num_poses
    if n < 3 and opt.align in ("se3", "sim3"):
        raise InputError(f"only {n} poses matched within {opt.max_diff} s; alignment needs 3")
    return traj_est_full, traj_gt_full, traj_gt, traj_est


def _align(
    traj_est: PoseTrajectory3D,
    traj_gt: PoseTrajectory3D,
    traj_est_full: PoseTrajectory3D,
    opt: EvalOptions,
    notes: list[str],
) -> tuple[np.ndarray, float]:
    """Align the matched estimate to the truth in place (``opt.align``), the whole
    estimate with the same transform; (alignment 4x4, scale)."""
    alignment = np.eye(4)
    scale = 1.0
    try:
        if opt.align in ("se3", "sim3"):
            r, t, s = traj_est.align(traj_gt, correct_scale=opt.align == "sim3", n=opt.n_align)
            alignment, scale = lie.sim3(r, t, s), float(s)
            if opt.align == "sim3":
                traj_est_full.scale(s)
            traj_est_full.transform(lie.se3(r, t))
        elif opt.align == "origin":
            alignment = traj_est.align_origin(traj_gt)
            traj_est_full.transform(alignment)
    except EvoException as exc:
        # a straight or very short path has no unique Umeyama solution: fall back to
        # aligning the first poses, and say so (users of short runs still get numbers)
        try:
            alignment = traj_est.align_origin(traj_gt)
            traj_est_full.transform(alignment)
            scale = 1.0
            notes.append(f"{opt.align} alignment impossible ({exc}); aligned the first poses")
        except EvoException as exc2:
            raise InputError(f"alignment failed (degenerate trajectory?): {exc2}") from exc
    return alignment, scale


def _rpe(data: tuple, opt: EvalOptions, notes: list[str]) -> tuple[dict | None, dict | None]:
    """RPE statistics (translation m, rotation deg) over ``opt.rpe_delta`` ``opt.rpe_unit``;
    (None, None) with a note when evo cannot compute them."""
    unit = metrics.Unit.meters if opt.rpe_unit == "m" else metrics.Unit.frames
    delta = float(opt.rpe_delta) if opt.rpe_unit == "m" else int(opt.rpe_delta)
    try:
        rpe_t = metrics.RPE(metrics.PoseRelation.translation_part, delta, unit)
        rpe_t.process_data(data)
        rpe_r = metrics.RPE(metrics.PoseRelation.rotation_angle_deg, delta, unit)
        rpe_r.process_data(data)
        return _stats(rpe_t), _stats(rpe_r)
    except EvoException as exc:
        notes.append(f"RPE not computed: {exc}")
        return None, None


def _kitti(gt_arr: np.ndarray, est_arr: np.ndarray, opt: EvalOptions, notes: list[str]):
    """KITTI drift of the matched poses; over scaled segments when the path is shorter
    than the KITTI lengths (noted); None for fewer than 2 poses."""
    if len(est_arr) < 2:
        return None
    kitti = kitti_metric(gt_arr, est_arr, lengths=opt.kitti_lengths, step=opt.kitti_step)
    if kitti["segments"] == 0 and kitti["path_length"] > 0:
        kitti = kitti_metric_scaled(gt_arr, est_arr, step=opt.kitti_step)
        notes.append(
            f"path {kitti['path_length']:.1f} m is shorter than the KITTI segments; "
            f"KITTI drift over scaled segments {kitti['lengths']} m"
        )
    return kitti


def evaluate_arrays(
    est_stamps: np.ndarray | None,
    est_poses: np.ndarray,
    gt_stamps: np.ndarray | None,
    gt_poses: np.ndarray,
    options: EvalOptions | None = None,
) -> EvalResult:
    """Compare (N,4,4) estimate poses with ground truth; stamps in seconds.

    Stamps ``None`` pairs poses by index. Same steps as ``evo_ape``/``evo_rpe``:
    associate (nearest stamp within ``max_diff``), align the estimate, then APE
    (translation m, rotation angle deg), RPE (same alignment) and the KITTI drift.
    """
    opt = options or EvalOptions()
    traj_est_full, traj_gt_full, traj_gt, traj_est = _associate(
        est_stamps, est_poses, gt_stamps, gt_poses, opt
    )
    n = traj_est.num_poses
    notes: list[str] = []
    est_indices = np.searchsorted(traj_est_full.timestamps, traj_est.timestamps)
    alignment, scale = _align(traj_est, traj_gt, traj_est_full, opt, notes)
    data = (traj_gt, traj_est)
    ape_t = metrics.APE(metrics.PoseRelation.translation_part)
    ape_t.process_data(data)
    ape_r = metrics.APE(metrics.PoseRelation.rotation_angle_deg)
    ape_r.process_data(data)
    rpe_trans, rpe_rot = _rpe(data, opt, notes)
    gt_arr = np.array(traj_gt.poses_se3)
    est_arr = np.array(traj_est.poses_se3)
    kitti = _kitti(gt_arr, est_arr, opt, notes)
    return EvalResult(
        ape_trans=_stats(ape_t),
        ape_rot=_stats(ape_r),
        rpe_trans=rpe_trans,
        rpe_rot=rpe_rot,
        kitti=kitti,
        n_matched=n,
        n_est=traj_est_full.num_poses,
        n_gt=traj_gt_full.num_poses,
        stamps=np.asarray(traj_est.timestamps, dtype=float).copy(),
        ape_errors=np.asarray(ape_t.error, dtype=float).copy(),
        ape_rot_errors=np.asarray(ape_r.error, dtype=float).copy(),
        est_poses=est_arr,
        gt_poses=gt_arr,
        est_indices=est_indices.astype(int),
        est_full=np.array(traj_est_full.poses_se3),
        alignment=np.asarray(alignment, dtype=float),
        scale=scale,
        path_length=float(traj_gt.path_length),
        options=copy.deepcopy(opt),
        notes=notes,
    )
