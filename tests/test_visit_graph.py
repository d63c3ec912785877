"""The visit graph: vertices per visit, loop edges between measurement-only
visit clouds found by the wide correlative search, and its use through ``dpcr2d``
(``visit_scans``) and the region-edges plugin."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.dpcr2d import Dpcr2d, Dpcr2dConfig, matrix_to_pose2
from slam.errors import ConfigError
from slam.factors import GraphView
from slam.mapping.grid2d import compose2d, inverse2d
from slam.pipeline import keyframe_cloud
from slam.region_edges import RegionEdgePlugin
from slam.sim.floorplan2d import simulate2d
from slam.types import Keyframe, Scan
from slam.visit_graph import (
    VisitGraphConfig,
    run_visit_graph,
    vertex_scans,
    visit_cloud,
)
from slam.visit_refine import offset_stats, visit_offsets


@pytest.fixture(scope="module")
def rooms():
    """1.3 laps of the rooms at 1 m/s (511 scans) and a drifting 'front end': the truth's
    steps with +0.15 deg per metre of heading and 0.5 % of scale (0.9 m off by the end)."""
    seq = simulate2d("rooms2d", speed=1.0, laps=1.3, seed=1)
    scans = [seq.points(k)[:, :2].astype(np.float64) for k in range(len(seq.stamps))]
    gt = np.asarray(seq.poses, dtype=np.float64)
    fe = [gt[0].copy()]
    for k in range(1, len(gt)):
        rel = compose2d(inverse2d(gt[k - 1]), gt[k])
        rel[2] += np.radians(0.15) * np.hypot(rel[0], rel[1])
        rel[0] *= 1.005
        fe.append(compose2d(fe[-1], rel))
    return seq, scans, gt, np.array(fe)


def test_visit_graph_closes_the_loop_of_a_drifting_front_end(rooms):
    """Measured: without loop edges the last 100 scans are 0.87 m off at most, with the
    visit graph 0.14 m, mean over the run 0.36 -> 0.11 m (17 loop edges, 20 of 37
    candidates rejected as ambiguous; with 3 candidates per visit: 0.08 m, 14 edges)."""
    _, scans, gt, fe = rooms
    none, _ = run_visit_graph(fe, scans, VisitGraphConfig(max_candidates=0))
    poses, vg = run_visit_graph(fe, scans, VisitGraphConfig())
    err_none = np.hypot(*(none - gt)[:, :2].T)
    err = np.hypot(*(poses - gt)[:, :2].T)
    assert err_none[-100:].max() > 0.6
    assert err[-100:].max() < 0.2 and err.mean() < 0.15
    assert len(vg.loops) >= 8
    # every accepted edge measures the true relative pose of its two vertices, up to the
    # drift inside a reference (5 visits of 0.15 deg / m: ~2 deg end to end, 10 cm at 5 m;
    # measured median 1.7 cm / 0.39 deg, worst 9.0 cm / 1.01 deg)
    anchors = vertex_scans(len(fe), vg.cfg.visit_scans)
    for j, i, z in vg.loops:
        true = compose2d(inverse2d(gt[anchors[j]]), gt[anchors[i]])
        d = compose2d(inverse2d(true), z)
        assert np.hypot(d[0], d[1]) < 0.12 and abs(np.degrees(d[2])) < 1.3, (j, i, d)


def test_visit_graph_rejects_ambiguous_matches(rooms):
    """With a uniqueness bound nothing passes (every search has a second peak below 1)
    no edge is added and the trajectory is the front end's."""
    _, scans, _, fe = rooms
    poses, vg = run_visit_graph(fe, scans, VisitGraphConfig(max_uniqueness=0.0))
    assert vg.loops == [] and len(vg.events) > 10
    assert all(e.reason == "ambiguous" for e in vg.events)
    assert np.allclose(poses, fe, atol=1e-6)


def test_final_refinement_pulls_the_visits_onto_each_other(rooms):
    """``refine_rounds``: every visit re-registered against the other visits near it at
    their optimised poses, those as edges, re-optimised. Measured: mean error over the
    run 0.108 -> 0.091 m, last 100 scans 0.136 -> 0.107 m at most; 15 of 15 visits
    registered each round, the last round's median correction 7 mm (converged). Without
    any loop edge, refinement alone: mean 0.362 -> 0.331 m (its window, +-0.3 m around
    the estimate, is no loop search)."""
    _, scans, gt, fe = rooms
    base, _ = run_visit_graph(fe, scans, VisitGraphConfig())
    poses, vg = run_visit_graph(fe, scans, VisitGraphConfig(refine_rounds=3))
    err_base = np.hypot(*(base - gt)[:, :2].T)
    err = np.hypot(*(poses - gt)[:, :2].T)
    assert err.mean() < err_base.mean() - 0.01 and err[-100:].max() < err_base[-100:].max()
    assert len(vg.refine_stats) == 3
    assert all(r["accepted"] >= 10 for r in vg.refine_stats)
    assert vg.refine_stats[-1]["median_m"] < 0.02
    # the same registrations as a consistency measure (``visit_offsets``): how far each
    # visit lies from the others. Measured median / p90: drifting front end 0.170 / 0.194 m
    # (10 of 15 visits beyond the 0.3 m window), truth 0.008 / 0.023 m (the clouds carry
    # the front end's drift inside a visit), visit graph 0.010 / 0.059, refined 0.007 / 0.010
    anchors = vertex_scans(len(fe), vg.cfg.visit_scans)
    clouds = [vg.loop_search.clouds[i] for i in range(len(anchors))]
    path = np.array([vg.loop_search.path[i] for i in range(len(anchors))])
    stats = {
        name: offset_stats(visit_offsets(P[anchors], clouds, path, vg.cfg))
        for name, P in [("fe", fe), ("truth", gt), ("graph", base), ("refined", poses)]
    }
    assert stats["fe"]["accepted"] < 10 and stats["fe"]["median_m"] > 0.1
    assert stats["truth"]["accepted"] == stats["refined"]["accepted"] == 15
    assert stats["truth"]["median_m"] < 0.015 and stats["refined"]["p90_m"] < 0.02
    assert stats["graph"]["p90_m"] > stats["refined"]["p90_m"]
    with pytest.raises(ConfigError):
        VisitGraphConfig(refine_rounds=-1)


def test_dpcr2d_visit_keyframes_carry_the_visit_clouds(rooms):
    """``visit_scans``: a keyframe at frame 0 and at the last frame of every visit, its
    cloud the replay's visit cloud of the same scans at the front end's own poses; the
    region-edges plugin then searches those clouds (the same loops as the replay)."""
    seq, _, _, _ = rooms
    n, vs = 95, 10
    fe = Dpcr2d(Dpcr2dConfig(visit_scans=vs, visit_pad=5))
    out, scans = [], []
    for k in range(n):
        xyz = np.column_stack([seq.points(k), np.zeros(len(seq.points(k)))])
        scans.append(xyz[:, :2])
        out.append(fe.process(Scan(float(seq.stamps[k]), xyz, index=k)))
    kf = [k for k, o in enumerate(out) if o.is_keyframe]
    assert kf == list(vertex_scans(n, vs)) == [0, 9, 19, 29, 39, 49, 59, 69, 79, 89]
    poses = np.array([matrix_to_pose2(o.pose) for o in out])
    prev = 0
    for a in kf:
        lo = max(0, prev + 1 - 5) if a else 0
        want = visit_cloud(poses[lo : a + 1], scans[lo : a + 1], poses[a], 0.05)
        assert out[a].region.visit and out[a].cloud.shape == (len(want), 3)
        assert np.allclose(out[a].cloud[:, :2], want, atol=1e-5)
        prev = a
    # the plugin on these keyframes: visit loop search, no region pairs
    keyframes = []
    plugin = RegionEdgePlugin(RegionEdgePlugin.Config(visits=VisitGraphConfig(min_path=5.0)))
    for i, a in enumerate(kf):
        o = out[a]
        keyframes.append(
            Keyframe(
                i, o.stamp, a, o.pose, o.relative, o.info, keyframe_cloud(o.cloud), region=o.region
            )  # fmt: skip
        )
        view = GraphView(keyframes, lambda j: keyframes[j].pose_odom)
        plugin.on_keyframe(keyframes[-1], view)
    assert len(plugin.visit_loops.order) == len(kf)
    assert all(e.region_source == -1 for e in plugin.events)


def test_visit_grid_fuses_the_visits_at_the_optimised_poses(rooms):
    """``visit_grid``: the visits' hits at the poses given (map.pgm of a visit run): at the
    front end's poses the walls of the scans; with every keyframe moved by 1 m the
    obstacles move by 1 m; without ``visit_scans`` there is none (regional maps instead)."""
    seq, _, _, _ = rooms
    fe = Dpcr2d(Dpcr2dConfig(visit_scans=10))
    plain = Dpcr2d()
    out = []
    for k in range(40):
        xyz = np.column_stack([seq.points(k), np.zeros(len(seq.points(k)))])
        out.append(fe.process(Scan(float(seq.stamps[k]), xyz, index=k)))
        plain.process(Scan(float(seq.stamps[k]), xyz, index=k))
    poses = [o.pose for o in out if o.is_keyframe]
    assert plain.visit_grid({i: T for i, T in enumerate(poses)}) is None
    grid = fe.visit_grid({i: T for i, T in enumerate(poses)})
    moved = {}
    for i, T in enumerate(poses):
        moved[i] = T.copy()
        moved[i][0, 3] += 1.0
    shifted = fe.visit_grid(moved)
    a, b = grid.obstacles(), shifted.obstacles()
    assert len(a) > 500 and abs(len(a) - len(b)) < 0.05 * len(a)
    assert np.median(b[:, 0]) - np.median(a[:, 0]) == pytest.approx(1.0, abs=0.06)
    # map.pgm is probabilistic: the beams of every visit's scans carve free space (the
    # rooms' floor); hits only, there is none and the walls are the same cells +- a few %
    hits = fe.visit_grid({i: T for i, T in enumerate(poses)}, free_space=False)
    assert (grid.data < 0).sum() > 10 * len(a) and (hits.data < 0).sum() == 0
    assert abs(len(hits.obstacles()) - len(a)) < 0.15 * len(a)
    # the visits' own scans: frame 0, then 1-9, 10-19, 20-29, 30-39
    assert [len(v) for v in fe.visit_scans] == [1, 9, 10, 10, 10]
