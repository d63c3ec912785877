"""The shared SE(3) solver's stop on a cycle of associations (``solve_weighted``)."""

from __future__ import annotations

import numpy as np

from slam.registration.solver import solve_weighted


def _flip_flop(T: np.ndarray):
    """Pairs whose targets depend on where the pose is: left of x = 5 mm they lie 1 cm
    ahead, right of it 2 mm behind (with twice the weight), so each step undoes the last."""
    p = np.random.default_rng(0).uniform(-5.0, 5.0, (200, 3))
    left = T[0, 3] < 0.005
    shift = np.array([0.01 if left else -0.002, 0.0, 0.0])
    W = np.broadcast_to(np.eye(3) * (1.0 if left else 2.0), (len(p), 3, 3)).copy()
    q = p + shift
    moved = p @ T[:3, :3].T + T[:3, 3]
    return p, q, W, None, np.sum((moved - q) ** 2, axis=1)


def test_a_cycle_of_pairs_stops_as_converged_only_when_asked():
    kw = dict(max_iterations=20, transformation_epsilon=1e-12, fitness_epsilon=0.0)
    res = solve_weighted(np.eye(4), _flip_flop, 200, cycle_tolerance=0.002, reference=True, **kw)
    assert res.stop_reason == "cycle" and res.converged
    assert res.iterations <= 4
    assert -0.003 < res.T_target_source[0, 3] < 0.011
    off = solve_weighted(np.eye(4), _flip_flop, 200, reference=True, **kw)
    assert off.stop_reason == "max_iterations" and not off.converged
