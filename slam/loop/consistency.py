"""Pairwise consistency of loop closures: a loop enters the graph once another loop nearby
agrees with it through the odometry (perceptual aliasing rarely repeats itself consistently).

Two loops ``(a1 -> b1, T1)`` and ``(a2 -> b2, T2)`` (T = T_target_source, a the older
keyframe) both predict the pose of b2 relative to a1, one through the odometry of the old
pass and one through the new pass:

    T1 * D_b  =  D_a * T2,     D_a = T_odom(a1)^-1 T_odom(a2),  D_b = T_odom(b1)^-1 T_odom(b2)

(Mangelson et al. 2018, "Pairwise Consistent Measurement Set Maximization", eq. 5, with the
two odometry segments short so that their drift is small). The cycle error
``E = (D_a T2)^-1 (T1 D_b)`` must stay within ``base + ratio x travelled`` m in translation
and ``base_deg + ratio_deg x travelled`` deg in rotation, where travelled (m) is the
odometric length of the two segments. The whole translation is compared, also along a
direction a loop's registration left free (slam.loop.verify.ambiguous_axis): such a loop
claims nothing there, but an edge that contradicts its partners along it is still a wrong
edge in graph.g2o, and the aliased registrations of a corridor do. ORB-SLAM's temporal
consistency check (Mur-Artal et al. 2015, section VI-A) is the same idea: a loop is trusted
once consecutive keyframes confirm it.

:class:`LoopConsistency` holds verified loops until one is confirmed: a loop is confirmed
when at least one other verified loop whose source keyframe lies within ``window`` keyframes
is consistent with it and it agrees with more of the confirmed loops in that window than it
contradicts. A loop that no partner confirms within ``window`` keyframes expires.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class OdometryGateParams:
    """The gate each registered loop passes against the estimates: it may move the current
    keyframe from its estimate relative to the candidate by at most base + ratio x the
    distance travelled between the two (m), and turn it by at most yaw_deg (ratio < 0: off).
    Against perceptual aliasing: look-alike rooms, repetitive corridors, corridors seen
    backwards. The ratio is the odometry drift allowed per metre travelled."""

    base: float = 3.0
    ratio: float = 0.04
    yaw_deg: float = 45.0

    @property
    def enabled(self) -> bool:
        return self.ratio >= 0

    def allowed(self, travelled: float) -> float:
        """Translation (m) a loop may move the keyframe after ``travelled`` m."""
        return self.base + self.ratio * travelled


@dataclass(frozen=True)
class ConsistencyParams:
    """window (keyframes, 0 = off: every verified loop enters at once); base (m) + ratio x
    travelled; base_deg (deg) + ratio_deg (deg per m) x travelled. A corridor that aliases a
    registration metres along its axis rarely does so twice by the same offset; the cost: a
    revisit seen by a single keyframe closes no loop."""

    window: int = 10
    base: float = 0.5
    ratio: float = 0.02
    base_deg: float = 2.0
    ratio_deg: float = 0.5

    def __post_init__(self) -> None:
        if self.window < 0 or min(self.base, self.ratio, self.base_deg, self.ratio_deg) < 0:
            raise ValueError(
                "window (keyframes) and base / ratio / base_deg / ratio_deg must be >= 0"
            )


@dataclass(eq=False)  # identity: loops are compared by object, never by value
class PendingLoop:
    """A verified loop: keyframe ids (target older), T_target_source, the odometry poses of
    both keyframes (4x4), their odometric distances from the start (m), ``payload``
    (whatever the caller attaches: the factor, the event), state."""

    target: int
    source: int
    T: np.ndarray
    T_odom_target: np.ndarray
    T_odom_source: np.ndarray
    s_target: float
    s_source: float
    payload: object = None
    confirmed: bool = False
    expired: bool = False


def cycle_error(l1: PendingLoop, l2: PendingLoop) -> tuple[np.ndarray, float, float]:
    """(translation error (3,) m in l1's target frame, rotation error deg, travelled m) of
    the cycle a1 -> b1 -> b2 -> a2 -> a1 closed by two loops and the odometry."""
    D_a = np.linalg.solve(l1.T_odom_target, l2.T_odom_target)
    D_b = np.linalg.solve(l1.T_odom_source, l2.T_odom_source)
    via_1 = l1.T @ D_b  # T_a1_b2 through loop 1 and the new pass
    via_2 = D_a @ l2.T  # T_a1_b2 through the old pass and loop 2
    E = np.linalg.solve(via_2, via_1)
    cos = np.clip((np.trace(E[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    travelled = abs(l1.s_target - l2.s_target) + abs(l1.s_source - l2.s_source)
    return via_1[:3, 3] - via_2[:3, 3], float(np.degrees(np.arccos(cos))), travelled


def consistent(l1: PendingLoop, l2: PendingLoop, p: ConsistencyParams) -> bool:
    """Whether two loops agree through the odometry within the tolerances."""
    e, rot_deg, travelled = cycle_error(l1, l2)
    return bool(
        np.linalg.norm(e) <= p.base + p.ratio * travelled
        and rot_deg <= p.base_deg + p.ratio_deg * travelled
    )


class LoopConsistency:
    """Verified loops waiting for a consistent partner; see the module docstring."""

    def __init__(self, params: ConsistencyParams = ConsistencyParams()):
        self.p = params
        self.loops: list[PendingLoop] = []  # confirmed and pending, in verification order

    def add(self, loop: PendingLoop) -> list[PendingLoop]:
        """Take a verified loop; returns the loops it confirms (itself and/or pending
        partners), in verification order. With window 0 every loop is confirmed at once."""
        if self.p.window <= 0:
            loop.confirmed = True
            self.loops.append(loop)
            return [loop]
        near = [
            m for m in self.loops if not m.expired and abs(m.source - loop.source) <= self.p.window
        ]
        agree = [m for m in near if consistent(loop, m, self.p)]
        self.loops.append(loop)
        if not agree or not self._wins(loop, near, agree):
            return []
        loop.confirmed = True
        out = [loop]
        for m in agree:  # pending partners that the newly confirmed loop now outvotes for
            if m.confirmed:
                continue
            m_near = [x for x in self.loops if x is not m and not x.expired
                      and abs(x.source - m.source) <= self.p.window]  # fmt: skip
            m_agree = [x for x in m_near if x is loop or consistent(m, x, self.p)]
            if self._wins(m, m_near, m_agree):
                m.confirmed = True
                out.append(m)
        return sorted(out, key=lambda m: self.loops.index(m))

    @staticmethod
    def _wins(loop: PendingLoop, near: list[PendingLoop], agree: list[PendingLoop]) -> bool:
        """More confirmed loops nearby agree with ``loop`` than contradict it."""
        ids = {id(m) for m in agree}
        confirmed_against = sum(1 for m in near if m.confirmed and id(m) not in ids)
        confirmed_for = sum(1 for m in agree if m.confirmed)
        return confirmed_for >= confirmed_against

    def expire(self, latest_source: int | None = None) -> list[PendingLoop]:
        """Pending loops no partner can confirm any more (source older than latest_source -
        window; None: all pending ones, at the end of the run)."""
        out = []
        for m in self.loops:
            if m.confirmed or m.expired:
                continue
            if latest_source is None or m.source < latest_source - self.p.window:
                m.expired = True
                out.append(m)
        return out
