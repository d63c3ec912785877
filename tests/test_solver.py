"""The shared SE(3) solver's stops (``solve_weighted``): on a cycle of associations, and at
the least re-associated cost when the steps only chase their pairs."""

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


_CREEP_POINTS = np.random.default_rng(1).uniform(-5.0, 5.0, (200, 3))


def _creep(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points and their pairs at pose T: every association puts the targets 4 cm (+ 10 % of
    the distance gone) behind the moved points along x, so each step goes back further and
    the re-associated cost rises (a sparse map's ring samples pairing behind a scan at speed)."""
    p = _CREEP_POINTS
    moved = p @ T[:3, :3].T + T[:3, 3]
    q = moved - np.array([0.04 + 0.1 * abs(T[0, 3]), 0.0, 0.0])
    return p, q


def test_steps_that_chase_their_pairs_stop_at_the_least_cost():
    def associate(T):
        p, q = _creep(T)
        moved = p @ T[:3, :3].T + T[:3, 3]
        return p, q, np.broadcast_to(np.eye(3), (len(p), 3, 3)), None, np.sum((moved - q) ** 2, 1)

    kw = dict(max_iterations=20, transformation_epsilon=1e-12, fitness_epsilon=0.0)
    res = solve_weighted(np.eye(4), associate, 200, least_cost=True, reference=True, **kw)
    assert res.stop_reason == "least_cost" and res.converged
    assert abs(res.T_target_source[0, 3]) < 1e-9  # the start had the least cost
    off = solve_weighted(np.eye(4), associate, 200, reference=True, **kw)
    assert off.stop_reason == "max_iterations" and not off.converged
    assert off.T_target_source[0, 3] < -1.0  # crept 20 steps back
