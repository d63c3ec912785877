"""Map points a second scan confirms (``slam.mapping.second_sighting``): a static surface
sampled again from the next pose is kept, a vehicle moved on is not, the ground always."""

from __future__ import annotations

import numpy as np

from slam.mapping.second_sighting import SecondSighting, seen_before


def _box(x0: float, n: int = 400, seed: int = 0) -> np.ndarray:
    """Points on the faces of a 12 x 2.5 x 3.6 m truck whose rear is at x = x0 (m)."""
    rng = np.random.default_rng(seed)
    p = rng.uniform([0.0, 0.0, 0.3], [12.0, 2.5, 3.9], (n, 3))
    face = rng.integers(0, 3, n)
    p[face == 0, 0] = 0.0  # the rear
    p[face == 1, 0] = 12.0  # the front
    p[face == 2, 1] = 0.0  # the side facing the sensor
    return p + [x0, 10.0, 0.0]


def test_a_surface_sampled_again_is_seen_before_a_moved_one_is_not():
    pole = np.column_stack([np.zeros(8), np.zeros(8), np.linspace(0.5, 4.0, 8)])
    # the next scan's beams meet the pole 0.4 m higher and 5 cm off: kept
    again = pole + [0.05, 0.0, 0.4]
    assert seen_before(again, pole, 0.5, 1.0).all()
    # 0.6 m on horizontally (a walker at 6 m/s, 10 Hz) or 1.2 m up: not
    assert not seen_before(pole + [0.6, 0.0, 0.0], pole, 0.5, 1.0).any()
    assert not seen_before(pole[:1] + [0.0, 0.0, 1.2], pole[:1], 0.5, 1.0).any()
    assert not seen_before(pole, np.zeros((0, 3)), 0.5, 1.0).any()


def test_a_truck_moved_on_stays_out_of_the_map_its_side_and_the_ground_do_not():
    """An oncoming truck 2.3 m on (23 m/s at 10 Hz): its rear and front faces are not
    confirmed, its side (a plane along the motion, which shows nothing along it) largely is;
    the ground is kept whatever moved."""
    sight = SecondSighting(0.5, 1.0)
    first = _box(20.0, seed=1)
    assert sight.keep(first, np.zeros(len(first), dtype=bool)).all()  # the first scan: whole
    truck = _box(17.7, seed=2)
    ground = np.random.default_rng(3).uniform([-30, -10, 0], [30, 10, 0.05], (200, 3))
    pts = np.concatenate([truck, ground])
    exempt = np.r_[np.zeros(len(truck), bool), np.ones(len(ground), bool)]
    keep = sight.keep(pts, exempt)
    kept = keep[: len(truck)]
    rear, front = truck[:, 0] == 17.7, truck[:, 0] == 29.7
    assert not kept[rear].any()  # 2.3 m from anything the first scan saw
    assert kept[front].mean() < 0.25  # only its edge next to the first scan's side
    assert kept[~rear & ~front].mean() > 0.7
    assert keep[len(truck) :].all()


def test_a_reset_keeps_the_next_scan_whole():
    sight = SecondSighting(0.5, 1.0)
    sight.keep(_box(0.0), np.zeros(400, dtype=bool))
    moved = _box(30.0)
    assert not sight.keep(moved, np.zeros(400, dtype=bool)).any()
    sight.reset()
    assert sight.keep(moved, np.zeros(400, dtype=bool)).all()
