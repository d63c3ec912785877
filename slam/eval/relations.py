"""The relation metric of Kuemmerle et al., "On measuring the accuracy of SLAM algorithms"
(Autonomous Robots 2009): a trajectory is scored by the relative poses it gives between
pairs of timestamps, against reference relations, not by a global alignment.

For each relation (t1, t2, delta*) the estimate's relative pose is delta = x(t1)^-1 x(t2)
and the error is delta*^-1 delta (eq. 3 of the paper: epsilon = delta ominus delta*): its
translation norm (m) and its rotation angle (deg) are the per-relation errors, summarised
as mean / std / median / p90 / the share above a threshold (0.2 m: a gross error).

Relations files are the Freiburg format, one per line: ``t1 t2 x y z roll pitch yaw``
(m, rad; the pose of t2 in the frame of t1). Timestamps are matched to the trajectory's
nearest stamp within ``max_dt`` seconds; relations with an unmatched end are counted and
left out.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from slam.errors import InputError

GROSS_M = 0.2  # m: Kuemmerle's tables report the share of relations above this


@dataclass(frozen=True)
class Relations:
    """Reference relations: stamps t1, t2 (N,) and relative poses (N, 4, 4), t2 in t1."""

    t1: np.ndarray
    t2: np.ndarray
    poses: np.ndarray

    def __len__(self) -> int:
        return len(self.t1)


@dataclass(frozen=True)
class RelationErrors:
    """Per relation (matched ones only): translation error (m), rotation error (deg), the
    index of the relation in the file; plus how many relations could not be matched."""

    trans: np.ndarray
    rot_deg: np.ndarray
    index: np.ndarray
    unmatched: int

    def summary(self, gross_m: float = GROSS_M) -> dict:
        """mean / std / median / p90 / max of both errors, the share of translation errors
        above ``gross_m`` and the counts."""
        out: dict = {"relations": int(len(self.trans)), "unmatched": int(self.unmatched)}
        for name, e in (("trans_m", self.trans), ("rot_deg", self.rot_deg)):
            e = e if len(e) else np.full(1, np.nan)
            out[name] = {
                "mean": float(np.mean(e)),
                "std": float(np.std(e)),
                "median": float(np.median(e)),
                "p90": float(np.percentile(e, 90)),
                "max": float(np.max(e)),
            }
        share = float(np.mean(self.trans > gross_m)) if len(self.trans) else float("nan")
        out["trans_m"][f"share_above_{gross_m:g}m"] = share
        return out


def _matrices(xyz: np.ndarray, rpy: np.ndarray) -> np.ndarray:
    T = np.tile(np.eye(4), (len(xyz), 1, 1))
    T[:, :3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    T[:, :3, 3] = xyz
    return T


def read_relations(path: str | Path) -> Relations:
    """A Freiburg relations file (``t1 t2 x y z roll pitch yaw`` per line, '#' comments)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"relations file not found: {path}")
    try:
        rows = np.loadtxt(path, comments="#", ndmin=2)
    except ValueError as exc:
        msg = f"{path}: not a relations file (t1 t2 x y z roll pitch yaw): {exc}"
        raise InputError(msg) from exc
    if rows.size == 0:
        raise InputError(f"{path}: no relations in the file")
    if rows.shape[1] != 8:
        raise InputError(
            f"{path}: {rows.shape[1]} columns; a relations file has 8 (t1 t2 x y z roll pitch yaw)"
        )
    return Relations(rows[:, 0].copy(), rows[:, 1].copy(), _matrices(rows[:, 2:5], rows[:, 5:8]))


def write_relations(path: str | Path, rel: Relations, header: str = "") -> None:
    """``rel`` as a Freiburg relations file."""
    rpy = Rotation.from_matrix(rel.poses[:, :3, :3]).as_euler("xyz")
    rows = np.column_stack([rel.t1, rel.t2, rel.poses[:, :3, 3], rpy])
    head = "t1 t2 x y z roll pitch yaw" + (f"\n{header}" if header else "")
    np.savetxt(path, rows, fmt="%.6f", header=head)


def relations_of(stamps: np.ndarray, poses: np.ndarray, i: np.ndarray, j: np.ndarray) -> Relations:
    """The relations of a trajectory (stamps (K,), poses (K, 4, 4)) between index pairs."""
    i, j = np.asarray(i, dtype=np.int64), np.asarray(j, dtype=np.int64)
    rel = np.linalg.inv(poses[i]) @ poses[j]
    return Relations(np.asarray(stamps)[i].copy(), np.asarray(stamps)[j].copy(), rel)


def relations_in_frame(rel: Relations, T_body_sensor: np.ndarray) -> Relations:
    """Relations between sensor poses as relations between the poses of the body it is
    mounted on (4x4 ``T_body_sensor``): T_b1_b2 = T_body_sensor T_s1_s2 T_body_sensor^-1."""
    M = np.asarray(T_body_sensor, dtype=np.float64)
    return Relations(rel.t1.copy(), rel.t2.copy(), M @ rel.poses @ np.linalg.inv(M))


def match_stamps(stamps: np.ndarray, query: np.ndarray, max_dt: float) -> np.ndarray:
    """Index of the nearest of the sorted ``stamps`` for each ``query``; -1 beyond ``max_dt``."""
    stamps = np.asarray(stamps, dtype=np.float64)
    order = np.argsort(stamps, kind="stable")
    s = stamps[order]
    k = np.clip(np.searchsorted(s, query), 1, max(len(s) - 1, 1))
    lo = np.clip(k - 1, 0, len(s) - 1)
    hi = np.clip(k, 0, len(s) - 1)
    pick = np.where(np.abs(s[hi] - query) < np.abs(s[lo] - query), hi, lo)
    out = order[pick]
    out[np.abs(s[pick] - query) > max_dt] = -1
    return out


def relation_errors(
    stamps: np.ndarray, poses: np.ndarray, rel: Relations, max_dt: float = 0.01
) -> RelationErrors:
    """Kuemmerle's per-relation errors of a trajectory (stamps (K,), poses (K, 4, 4))."""
    a = match_stamps(stamps, rel.t1, max_dt)
    b = match_stamps(stamps, rel.t2, max_dt)
    ok = (a >= 0) & (b >= 0)
    est = np.linalg.inv(poses[a[ok]]) @ poses[b[ok]]
    err = np.linalg.inv(rel.poses[ok]) @ est
    trans = np.linalg.norm(err[:, :3, 3], axis=1)
    rot = np.degrees(Rotation.from_matrix(err[:, :3, :3]).magnitude())
    return RelationErrors(trans, rot, np.flatnonzero(ok), int((~ok).sum()))


def format_summary(name: str, summary: dict) -> str:
    """The metric as printed by ``slam eval --relations``."""
    t, r = summary["trans_m"], summary["rot_deg"]
    share = next(v for k, v in t.items() if k.startswith("share_above"))
    lines = [
        f"{name}: {summary['relations']} relations ({summary['unmatched']} unmatched)",
        f"  translation (m):  mean {t['mean']:.4f}  std {t['std']:.4f}  median "
        f"{t['median']:.4f}  p90 {t['p90']:.4f}  max {t['max']:.4f}  > {GROSS_M:g} m "
        f"{100 * share:.1f} %",
        f"  rotation (deg):   mean {r['mean']:.3f}  std {r['std']:.3f}  median "
        f"{r['median']:.3f}  p90 {r['p90']:.3f}  max {r['max']:.3f}",
    ]
    return "\n".join(lines)


__all__ = [
    "GROSS_M",
    "RelationErrors",
    "Relations",
    "format_summary",
    "match_stamps",
    "read_relations",
    "relation_errors",
    "relations_in_frame",
    "relations_of",
    "write_relations",
]
