"""Registration of one scan from several starts: the speed hypotheses of a run's first
motion and the positions along the extrapolated motion after a long gap."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from slam.odometry.config import CommonConfig
from slam.odometry.estimate import Estimate
from slam.registration.gicp import RegistrationError
from slam.registration.plausibility import motion_magnitude
from slam.types import Scan

Register = Callable[[Scan, np.ndarray, dict, bool], Estimate]
Tried = list[tuple[Estimate, np.ndarray]]


def start_beats(est: Estimate, base: Estimate | None, c: CommonConfig, turns: bool = False) -> bool:
    """Whether a registration from a speed hypothesis explains the scan better than the one
    from the prediction ``base``: ``base`` failed or did not converge and ``est`` did, or
    ``est`` converged more than ``start_min_shift`` m away (``turns``: or
    ``start_min_turn_deg`` turned) and ``explains_better`` by ``start_min_gain`` (else the
    prediction's stands: the same minimum found twice)."""
    res = est.result
    if res is None or not res.converged:
        return False
    if base is None or base.result is None or not base.result.converged:
        return True
    shift = float(np.linalg.norm(est.pose[:3, 3] - base.pose[:3, 3]))
    apart = shift > c.start_min_shift
    if turns:
        turn = motion_magnitude(np.linalg.inv(base.pose) @ est.pose)[1]
        apart = apart or turn > c.start_min_turn_deg
    return apart and explains_better(est, base, c) > c.start_min_gain


def explains_better(est: Estimate, base: Estimate, c: CommonConfig) -> float:
    """How much better ``est`` explains the scan than ``base``: the share more
    correspondences plus ``start_rmse_weight`` x the share lower RMSE. Either alone misleads
    at a moving start: within the correspondence distance of the true step (a car at 5-15
    m/s moves 0.5-1.5 m a frame) nearly every point pairs with something, so the pose left
    near rest pairs as many points or more, only loosely (street at 7.6 m/s: rest 6754 pairs,
    RMSE 0.30 m; the true step 6601, 0.25 m), while along a plain street a slid alignment
    pairs fewer points tighter."""
    (n, rmse), (n0, rmse0) = evidence(est), evidence(base)
    gain = n / max(n0, 1) - 1.0
    tighter = 1.0 - rmse / max(rmse0, 1e-12)
    return gain + c.start_rmse_weight * tighter


def evidence(est: Estimate) -> tuple[int, float]:
    """(pairs, RMSE m) a start is judged by: the front end's ``est.evidence`` (e.g. the
    points that show the motion along an open road) or the registration's."""
    if est.evidence is not None:
        return est.evidence
    return est.result.num_inliers, est.result.rmse


def most_explained(tried: Tried) -> tuple[Estimate, np.ndarray]:
    """The registration with the most correspondences (the consensus; fitness breaks ties):
    along a street the wrong alignments fit tighter but on fewer points."""
    return max(tried, key=lambda et: (evidence(et[0])[0], -evidence(et[0])[1]))


class StartSearch:
    """Registers a scan from several starts through the front end's ``register(scan, T0,
    timings, wide)``, each from the same per-scan front-end state (``save`` / ``restore``:
    what registering a scan advances, e.g. a dynamics tracker)."""

    def __init__(
        self,
        cfg: CommonConfig,
        register: Register,
        save: Callable[[], object],
        restore: Callable[[object], None],
    ):
        self._c = cfg
        self._register = register
        self._save = save
        self._restore = restore

    def tried(self, work: Scan, starts: list[np.ndarray], timings: dict) -> Tried:
        """The registrations (wide search) from each start that did not fail."""
        state = self._save()
        out = []
        for T0 in starts:
            self._restore(state)
            try:
                out.append((self._register(work, T0, timings, True), T0))
            except RegistrationError:
                continue
        return out

    def best_after_gap(
        self, work: Scan, starts: list[np.ndarray], timings: dict
    ) -> tuple[Estimate, np.ndarray]:
        """After a long gap: the registration that explains the most of the scan, and its
        start."""
        tried = self.tried(work, starts, timings)
        if not tried:
            raise RegistrationError("no registration converged from any gap hypothesis")
        scored = [(e, T0) for e, T0 in tried if e.result is not None]
        return most_explained(scored) if scored else tried[0]

    def _race(
        self,
        work: Scan,
        T_base: np.ndarray,
        others: list[np.ndarray],
        timings: dict,
        wide: bool,
        turns: bool = False,
    ) -> tuple[Estimate | None, Tried, Tried, object, object]:
        """The registration from ``T_base`` and (wide) from each of ``others``, each from the
        same per-scan state: the base's (None: it failed; without a result: nothing to
        register against, no other tried), the others that did not fail, those of them
        that ``start_beats`` the base's, the state before and the state after the base."""
        state = self._save()
        try:
            base = self._register(work, T_base, timings, wide)
        except RegistrationError:
            base = None
        after = self._save()
        if base is not None and base.result is None:
            return base, [], [], state, after
        self._restore(state)
        tried = self.tried(work, others, timings)
        better = [(e, T0) for e, T0 in tried if start_beats(e, base, self._c, turns)]
        return base, tried, better, state, after

    def first_motion(
        self,
        work: Scan,
        T_pred: np.ndarray,
        starts: list[np.ndarray],
        timings: dict,
        wide: bool,
    ) -> tuple[Estimate, np.ndarray, int]:
        """A map but no velocity yet: the registration from the prediction (at rest, the
        first of ``starts``) as usual and from the speed hypotheses; another start's is
        kept only where it ``start_beats`` the prediction's. Returns it, its start and the
        number of starts."""
        base, tried, better, state, after = self._race(work, T_pred, starts[1:], timings, wide)
        if base is not None and base.result is None:  # nothing to register against
            return base, T_pred, 0
        self._restore(after)
        if better:
            return (*most_explained(better), len(starts))
        if len(starts) > 1 and not _converged(base):
            # no start converged: a flat cost creeps for all its iterations (a 16-beam
            # scan against one scan at 25 m/s); the most explained end is refined once more
            ends = [(e, T0) for e, T0 in tried if e.result is not None]
            if base is not None:
                ends.append((base, T_pred))
            if ends:
                end, T0 = most_explained(ends)
                self._restore(state)
                try:
                    again = self._register(work, end.pose, timings, False)
                except RegistrationError:
                    again = None
                if _converged(again):
                    return again, T0, len(starts)
                self._restore(after)
        if base is None:
            raise RegistrationError("no registration converged from any start hypothesis")
        return base, T_pred, len(starts)

    def after_turns(
        self, work: Scan, starts: list[np.ndarray], shifts: list[np.ndarray], timings: dict
    ) -> tuple[Estimate, bool]:
        """Tracking lost: the registrations (wide) from the prediction (the first of
        ``starts``) and from its turns; a turn's is kept where it ``start_beats`` the
        prediction's (``turns``). Returns it, and whether the scan shows its pose: another
        of ``starts`` converged to it (within ``start_min_shift`` m and
        ``start_min_turn_deg``), and so did, along each of x and y, a start from it moved by
        one of ``shifts`` (sensor-frame offsets, 4x4) along that axis: a pose the sensor is
        pulled to from starts tens of degrees and half a metre apart is the scan's, not its
        start's (along a plain corridor the shifted starts stay where they started)."""
        base, tried, better, state, after = self._race(
            work, starts[0], starts[1:], timings, True, turns=True
        )
        if base is not None and base.result is None:  # nothing to register against
            return base, False
        if better:
            best = most_explained(better)[0]
        elif base is None:
            raise RegistrationError("no registration converged from any turn hypothesis")
        else:
            best = base
        others = [e for e in [base, *(e for e, _ in tried)] if e is not None and e is not best]
        shown = any(_near(e, best, self._c) for e in others if e.result is not None)
        if shown and shifts:
            self._restore(state)
            back = self.tried(work, [best.pose @ D for D in shifts], timings)
            axes = {
                int(np.argmax(np.abs((np.linalg.inv(best.pose) @ T0)[:3, 3])))
                for e, T0 in back
                if e.result is not None and _near(e, best, self._c)
            }
            shown = {0, 1} <= axes
        if best is base:
            self._restore(after)
        else:  # the kept registration's per-scan state
            self._restore(state)
            best = self._register(work, best.pose, timings, False)
        return best, shown


def _converged(est: Estimate | None) -> bool:
    """Whether ``est`` has a converged registration."""
    return est is not None and est.result is not None and est.result.converged


def _near(a: Estimate, b: Estimate, c: CommonConfig) -> bool:
    """Whether two registrations ended at the same pose (``start_min_shift`` m and
    ``start_min_turn_deg``)."""
    shift, turn = motion_magnitude(np.linalg.inv(a.pose) @ b.pose)
    return shift <= c.start_min_shift and turn <= c.start_min_turn_deg
