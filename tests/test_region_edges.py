"""Region edges (slam/region_edges.py) on a revisit beyond PLICP's basin: two regional
maps of the same rooms, the second drawn 20 deg / 1 m off; the wide search finds the
edge, PLICP from the estimate alone does not."""

from __future__ import annotations

import numpy as np
import pytest

from slam.factors import GraphView
from slam.mapping.grid2d import (
    GridConfig,
    OccupancyGrid,
    compose2d,
    inverse2d,
    matrix_to_pose2,
    pose2_to_matrix,
    transform2d,
)
from slam.region_edges import RegionEdgeConfig, RegionEdgePlugin
from slam.sim.floorplan2d import simulate2d
from slam.types import Keyframe, RegionTag


def _keyframes(drift: np.ndarray):
    """Keyframe 0 at frame 30 with the map of frames 0-40; keyframe 1, the revisit, at
    frame 40 with the map of frames 20-60, both drawn (and posed) in a frame off by
    ``drift``. Returns the keyframes and the true relative pose 0 -> 1."""
    seq = simulate2d("rooms2d", frames=60, speed=1.0, seed=5)

    def region_map(frames, offset):
        g = OccupancyGrid(GridConfig())
        for k in frames:
            p = compose2d(offset, seq.poses[k])
            g.add_scan(transform2d(p, seq.points(k)), p[:2])
        return g.obstacles()

    kfs = []
    for i, (at, frames, off) in enumerate(
        [(30, range(0, 40, 2), np.zeros(3)), (40, range(20, 60, 2), drift)]
    ):
        pose = compose2d(off, seq.poses[at])
        local = transform2d(inverse2d(pose), region_map(frames, off))
        cloud = np.column_stack([local, np.zeros(len(local))]).astype(np.float32)
        relative = np.eye(4) if i == 0 else np.linalg.solve(kfs[0].pose_odom, pose2_to_matrix(pose))
        kfs.append(Keyframe(i, float(i), at, pose2_to_matrix(pose), relative, np.eye(6), cloud,
                            region=RegionTag(region=8 + i, left=7)))  # fmt: skip
    return kfs, compose2d(inverse2d(seq.poses[30]), seq.poses[40])


@pytest.mark.parametrize("wide", [True, False])
def test_wide_search_finds_the_edge_of_a_revisit_20_deg_1_m_off(wide):
    drift = np.array([1.0, -0.4, np.radians(20.0)])
    kfs, truth = _keyframes(drift)
    view = GraphView(kfs, lambda i: kfs[i].pose_odom)  # the estimate: the drifted poses
    plugin = RegionEdgePlugin(RegionEdgeConfig(skip_recent=0, wide_search=wide))
    assert plugin.on_keyframe(kfs[0], view) == []
    factors = plugin.on_keyframe(kfs[1], view)
    if not wide:  # PLICP alone may land on it, but a 20 deg correction is beyond its gate
        assert factors == [] and not plugin.events[-1].accepted
        return
    assert len(factors) == 1 and plugin.events[-1].wide
    measured = matrix_to_pose2(factors[0].measured().matrix())
    assert np.linalg.norm(measured[:2] - truth[:2]) < 0.01
    assert abs(np.degrees(measured[2] - truth[2])) < 0.05
    assert plugin.stats()["region_edges_wide"] == 1
