"""Speed of preprocessing and features on a simulated 28.8k-point 16-beam scan (ms per scan).

Run: .venv/bin/python benchmarks/bench_preprocess.py [--repeat 7] [--before REV] [--knn]
     .venv/bin/python benchmarks/bench_preprocess.py --scans [--repeat 7]
Every row is also given relative to open3d remove_statistical_outlier (C++), measured in the
same run, so numbers from runs under different machine load can be compared. --before REV
loads the preprocessing modules of git revision REV (``git show``, read-only) and times them
side by side with the working tree ("before"/"after" columns, same run, results compared).
--knn also times the k-NN back ends (small_gicp 1/2 threads, scipy cKDTree, open3d).
--scans times SOR and its k-NN old (KD-tree, no ring) against new (range image with the
scan's rings, slam.preprocess.range_image) on a simulated 16-beam corridor and park scan, a
simulated 64-beam urban scan and a real KITTI-raw HDL-64E scan (rings inferred as the pipeline
does), with the certificate rate and whether the keep-masks are identical.
--scans --before REV times the SOR with rings of revision REV (its sor, sor_kernels, knn,
range_image and range_image_kernels modules, written to a temporary package so that numba
caches them) against the working tree on the same scans, interleaved; --threads N sets
numba's threads (CPU time with 1 thread is the unloaded single-core time on a busy machine).
--steps gives the CPU time of each step of the SOR with rings (range image, window search,
box search, row gather, statistics) on the same scans. --banded times the paper's SOR
(one statistic per scan) against ``SorConfig(mode="banded")`` (per range band) on the same
scans, with the share of points each removes per range band.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
import types

import numpy as np
import open3d as o3d

import slam.features.curvature
import slam.features.loam
from slam import deskew as deskew_mod
from slam.preprocess import sor as sor_mod
from slam.preprocess import voxel as voxel_mod

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MODULES = {
    "sor": ("slam/preprocess/sor.py", sor_mod),
    "voxel": ("slam/preprocess/voxel.py", voxel_mod),
    "curvature": ("slam/features/curvature.py", slam.features.curvature),
    "loam": ("slam/features/loam.py", slam.features.loam),
    "deskew": ("slam/deskew.py", deskew_mod),
}


def scan(seed=0):
    """16 x 1800 rays in a closed yard (ground + 4 walls, infinite height) -> 28,800 points,
    1 cm range noise, 0.5 % of the points replaced by outliers uniform in the volume."""
    rng = np.random.default_rng(seed)
    el = np.radians(np.linspace(-15.0, 15.0, 16))
    az = np.linspace(-np.pi, np.pi, 1800, endpoint=False)
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    t = np.full(len(d), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        for c, ax in ((-15.0, 0), (25.0, 0), (-10.0, 1), (12.0, 1), (-1.5, 2)):
            tt = c / d[:, ax]
            t = np.where((tt > 0) & (tt < t), tt, t)
    xyz = d * (t + rng.normal(0, 0.01, len(t)))[:, None]
    label = np.zeros(len(xyz), dtype=int)
    out = rng.choice(len(xyz), int(0.005 * len(xyz)), replace=False)
    xyz[out] = rng.uniform([-15, -10, -1.5], [25, 12, 4], (len(out), 3))
    label[out] = 1
    ring = np.repeat(np.arange(16), 1800).astype(np.int16)
    time_s = np.tile(np.arange(1800) / 1800 * 0.1, 16)
    return xyz, label, ring, time_s


def load_revision(rev: str) -> dict[str, types.ModuleType]:
    """The preprocessing modules as of git revision rev, wired to each other (not to HEAD)."""
    mods = {}
    for name, (path, _) in MODULES.items():
        src = subprocess.run(
            ["git", "show", f"{rev}:{path}"], cwd=ROOT, capture_output=True, text=True, check=True
        ).stdout
        mod = types.ModuleType(f"before_{name}")
        sys.modules[mod.__name__] = mod  # dataclasses look their module up
        exec(compile(src, f"{rev}:{path}", "exec"), mod.__dict__)
        mods[name] = mod
    mods["loam"].covariance_curvature = mods["curvature"].covariance_curvature
    return mods


SOR_CHAIN = ("sor", "sor_kernels", "knn", "range_image", "range_image_kernels")


def load_sor_chain(rev: str, folder: str) -> types.ModuleType:
    """slam.preprocess.sor of revision rev with the k-NN modules it uses, as files of a
    package ``sor_before`` under folder (imports rewired to it; numba caches beside them)."""
    import importlib
    import importlib.util

    pkg = os.path.join(folder, "sor_before")
    os.makedirs(pkg, exist_ok=True)
    open(os.path.join(pkg, "__init__.py"), "w").close()
    for name in SOR_CHAIN:
        src = subprocess.run(
            ["git", "show", f"{rev}:slam/preprocess/{name}.py"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        with open(os.path.join(pkg, f"{name}.py"), "w") as f:
            f.write(src.replace("slam.preprocess.", "sor_before."))
    spec = importlib.util.spec_from_file_location(
        "sor_before", os.path.join(pkg, "__init__.py"), submodule_search_locations=[pkg]
    )
    sys.modules["sor_before"] = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(sys.modules["sor_before"])
    return importlib.import_module("sor_before.sor")


def stages(m: dict[str, types.ModuleType], xyz, ring, time_s, T) -> dict:
    """Callables per stage; the improved-FLOAM chain is deskew -> weighted SOR -> features with
    kappa -> voxel downsample of edges (0.2 m) and planes (0.4 m)."""
    cfg = m["loam"].FeatureConfig(use_covariance_curvature=True)
    keep = m["sor"].weighted_sor(xyz)
    xf, rf = xyz[keep], ring[keep]
    feats = m["loam"].extract_features(xf, rf, cfg)
    edges, planes = xf[feats.edge_idx], xf[feats.plane_idx]

    def chain():
        p = m["deskew"].deskew(xyz, time_s, T, 0.1)
        k = m["sor"].weighted_sor(p)
        q = p[k]
        f = m["loam"].extract_features(q, ring[k], cfg)
        m["voxel"].voxel_downsample(q[f.edge_idx], 0.2)
        m["voxel"].voxel_downsample(q[f.plane_idx], 0.4)

    return {
        "classic_sor (k=10)": lambda: m["sor"].classic_sor(xyz),
        "weighted_sor (k=10)": lambda: m["sor"].weighted_sor(xyz),
        "covariance_curvature (k=10, all)": lambda: m["curvature"].covariance_curvature(xf),
        "extract_features": lambda: m["loam"].extract_features(xf, rf),
        "extract_features + kappa": lambda: m["loam"].extract_features(xf, rf, cfg),
        "deskew": lambda: m["deskew"].deskew(xyz, time_s, T, 0.1),
        "voxel_downsample (all, 0.2 m)": lambda: m["voxel"].voxel_downsample(xyz, 0.2),
        "voxel_downsample (edges+planes)": lambda: (
            m["voxel"].voxel_downsample(edges, 0.2),
            m["voxel"].voxel_downsample(planes, 0.4),
        ),
        "IMPROVED-FLOAM PREPROCESSING": chain,
    }


def timed(fn, repeat):
    """Median wall-clock ms of fn."""
    return timed_pair({"_": fn}, repeat)["_"][0]


def timed_pair(fns: dict, repeat: int, stat=np.median) -> dict[str, tuple[float, float]]:
    """Median (or stat) of the (wall, CPU) ms per callable, the callables interleaved run by
    run so that load changes hit all of them alike. CPU = process time, close to the unloaded
    wall time of single-threaded code on a busy machine (threads add their CPU time up)."""
    for fn in fns.values():
        fn()
    wall: dict = {k: [] for k in fns}
    cpu: dict = {k: [] for k in fns}
    for _ in range(repeat):
        for k, fn in fns.items():
            c0, t0 = time.process_time(), time.perf_counter()
            fn()
            wall[k].append(time.perf_counter() - t0)
            cpu[k].append(time.process_time() - c0)
    return {k: (1e3 * float(stat(wall[k])), 1e3 * float(stat(cpu[k]))) for k in fns}


def knn_rows(xyz, repeat) -> dict:
    import small_gicp
    from scipy.spatial import cKDTree

    def o3d_knn():
        t = o3d.core.Tensor(xyz)
        nns = o3d.core.nns.NearestNeighborSearch(t)
        nns.knn_index()
        return nns.knn_search(t, 11)

    rows = {
        f"small_gicp KdTree, {n} thread(s)": lambda n=n: small_gicp.KdTree(
            xyz, num_threads=n
        ).batch_knn_search(xyz, 11, num_threads=n)
        for n in (1, 2)
    }
    for w in (1, -1):
        rows[f"cKDTree workers={w}"] = lambda w=w: cKDTree(xyz).query(xyz, 11, workers=w)
        rows[f"cKDTree unbalanced, workers={w}"] = lambda w=w: cKDTree(
            xyz, balanced_tree=False, compact_nodes=False
        ).query(xyz, 11, workers=w)
    rows["open3d NearestNeighborSearch"] = o3d_knn
    return {name: ms for name, (ms, _) in timed_pair(rows, repeat).items()}


def real_scans() -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, xyz, ring) of one scan each: corridor/park (VLP-16), urban (HDL-64, no ring
    field), KITTI-raw (real HDL-64E, no ring); missing rings from the first scans' beams."""
    import itertools
    import tarfile
    import tempfile
    from pathlib import Path

    from slam.io.folders import cloud_files, read_cloud
    from slam.io.source import open_source
    from slam.sensor import estimate_beams
    from slam.sim.cache import ensure_sequence

    def with_rings(name, scans):
        s = scans[-1]
        ring = s.ring
        if ring is None:
            ring = estimate_beams([t.xyz for t in scans]).ring_of(s.xyz)
        return name, s.xyz, ring

    out = []
    for name, kw in (
        ("corridor 16-beam", dict(scene="corridor", frames=100)),
        ("park 16-beam", dict(scene="park", frames=150)),
        ("urban 64-beam", dict(scene="urban", frames=30, sensor="hdl64")),
    ):
        seq = ensure_sequence(kw.pop("scene"), **kw)
        out.append(with_rings(name, list(itertools.islice(iter(open_source(seq.bag)), 6))))
    data = Path(ROOT).parent / "shared" / "data" / "kitti_raw_drive" / "data_1.tar.xz"
    with tempfile.TemporaryDirectory() as tmp:
        with tarfile.open(data, "r:xz") as tar:
            tar.extractall(tmp, filter="data")
        files = cloud_files(Path(tmp) / "data_1")[:3]
        scans = [read_cloud(f, index=i, stamp=0.1 * i) for i, f in enumerate(files)]
    out.append(with_rings("KITTI-raw HDL-64E", scans))
    return out


def scan_rows_before(rev: str, repeat: int) -> None:
    """SOR with rings, revision rev against the working tree, same scans, same run."""
    import tempfile

    from slam.preprocess.range_image import range_image_knn

    folder = tempfile.mkdtemp(prefix="sor_before_")
    before = load_sor_chain(rev, folder)
    cfg_b, cfg_a = before.SorConfig(), sor_mod.SorConfig()
    print(f"load average {os.getloadavg()[0]:.2f}; min of {repeat}, ms per scan (wall / CPU)")
    print(
        f"  {'scan':20s} {'points':>7s} {'SOR ' + rev[:10]:>15s} {'SOR now':>15s}"
        f" {'x wall':>6s} {'x CPU':>6s} {'cert':>6s} same-mask same-k-NN"
    )
    for name, xyz, ring in real_scans():
        res = timed_pair(
            {
                "before": lambda x=xyz, r=ring: before.apply_sor(x, cfg_b, ring=r),
                "after": lambda x=xyz, r=ring: sor_mod.apply_sor(x, cfg_a, ring=r),
            },
            repeat,
            stat=min,
        )
        (wb, cb), (wa, ca) = res["before"], res["after"]
        nb = before.neighbourhoods(xyz, cfg_b.k, ring=ring)
        na = sor_mod.neighbourhoods(xyz, cfg_a.k, ring=ring)
        same_mask = np.array_equal(
            before.apply_sor(xyz, cfg_b, ring=ring), sor_mod.apply_sor(xyz, cfg_a, ring=ring)
        )
        same_knn = np.array_equal(nb.dist, na.dist) and np.array_equal(
            np.sort(nb.idx, axis=1), np.sort(na.idx, axis=1)
        )
        cert = range_image_knn(xyz, ring, cfg_a.k).certified_rate
        print(
            f"  {name:20s} {len(xyz):7d} {wb:7.1f}/{cb:7.1f} {wa:7.1f}/{ca:7.1f}"
            f" {wb / wa:6.2f} {cb / ca:6.2f} {cert:6.3f} {same_mask!s:9s} {same_knn}"
        )


def scan_rows(repeat: int) -> None:
    """Old (KD-tree) vs new (range image) k-NN and weighted SOR per scan, same run."""
    from slam.preprocess.knn import self_knn
    from slam.preprocess.range_image import range_image_knn

    cfg = sor_mod.SorConfig()
    print(f"load average {os.getloadavg()[0]:.2f}; median of {repeat}, ms (wall / CPU)")
    print(
        f"  {'scan':20s} {'points':>7s} {'k-NN old':>13s} {'k-NN new':>13s} {'x':>5s}"
        f" {'SOR old':>13s} {'SOR new':>13s} {'x':>5s} {'cert':>6s} {'visits':>6s} same"
    )
    for name, xyz, ring in real_scans():
        res = timed_pair(
            {
                "knn_old": lambda x=xyz: self_knn(x, cfg.k),
                "knn_new": lambda x=xyz, r=ring: self_knn(x, cfg.k, ring=r),
                "sor_old": lambda x=xyz: sor_mod.apply_sor(x, cfg),
                "sor_new": lambda x=xyz, r=ring: sor_mod.apply_sor(x, cfg, ring=r),
            },
            repeat,
        )
        ri = range_image_knn(xyz, ring, cfg.k)
        same = np.array_equal(sor_mod.apply_sor(xyz, cfg), sor_mod.apply_sor(xyz, cfg, ring=ring))
        (ko, kco), (kn, kcn), (so, sco), (sn, scn) = res.values()
        print(
            f"  {name:20s} {len(xyz):7d} {ko:6.1f}/{kco:6.1f} {kn:6.1f}/{kcn:6.1f} {ko / kn:5.1f}"
            f" {so:6.1f}/{sco:6.1f} {sn:6.1f}/{scn:6.1f} {so / sn:5.1f}"
            f" {ri.certified_rate:6.3f} {ri.visits.mean():6.1f} {same}"
        )


def scan_rows_banded(repeat: int) -> None:
    """The paper's SOR against the banded statistics on the same scans, interleaved, min of
    repeat (wall / CPU ms per scan), and the share of points removed at 0-15, 15-30, 30-50
    and beyond 50 m by each."""
    cfgs = {"paper": sor_mod.SorConfig(), "banded": sor_mod.SorConfig(mode="banded")}
    print(f"load average {os.getloadavg()[0]:.2f}; min of {repeat}, ms per scan (wall / CPU)")
    bands = ((0, 15), (15, 30), (30, 50), (50, np.inf))
    for name, xyz, ring in real_scans():
        fns = {
            m: (lambda c=c, x=xyz, g=ring: sor_mod.apply_sor(x, c, ring=g)) for m, c in cfgs.items()
        }
        res = timed_pair(
            fns,
            repeat,
            stat=min,
        )
        r = np.linalg.norm(xyz, axis=1)
        for m, cfg in cfgs.items():
            keep = sor_mod.apply_sor(xyz, cfg, ring=ring)
            removed = " ".join(
                f"{1 - keep[(r >= lo) & (r < hi)].mean():.3f}"
                if np.any((r >= lo) & (r < hi))
                else "  -  "
                for lo, hi in bands
            )
            w, c = res[m]
            print(f"  {name:20s} {len(xyz):7d} {m:7s} {w:7.1f}/{c:7.1f}  removed {removed}")


def scan_steps(repeat: int) -> None:
    """CPU ms per step of ``apply_sor`` with rings (range image, window search, box search,
    row gather, statistics) on the same scans, min of repeat; --threads 1 gives each step's
    single-core cost on a busy machine."""
    import numba

    from slam.preprocess import range_image as ri
    from slam.preprocess import range_image_kernels as rik

    k = sor_mod.SorConfig().k
    steps = ("range image", "window", "box", "gather", "statistics")
    print(f"load average {os.getloadavg()[0]:.2f}; min of {repeat}, CPU ms per step")
    print(f"  {'scan':20s} {'points':>7s}" + "".join(f" {s:>11s}" for s in steps))
    for name, xyz, ring in real_scans():
        n = len(xyz)
        ring = np.asarray(ring).astype(np.int64)
        best = dict.fromkeys(steps, np.inf)
        for _ in range(repeat + 1):
            buf = ri._BUFFERS
            order, xyz_s = buf.get("order", n, np.int64), buf.get("xyz", (n, 3))
            rng, el_s, az_s = buf.get("rng", n), buf.get("el_s", n), buf.get("az_s", n)
            cx, cy = buf.get("cx", n), buf.get("cy", n)
            t = [time.process_time()]
            start, lo, hi, _ = rik.range_image_into(
                xyz, ring, buf.get("az", n), buf.get("el", n), buf.get("rank", n, np.int64),
                order, xyz_s, rng, el_s, az_s, cx, cy,
            )  # fmt: skip
            in_place = np.count_nonzero(np.abs(np.diff(order)) == 1) > n // 2
            rows = (np.empty((n, k + 1), np.int64), np.empty((n, k)), np.empty(n, bool))
            rows = (*rows, np.empty(n, np.int64))
            out = tuple(np.empty_like(r) for r in rows) if not in_place else rows
            t.append(time.process_time())
            with numba.parallel_chunksize(1):
                rik.window_knn(
                    xyz_s, rng, el_s, cx, cy, az_s, order, start, lo, hi, k, ri.MAX_VISITS,
                    *rows, in_place, ri._NO_JOB, -1.0, ri._NO_EXIT,
                )  # fmt: skip
                t.append(time.process_time())
                bad = np.flatnonzero(~(rows[2][order] if in_place else rows[2]))
                rik.box_knn(xyz_s, order, bad, k, rows[0], rows[1], in_place)
                t.append(time.process_time())
                if not in_place:
                    rik.gather_rows(order, *rows, *out)
            t.append(time.process_time())
            sor_mod.weighted_sor_terms_fast(out[1])
            t.append(time.process_time())
            for j, s in enumerate(steps):
                best[s] = min(best[s], 1e3 * (t[j + 1] - t[j]))
        print(f"  {name:20s} {n:7d}" + "".join(f" {best[s]:11.2f}" for s in steps))


def stage_rows(xyz, ring, time_s, T, before: str | None, repeat: int) -> None:
    """Wall / CPU ms per scan of every stage (and of revision ``before``) against open3d's
    statistical outlier removal (the reference R)."""
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    after = {name: mod for name, (_, mod) in MODULES.items()}
    runs = {"after": stages(after, xyz, ring, time_s, T)}
    if before:
        runs = {"before": stages(load_revision(before), xyz, ring, time_s, T), **runs}
    ref = timed(lambda: pc.remove_statistical_outlier(11, 1.0), repeat)
    print(f"{len(xyz)} points, median of {repeat} runs, load average {os.getloadavg()[0]:.2f}")
    print(f"  open3d remove_statistical_outlier (reference R) {ref:7.1f} ms")
    head = "".join(f"{k + ' wall':>12s} {'cpu':>6s} {'x R':>5s}" for k in runs)
    print(f"  {'stage (ms per scan)':36s}{head}")
    for name in runs["after"]:
        res = timed_pair({k: run[name] for k, run in runs.items()}, repeat)
        cols = "".join(f"{w:12.1f} {c:6.1f} {w / ref:5.2f}" for w, c in res.values())
        print(f"  {name:36s}{cols}")


def same_as_before(xyz, ring, time_s, T, before: str) -> None:
    """Whether SOR, the features and deskew give what revision ``before`` gives."""
    b = load_revision(before)
    for fn in ("classic_sor", "weighted_sor"):
        same = np.array_equal(getattr(b["sor"], fn)(xyz), getattr(sor_mod, fn)(xyz))
        print(f"  {fn} keep-mask identical to {before}: {same}")
    cfg = slam.features.loam.FeatureConfig(use_covariance_curvature=True)
    fb = b["loam"].extract_features(xyz, ring, b["loam"].FeatureConfig(**vars(cfg)))
    fa = slam.features.loam.extract_features(xyz, ring, cfg)
    same = all(np.array_equal(getattr(fb, f), getattr(fa, f)) for f in ("edge_idx", "plane_idx"))
    print(f"  features (with kappa) identical to {before}: {same}")
    db = b["deskew"].deskew(xyz, time_s, T, 0.1)
    err = np.abs(db - deskew_mod.deskew(xyz, time_s, T, 0.1)).max()
    print(f"  deskew max difference: {err:.1e} m")


def synthetic_scan_rows(args: argparse.Namespace) -> None:
    """The stages on the synthetic 16-beam scan; k-NN back ends, the check against
    ``--before`` and the outliers each SOR removes."""
    xyz, label, ring, time_s = scan()
    T = np.eye(4)
    T[:3, :3] = o3d.geometry.get_rotation_matrix_from_axis_angle(np.array([0.0, 0.0, 0.05]))
    T[:3, 3] = [0.1, 0.0, 0.0]
    stage_rows(xyz, ring, time_s, T, args.before, args.repeat)
    if args.knn:
        print("  k-NN, 28.8k points, k=11 (build + query):")
        for name, ms in knn_rows(xyz, args.repeat).items():
            print(f"    {name:34s} {ms:8.1f} ms")
    if args.before:
        same_as_before(xyz, ring, time_s, T, args.before)
    for name, keep in (
        ("classic", sor_mod.classic_sor(xyz)),
        ("weighted", sor_mod.weighted_sor(xyz)),
    ):
        print(
            f"  {name:9s} outliers removed {1 - keep[label == 1].mean():6.1%}"
            f"  surface kept {keep[label == 0].mean():6.1%}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--before", metavar="REV", help="git revision to compare against")
    ap.add_argument("--knn", action="store_true", help="also time the k-NN back ends")
    ap.add_argument("--scans", action="store_true", help="SOR old vs new on 16/64-beam scans")
    ap.add_argument("--threads", type=int, help="numba threads (default: numba's)")
    ap.add_argument("--steps", action="store_true", help="CPU ms per step of SOR with rings")
    ap.add_argument("--banded", action="store_true", help="paper vs banded SOR per scan")
    args = ap.parse_args()
    if args.threads:
        import numba

        numba.set_num_threads(args.threads)
    if args.steps:
        scan_steps(args.repeat)
    elif args.banded:
        scan_rows_banded(args.repeat)
    elif args.scans and args.before:
        scan_rows_before(args.before, args.repeat)
    elif args.scans:
        scan_rows(args.repeat)
    else:
        synthetic_scan_rows(args)


if __name__ == "__main__":
    main()
