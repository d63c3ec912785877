"""Loop detection cost per keyframe at 1000 keyframes (target <= 10 ms without verification).

Synthetic clouds: 5-10k points on the faces of random boxes around the sensor (up to 80 m),
a new random place per keyframe with one in ten revisiting an older place (rotated, noisy)
so the search has real candidates. Reports descriptor, search (ring-key tree + column
distance on the top-k), the plugin's whole detection step (descriptor + search; the plugin
keeps no cloud of its own) for Scan Context and Scan Context++ (polar + Cartesian context,
augmented queries) as a ratio to Scan Context's, and, separately, GICP verification.

    .venv/bin/python benchmarks/bench_loop.py [--keyframes 1000]
    .venv/bin/python benchmarks/bench_loop.py --real [--baseline-rev 5202a20]

``--real``: verification on the real scans of ``../shared/data`` (the HDL-32E pair, KITTI-raw
scan 0 against scans 2-17 m ahead, both ways, and pairs of different places), started from
the Scan Context yaw alone as in the plugin (clouds voxelised at 0.25 m as the plugin stores
them): accepted / false loops, transform error against small_gicp's fine alignment, ms per
candidate (wall and CPU), for both coarse stages (VGICP, GICP); with ``--baseline-rev`` the
same for ``slam/loop/verify.py`` of that commit.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

from slam.factors import GraphView
from slam.loop.config import ConsistencyConfig, DescriptorConfig, SearchConfig
from slam.loop.consistency import OdometryGateParams
from slam.loop.plugin import LoopClosurePlugin
from slam.loop.scan_context import scan_context
from slam.loop.verify import verify, yaw_matrix
from slam.types import Keyframe


def box_cloud(rng: np.random.Generator, n_points: int) -> np.ndarray:
    """Points on the side faces of 40 random boxes (1-15 m wide, 2-20 m tall) plus ground."""
    centres = rng.uniform(-70, 70, (40, 2))
    half = rng.uniform(0.5, 7.5, (40, 2))
    height = rng.uniform(2, 20, 40)
    b = rng.integers(0, 40, n_points)
    face = rng.integers(0, 4, n_points)
    u = rng.uniform(-1, 1, n_points)
    axis = face % 2  # faces 0/1: constant x, 2/3: constant y
    sign = np.where(face < 2, 1.0, -1.0)
    xy = np.empty((n_points, 2))
    xy[:, 0] = np.where(axis == 0, sign * half[b, 0], u * half[b, 0])
    xy[:, 1] = np.where(axis == 1, sign * half[b, 1], u * half[b, 1])
    xy += centres[b]
    z = rng.uniform(0, 1, n_points) * height[b] - 1.8
    ground = rng.random(n_points) < 0.3
    xy[ground] = rng.uniform(-30, 30, (ground.sum(), 2))
    z[ground] = -1.8
    return np.column_stack([xy, z])


def rotate(points: np.ndarray, yaw: float, rng: np.random.Generator) -> np.ndarray:
    T = yaw_matrix(yaw)
    return points @ T[:3, :3].T + rng.normal(0, 0.02, points.shape)


DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _fine(target: np.ndarray, source: np.ndarray, init: np.ndarray) -> np.ndarray:
    import small_gicp

    res = small_gicp.align(
        target, source, init_T_target_source=init, max_correspondence_distance=1.0
    )
    return np.asarray(res.T_target_source)


def real_pairs() -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]]:
    """(name, target, source, reference T_target_source or None for different places)."""
    import open3d as o3d
    import small_gicp

    from slam.io.folders import read_cloud

    def vox(p: np.ndarray) -> np.ndarray:
        return np.asarray(small_gicp.voxelgrid_sampling(p, 0.25).points())[:, :3]

    tgt, src = (np.asarray(o3d.io.read_point_cloud(str(DATA / "scan_pair" / f"{n}.ply")).points)
                for n in ("target", "source"))  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        with tarfile.open(DATA / "kitti_raw_drive" / "data_1.tar.xz", "r:xz") as tar:
            tar.extractall(tmp, filter="data")
        scans = [read_cloud(f).xyz for f in sorted(Path(tmp, "data_1").glob("*.pcd"))]
    chain = [np.eye(4)]
    for a, b in zip(scans[:-1], scans[1:], strict=True):
        chain.append(chain[-1] @ _fine(a, b, np.eye(4)))
    pairs = [("hdl32 pair", vox(tgt), vox(src), _fine(tgt, src, np.eye(4)))]
    for i in (3, 10, 15, 21):
        ref = _fine(scans[0], scans[i], chain[i])
        pairs.append((f"kitti 0<-{i}", vox(scans[0]), vox(scans[i]), ref))
        back = _fine(scans[i], scans[0], np.linalg.inv(ref))  # small_gicp's own, this way round
        pairs.append((f"kitti {i}<-0", vox(scans[i]), vox(scans[0]), back))
    k0 = vox(scans[0])
    pairs += [
        ("kitti vs hdl32", k0, vox(src), None),
        ("hdl32 vs kitti", vox(tgt), vox(scans[15]), None),
        ("kitti vs mirrored", k0, vox(scans[10] * [1.0, -1.0, 1.0]), None),
        ("kitti vs shifted 30 m", k0, vox(scans[10] + [0.0, 30.0, 0.0]), None),
    ]
    return pairs


def _baseline_verify(rev: str):
    code = subprocess.run(
        ["git", "show", f"{rev}:slam/loop/verify.py"], capture_output=True, text=True, check=True,
        cwd=Path(__file__).resolve().parents[1],
    ).stdout  # fmt: skip
    path = Path(tempfile.mkdtemp()) / "baseline_verify.py"
    path.write_text(code)
    spec = importlib.util.spec_from_file_location("baseline_verify", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["baseline_verify"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod.verify


def _coarse(name: str):
    """verify with the coarse stage ``name`` (gicp / vgicp)."""
    import dataclasses

    from slam.loop.verify import VerifyParams

    params = dataclasses.replace(VerifyParams(), coarse_registration=name)
    return lambda t, s, init: verify(t, s, init, params)


def bench_real(baseline_rev: str | None) -> None:
    pairs = real_pairs()
    impls = [("this, coarse gicp (default)", _coarse("gicp")),
             ("this, coarse vgicp", _coarse("vgicp"))]  # fmt: skip
    impls += [(baseline_rev, _baseline_verify(baseline_rev))] if baseline_rev else []
    for label, fn in impls:
        print(f"--- verify of {label}")
        acc = false = true_pairs = 0
        errs, ms, cpu = [], [], []
        for name, t, s, ref in pairs:
            t0, c0 = time.perf_counter(), time.thread_time()
            res = fn(t, s, yaw_matrix(0.0))
            ms.append(1e3 * (time.perf_counter() - t0))
            cpu.append(1e3 * (time.thread_time() - c0))
            line = f"{name:24s} {'accepted' if res.accepted else 'rejected':8s} {ms[-1]:6.0f} ms"
            if ref is not None:
                true_pairs += 1
                E = np.linalg.inv(ref) @ res.T_target_source
                te = float(np.linalg.norm(E[:3, 3]))
                re = float(np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1))))
                line += f"  error {100 * te:6.1f} cm {re:5.2f} deg"
                if res.accepted:
                    acc += 1
                    errs.append((te, re))
            elif res.accepted:
                false += 1
            print(f"{line}  {res.reason}")
        e = np.array(errs).reshape(-1, 2)
        worst = f"{100 * e[:, 0].max():.1f} cm / {e[:, 1].max():.2f} deg" if len(e) else "-"
        print(
            f"accepted {acc}/{true_pairs} true pairs, false {false}/{len(pairs) - true_pairs}, "
            f"worst accepted error {worst}, {np.mean(ms):.0f} ms/candidate "
            f"({np.mean(cpu):.0f} ms CPU)"
        )


def synthetic_clouds(rng, n: int) -> list[np.ndarray]:
    """n keyframe clouds of 5000-10000 points: new boxes, ~10 % revisits of an older place
    (rotated) after the first 100."""
    places: list[np.ndarray] = []
    clouds = []
    for i in range(n):
        if i > 100 and rng.random() < 0.1:
            clouds.append(rotate(places[rng.integers(0, i - 50)], rng.uniform(-np.pi, np.pi), rng))
        else:
            clouds.append(box_cloud(rng, int(rng.integers(5000, 10001))))
        places.append(clouds[-1])
    return clouds


def detection(clouds: list[np.ndarray]) -> tuple[dict, list[float], int]:
    """Detection only per descriptor (a huge min_keyframe_gap skips verification): the
    plugin's detect ms per keyframe and the plugin; for scan_context the search is also
    timed on its own (a second query per keyframe): its ms per keyframe and hits."""
    det_by = {}
    sc_search: list[float] = []
    sc_hits = 0
    for descriptor in ("scan_context", "scan_context_pp"):
        cfg = LoopClosurePlugin.Config(
            descriptor=DescriptorConfig(kind=descriptor),
            search=SearchConfig(min_keyframe_gap=10**9),
            consistency=ConsistencyConfig(odometry=OdometryGateParams(ratio=-1.0)),
        )
        plugin = LoopClosurePlugin(cfg)
        kfs: list[Keyframe] = []
        view = GraphView(kfs, lambda i: np.eye(4))
        for i, c in enumerate(clouds):
            kf = Keyframe(i, 0.1 * i, i, np.eye(4), np.eye(4), np.eye(6), c)
            kfs.append(kf)
            plugin.on_keyframe(kf, view)
            if descriptor == "scan_context":
                d = scan_context(c)
                t = time.perf_counter()
                found = plugin.db.detect(d, kf.stamp)
                sc_search.append(1e3 * (time.perf_counter() - t))
                sc_hits += found is not None
        det_by[descriptor] = (np.array(plugin.times.detect_ms), plugin)
    return det_by, sc_search, sc_hits


def verification_cpu(rng) -> dict[str, list[float]]:
    """CPU ms of verify on 10 rotated box pairs, per coarse stage."""
    ver_cpu: dict[str, list[float]] = {"vgicp": [], "gicp": []}
    for _ in range(10):
        a = box_cloud(rng, 8000)
        yaw = rng.uniform(-np.pi, np.pi)
        b = rotate(a, -yaw, rng)
        for name, samples in ver_cpu.items():
            c0 = time.thread_time()
            _coarse(name)(a, b, yaw_matrix(yaw + np.radians(4)))
            samples.append(1e3 * (time.thread_time() - c0))
    return ver_cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keyframes", type=int, default=1000)
    ap.add_argument("--real", action="store_true", help="verification on real scans only")
    ap.add_argument("--baseline-rev", default=None, help="also run verify.py of this commit")
    args = ap.parse_args()
    if args.real:
        bench_real(args.baseline_rev)
        return
    rng = np.random.default_rng(0)
    n = args.keyframes
    clouds = synthetic_clouds(rng, n)
    t = time.perf_counter()
    for c in clouds[:200]:
        scan_context(c)
    desc_ms = 1e3 * (time.perf_counter() - t) / 200
    det_by, sc_search, sc_hits = detection(clouds)
    ver_cpu = verification_cpu(rng)

    print(f"keyframes: {n}, points per cloud: 5000-10000, candidates under threshold: {sc_hits}")
    print(f"descriptor                 {desc_ms:7.2f} ms/keyframe")
    det, plugin = det_by["scan_context"]
    print(
        f"search (tree + top-k SC)   {np.mean(sc_search):7.2f} ms/keyframe (last 100: "
        f"{np.mean(sc_search[-100:]):.2f}), tree builds: {plugin.db.tree_builds}"
    )
    for name, (det, _plugin) in det_by.items():
        print(
            f"plugin detection {name:15s} {det.mean():7.2f} ms/keyframe (last 100: "
            f"{det[-100:].mean():.2f}; ratio to scan_context "
            f"{det.mean() / det_by['scan_context'][0].mean():.2f})"
        )
    v, g = np.mean(ver_cpu["vgicp"]), np.mean(ver_cpu["gicp"])
    print(
        f"verification (CPU)         {v:7.2f} ms/candidate with the VGICP coarse stage, "
        f"{g:.2f} with GICP (ratio {v / g:.2f})"
    )


if __name__ == "__main__":
    main()
