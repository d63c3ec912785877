"""Pairwise consistency of the visit graph's loop edges (``slam.visit_graph.PairwiseCheck``):
an edge enters once an independent edge nearby agrees with it through the front end."""

from __future__ import annotations

import numpy as np

from slam.mapping.grid2d import compose2d, inverse2d
from slam.visit_graph import PairwiseCheck, VerifiedLoop, VisitGraphConfig


def two_passes():
    """Front-end poses of visits 0-9 (first pass, 2 m apart along x) and 10-19 (the same
    places again), the second pass off by 0.8 m / 3 deg (drift); the true poses."""
    true = {k: np.array([2.0 * (k % 10), 0.0, 0.0]) for k in range(20)}
    off = np.array([0.8, -0.3, np.radians(3.0)])
    fe, path = {}, {}
    for k in range(20):
        fe[k] = true[k] if k < 10 else compose2d(off, true[k])
        path[k] = 2.0 * k
    return true, fe, path


def edge(true, old, new, shift=(0.0, 0.0, 0.0)) -> VerifiedLoop:
    z = compose2d(compose2d(inverse2d(true[old]), true[new]), np.asarray(shift))
    return VerifiedLoop(old, new, z)


def test_true_edges_confirm_each_other_an_aliased_one_stays_out():
    true, fe, path = two_passes()
    check = PairwiseCheck(VisitGraphConfig(pair_window=4), fe, path)
    assert check.add(edge(true, 2, 12)) == []  # alone: waits for a partner
    wrong = edge(true, 3, 13, shift=(1.0, 0.0, 0.0))  # a corridor aliased by 1 m
    assert check.add(wrong) == []
    confirmed = check.add(edge(true, 4, 14))
    assert {(m.old, m.new) for m in confirmed} == {(2, 12), (4, 14)}
    assert not wrong.confirmed
    # a later wrong one is outvoted by the confirmed true ones
    assert check.add(edge(true, 5, 15, shift=(0.0, 0.0, np.radians(4.0)))) == []
    assert check.add(edge(true, 6, 16))[0].confirmed


def test_edges_of_one_visit_on_overlapping_references_do_not_confirm_each_other():
    """Two edges of the same new visit whose old references share clouds (visits 3 and 4,
    ref_visits 2) are one measurement, not two: no confirmation; 3 and 9 are independent."""
    true, fe, path = two_passes()
    check = PairwiseCheck(VisitGraphConfig(pair_window=4, ref_visits=2), fe, path)
    assert check.add(edge(true, 3, 13)) == []
    assert check.add(edge(true, 4, 13)) == []
    assert len(check.add(edge(true, 9, 13))) == 3


def test_unconfirmed_edges_expire_and_window_zero_admits_all():
    true, fe, path = two_passes()
    check = PairwiseCheck(VisitGraphConfig(pair_window=2), fe, path)
    check.add(edge(true, 1, 11))
    assert check.add(edge(true, 5, 15)) == [] and check.expired == 1
    assert check.loops[0].expired
    open_check = PairwiseCheck(VisitGraphConfig(pair_window=0), fe, path)
    assert open_check.add(edge(true, 1, 11))[0].confirmed
