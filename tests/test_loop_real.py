"""Loop closure on real scans (slam/loop/*): a real HDL-32E pair and a real KITTI HDL-64 drive.

Same-place pairs must verify with the right transform, scans of different places must not,
and Scan Context must rank the revisits ahead of unrelated scans. References: the pair's
``T_target_source.txt`` and small_gicp's own fine alignment; for the KITTI drive (no ground
truth) small_gicp's fine alignment of scan 0 and scan i started from the chain of its
consecutive-scan alignments (the car drives ~0.8 m per scan, so scan 21 is ~17 m ahead).
"""

from __future__ import annotations

import tarfile

import numpy as np
import open3d as o3d
import pytest
import small_gicp
from shared_data import shared_path

from slam.factors import GraphView
from slam.io.folders import read_cloud
from slam.loop.config import SearchConfig
from slam.loop.plugin import LoopClosurePlugin, auto_descriptor_params
from slam.loop.scan_context import column_shift_distance, scan_context
from slam.loop.verify import COARSE_REGISTRATIONS, VerifyParams, verify, yaw_matrix
from slam.types import Keyframe

KITTI_PAIRS = (3, 10, 15, 21)  # scan 0 against these: 2.3, 7.8, 11.9 and 16.8 m apart


def _err(T_est: np.ndarray, T_ref: np.ndarray) -> tuple[float, float]:
    E = np.linalg.inv(T_ref) @ T_est
    ang = np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(E[:3, 3])), float(ang)


def _fine(target: np.ndarray, source: np.ndarray, init: np.ndarray) -> np.ndarray:
    res = small_gicp.align(
        target, source, init_T_target_source=init, downsampling_resolution=0.25,
        max_correspondence_distance=1.0,
    )  # fmt: skip
    return np.asarray(res.T_target_source)


@pytest.fixture(scope="module")
def pair():
    folder = shared_path("scan_pair")
    tgt, src = (
        np.asarray(o3d.io.read_point_cloud(str(folder / f"{n}.ply")).points, dtype=np.float64)
        for n in ("target", "source")
    )
    T_ref = np.loadtxt(folder / "T_target_source.txt")
    return tgt, src, T_ref, _fine(tgt, src, T_ref)


@pytest.fixture(scope="module")
def kitti(tmp_path_factory):
    """The 22 scans and references T_0_i (small_gicp fine from the consecutive chain)."""
    out = tmp_path_factory.mktemp("kitti_raw")
    with tarfile.open(shared_path("kitti_raw_drive", "data_1.tar.xz"), "r:xz") as tar:
        tar.extractall(out, filter="data")
    files = sorted((out / "data_1").glob("*.pcd"))
    assert len(files) == 22
    scans = [read_cloud(f).xyz for f in files]
    chain = [np.eye(4)]
    for a, b in zip(scans[:-1], scans[1:], strict=True):
        chain.append(chain[-1] @ _fine(a, b, np.eye(4)))
    ref = {i: _fine(scans[0], scans[i], chain[i]) for i in KITTI_PAIRS}
    return scans, chain, ref


# --------------------------------------------------------------------------- verification


def test_real_hdl32_pair_verifies_with_the_reference_transform(pair):
    tgt, src, T_ref, T_sg = pair
    res = verify(tgt, src, yaw_matrix(0.0))  # Scan Context's yaw: 0 (one 6-degree sector)
    assert res.accepted, res.reason
    t, r = _err(res.T_target_source, T_sg)
    assert t < 0.05 and r < 0.3, (t, r)
    t, r = _err(res.T_target_source, T_ref)  # the reference is good to a few cm, ~0.3 deg
    assert t < 0.05 and r < 0.5, (t, r)
    assert res.overlap > 0.7 and res.fitness < 0.06


@pytest.mark.parametrize("i", KITTI_PAIRS)
def test_real_kitti_scans_metres_apart_verify_from_the_yaw_alone(kitti, i):
    """Started at zero translation (all Scan Context gives), 2-17 m off: the bird's-eye-view
    start reaches the right basin, and the result matches small_gicp's fine alignment."""
    scans, _, ref = kitti
    res = verify(scans[0], scans[i], yaw_matrix(0.0))
    assert res.accepted, res.reason
    t, r = _err(res.T_target_source, ref[i])
    assert t < 0.05 and r < 0.3, (i, t, r)
    assert np.linalg.norm(ref[i][:3, 3]) > 2.0  # the start was really metres away
    # the other way round too: scan i as the target
    back = verify(scans[i], scans[0], yaw_matrix(0.0))
    assert back.accepted, back.reason
    t, r = _err(back.T_target_source, np.linalg.inv(ref[i]))
    assert t < 0.05 and r < 0.3, (i, t, r)


def test_real_kitti_correct_start_is_not_pulled_away(kitti):
    """Started at the right answer, the schedule must stay there (a coarse pass with long
    correspondences once slid correct starts ~2 m along the road)."""
    scans, _, ref = kitti
    for i in (3, 15):
        res = verify(scans[0], scans[i], ref[i])
        assert res.accepted, res.reason
        t, r = _err(res.T_target_source, ref[i])
        assert t < 0.02 and r < 0.1, (i, t, r)


def test_real_scans_of_different_places_do_not_verify(pair, kitti):
    tgt, src, *_ = pair
    scans, *_ = kitti
    mirrored = scans[10] * [1.0, -1.0, 1.0]  # the street seen in a mirror: no real place
    shifted = scans[10] + [0.0, 30.0, 0.0]  # the scene 30 m to the side: sensor elsewhere
    cases = {
        "kitti vs hdl32": (scans[0], src),
        "hdl32 vs kitti": (tgt, scans[15]),
        "kitti vs mirrored": (scans[0], mirrored),
        "kitti vs shifted": (scans[0], shifted),
    }
    for name, (target, source) in cases.items():
        for yaw in (0.0, np.pi):
            res = verify(target, source, yaw_matrix(yaw))
            assert not res.accepted, (name, yaw, res.overlap, res.fitness)


def test_both_coarse_registrations_verify_real_revisits_alike_and_reject_other_places(pair, kitti):
    """The coarse stage by KD-tree GICP (default) or by VGICP on the fine target's voxels
    (cheaper): the same decisions, transforms within 1 cm / 0.05 deg of each other."""
    import dataclasses

    tgt, src, *_ = pair
    scans, _, ref = kitti
    params = {c: dataclasses.replace(VerifyParams(), coarse_registration=c)
              for c in COARSE_REGISTRATIONS}  # fmt: skip
    for i in (3, 15):
        results = {c: verify(scans[i], scans[0], yaw_matrix(0.0), p) for c, p in params.items()}
        assert all(r.accepted for r in results.values()), i
        t, r = _err(results["vgicp"].T_target_source, results["gicp"].T_target_source)
        assert t < 0.01 and r < 0.05, (i, t, r)
    for target, source in ((scans[0], src), (scans[0], scans[10] + [0.0, 30.0, 0.0])):
        assert not any(verify(target, source, yaw_matrix(0.0), p).accepted
                       for p in params.values())  # fmt: skip


# --------------------------------------------------------------------------- Scan Context


def test_real_scan_context_ranks_revisits_ahead_of_unrelated_scans(pair, kitti):
    tgt, src, *_ = pair
    scans, *_ = kitti
    cfg = LoopClosurePlugin.Config()
    p = auto_descriptor_params(scans[:10], cfg.descriptor)
    # KITTI's Velodyne sits 1.73 m above the road; ranges up to ~80 m (99 %: ~50 m)
    assert 55.0 <= p.max_radius <= 80.0
    assert 1.5 < p.lidar_height < 2.2
    d = {n: scan_context(c, p) for n, c in
         {"k0": scans[0], "k3": scans[3], "k15": scans[15], "k21": scans[21], "ht": tgt,
          "hs": src}.items()}  # fmt: skip

    def dist(a, b):
        return float(column_shift_distance(d[a], d[b][None])[0][0])

    revisits = [dist("k0", "k3"), dist("k0", "k15"), dist("ht", "hs")]
    unrelated = [dist("k0", "hs"), dist("k15", "hs"), dist("k21", "ht"), dist("k3", "ht")]
    assert max(revisits) < min(unrelated), (revisits, unrelated)
    assert dist("ht", "hs") < 0.2 and dist("k0", "k3") < 0.25  # a few metres: a candidate


def test_real_kitti_drive_through_the_plugin(kitti):
    """The plugin on the drive, estimates = the consecutive chain: auto geometry from the
    first 10 keyframes; every candidate 8-17 m back along the street is a true revisit, so
    every accepted loop must carry the reference transform."""
    scans, chain, _ = kitti
    cfg = LoopClosurePlugin.Config(search=SearchConfig(exclude_recent=10, threshold=0.35))
    plugin = LoopClosurePlugin(cfg)
    kfs: list[Keyframe] = []
    view = GraphView(kfs, lambda i: chain[i])
    for i, cloud in enumerate(scans):
        rel = np.eye(4) if i == 0 else np.linalg.inv(chain[i - 1]) @ chain[i]
        kfs.append(Keyframe(i, 0.1 * i, i, chain[i], rel, np.eye(6), cloud))
        plugin.on_keyframe(kfs[-1], view)
    assert 55.0 <= plugin.sc_params.max_radius <= 80.0
    accepted = plugin.accepted
    assert len(accepted) >= 5, [(e.source, e.target, e.reason) for e in plugin.events]
    for e in accepted:
        T_ref = _fine(
            scans[e.target], scans[e.source], np.linalg.inv(chain[e.target]) @ chain[e.source]
        )
        t, r = _err(e.T_target_source, T_ref)
        assert t < 0.05 and r < 0.3, (e.source, e.target, t, r)
        sig = np.sqrt(np.diag(np.linalg.inv(e.info)))
        assert np.all(sig[3:] >= 0.05 * 0.999)  # the factor claims no more than its floor


def test_real_kitti_revisit_seen_turned_with_a_coarse_yaw_guess(kitti):
    """The same street 12 m on, the sensor turned by -150 deg; the guess 5 deg off (a Scan
    Context sector is 6 deg): the transform is still found."""
    scans, _, ref = kitti
    R = yaw_matrix(np.radians(-150.0))
    turned = scans[15] @ R[:3, :3]  # T_0_turned = T_0_15 @ R
    res = verify(scans[0], turned, yaw_matrix(np.radians(-145.0)))
    assert res.accepted, res.reason
    t, r = _err(res.T_target_source, ref[15] @ R)
    assert t < 0.05 and r < 0.3, (t, r)
