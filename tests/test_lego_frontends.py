"""LeGO-LOAM and LeGO-LOAM-LPB front ends on 100 simulated corridor frames (bounded APE vs
ground truth, no frame lost), the recipes, the LPB ablation switches and the ground plane
published for the ground factor."""

import numpy as np
import pytest

from frontends.lego_loam import LegoLoam
from frontends.lego_lpb import LegoLpb
from slam.config import load_config
from slam.frontend import Frontend
from slam.io.source import open_source
from slam.plugins import instantiate
from slam.sim.cache import ensure_sequence

FRAMES = 100


@pytest.fixture(scope="module")
def corridor():
    sim = ensure_sequence("corridor", frames=FRAMES)
    stamps, poses = sim.read_ground_truth()
    return list(open_source(sim.bag)), stamps, poses


def _run(fe, corridor):
    scans, gt_stamps, gt = corridor
    outs = [fe.process(s) for s in scans]
    idx = np.clip(np.searchsorted(gt_stamps, [o.stamp for o in outs]), 0, len(gt) - 1)
    G = np.linalg.inv(gt[idx[0]]) @ gt[idx]
    P = np.array([o.pose for o in outs])
    err = np.linalg.norm(P[:, :3, 3] - G[:, :3, 3], axis=1)
    dist = float(np.sum(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1)))
    return outs, err, dist, gt[idx]


@pytest.fixture(scope="module")
def runs(corridor):
    out = {}
    for name in ("lego_loam", "lego_lpb"):
        fe = instantiate("slam.frontends", load_config(name).frontend, "frontend")
        out[name] = (fe, *_run(fe, corridor))
    return out


@pytest.mark.parametrize(
    ("name", "cls", "max_rmse"), [("lego_loam", LegoLoam, 0.04), ("lego_lpb", LegoLpb, 0.04)]
)
def test_tracks_100_corridor_frames(runs, name, cls, max_rmse):
    """APE RMSE (origin-aligned, no SE3 fit) over 100 frames (10.8 m): measured 2.69 cm
    (lego_loam) and 2.65 cm (lego_lpb), mostly height; floam 4.71 cm, improved_floam 0.80 cm
    on the same frames."""
    fe, outs, err, dist, _ = runs[name]
    assert isinstance(fe, cls) and isinstance(fe, Frontend)
    assert dist > 10.0
    rmse = float(np.sqrt(np.mean(err**2)))
    assert rmse < max_rmse, rmse
    assert err[-1] < 0.01 * dist, (err[-1], dist)
    assert not [(i, o.extras["lost"]) for i, o in enumerate(outs) if "lost" in o.extras]
    # a frame may stop on the iteration cap and still pass the plausibility gate (lego_lpb:
    # 4 of 99 frames at 20 iterations, fitness as usual)
    assert sum(not o.extras["converged"] for o in outs[1:]) <= 0.06 * len(outs)
    assert all(o.extras["n_edges"] > 50 and o.extras["n_ground"] > 50 for o in outs)
    kfs = [o for o in outs if o.is_keyframe]
    assert 5 <= len(kfs) <= int(dist) + 2
    for o in kfs[1:]:
        sig = np.sqrt(np.diag(np.linalg.inv(o.info)))
        assert np.all(sig[3:] > 0.009) and np.all(sig[3:] < 0.5)
        assert 100 < len(o.cloud)


def test_lpb_publishes_the_ground_plane(runs):
    """[nx, ny, nz, d] in the sensor frame against the truth: the corridor floor is the world's
    z = 0, so d is the sensor's true height and n its up axis seen from the sensor. Measured:
    height median 1.1 cm / max 8.9 cm off, tilt median 0.5 deg / max 1.7 deg (the floor is a
    2.5 m wide strip between walls: its roll is weakly determined)."""
    _, outs, _, _, T_world = runs["lego_lpb"]
    gp = np.array([o.extras["ground_plane"] for o in outs])
    dz = np.abs(gp[:, 3] - T_world[:, 2, 3])
    assert np.median(dz) < 0.02 and np.all(dz < 0.12), (np.median(dz), dz.max())
    up = np.einsum("nji,j->ni", T_world[:, :3, :3], np.array([0.0, 0.0, 1.0]))
    tilt = np.degrees(np.arccos(np.clip(np.sum(up * gp[:, :3], axis=1), -1, 1)))
    assert np.median(tilt) < 1.0 and np.all(tilt < 3.0), (np.median(tilt), tilt.max())
    assert all(o.extras["ground_d"] == o.extras["ground_plane"][3] for o in outs)
    assert sum(o.extras["n_dynamic"] for o in outs) > 0  # pedestrians walk in the corridor


def test_lpb_ablation_switches(corridor):
    """Each block off by config: a short run still tracks, and the switched-off block leaves
    no trace (no plane published, no point removed, the voxel maps in use)."""
    scans, gt_stamps, gt = corridor
    scans = scans[:12]
    raw = load_config("lego_lpb").frontend
    off = dict(raw)
    off.update(
        outliers={"enabled": False},
        ground={"enabled": False},
        dynamics={"enabled": False},
        map={"enabled": False},
    )
    fe = instantiate("slam.frontends", off, "frontend")
    outs = [fe.process(s) for s in scans]
    assert all("ground_plane" not in o.extras for o in outs)
    assert all(o.extras["n_outliers"] == 0 and o.extras["n_dynamic"] == 0 for o in outs)
    assert type(fe.edge_map).__name__ == "VoxelHashMap"
    assert not [o.extras["lost"] for o in outs if "lost" in o.extras]
    i = np.clip(np.searchsorted(gt_stamps, [scans[0].stamp, scans[-1].stamp]), 0, len(gt) - 1)
    G = np.linalg.inv(gt[i[0]]) @ gt[i[1]]
    assert np.linalg.norm(G[:3, 3]) > 0.2
    assert np.linalg.norm(outs[-1].pose[:3, 3] - G[:3, 3]) < 0.02


def test_recipes():
    lpb, lego = load_config("lego_lpb"), load_config("lego_loam")
    assert (lego.frontend["name"], lpb.frontend["name"]) == ("lego_loam", "lego_lpb")
    assert lego.frontend["registration"]["ground_weight"] == 0.0
    assert lpb.frontend["registration"]["ground_weight"] == 0.2
    assert lpb.frontend["segmentation"]["enabled"] is False  # the preprocessing instead
    assert lpb.frontend["keyframe"] == lego.frontend["keyframe"]
    assert lpb.factors["loop_closure"]["enabled"] is False
