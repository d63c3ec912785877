"""Loop-closure experiments without re-running the front end: record once, replay many.

The front end never sees the back end (DESIGN.md), so a run's odometry and keyframe clouds
do not depend on the loop closure: ``record`` runs a recipe's front end once over a bag and
stores every frame's Odometry (pose, relative motion, information, keyframe flag, the
keyframes' clouds and scalar extras) in one .npz; ``replay`` feeds those to a Pipeline
with any factor / back-end settings (``--set factors.loop_closure.x=...``), writes the
usual run outputs (trajectory.tum, graph.g2o, loops.csv, ...) and prints APE of odometry and
optimised trajectory and the false loops against the ground truth (loop_audit.py).
A replay gives the same trajectory as ``slam run`` of the same recipe (the loop plugin reads
only keyframes and estimates).

    .venv/bin/python benchmarks/loop_replay.py record BAG --config lego_lpb_loop OUT.npz
    .venv/bin/python benchmarks/loop_replay.py replay OUT.npz --config lego_lpb_loop \
        --gt GT.tum --out runs/replay/x [--set factors.loop_closure.robust=cauchy ...]
    .venv/bin/python benchmarks/loop_replay.py figures GT.tum lpb=runs/replay/x \\
        loam=runs/replay/y --out docs/lego_lpb/return --prefix building_return
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from loop_audit import audit, summary  # noqa: E402

from slam import plugins  # noqa: E402
from slam.config import load_config  # noqa: E402
from slam.types import Odometry, Scan  # noqa: E402


class Recorder:
    """Wraps a front end and keeps what it returns (clouds of keyframes only)."""

    def __init__(self, inner: Any):
        self.inner = inner
        self.rows: list[dict[str, Any]] = []
        self.clouds: dict[int, np.ndarray] = {}

    def process(self, scan: Scan) -> Odometry:
        odom = self.inner.process(scan)
        i = len(self.rows)
        extras = {
            k: v
            for k, v in odom.extras.items()
            if isinstance(v, (bool, int, float, np.generic)) and not k.startswith("_")
        }
        self.rows.append(
            {
                "stamp": float(odom.stamp),
                "pose": np.asarray(odom.pose, float),
                "kf": bool(odom.is_keyframe),
                "relative": np.asarray(odom.relative, float),
                "info": np.asarray(odom.info, float),
                # the keyframe information before the front end's odometry_ambiguity loosened it
                "info_raw": np.asarray(odom.extras.get("_info_before_ambiguity", odom.info), float),
                "extras": {k: float(v) for k, v in extras.items()},
            }
        )
        if odom.is_keyframe or i == 0:
            self.clouds[i] = np.asarray(odom.cloud, dtype=np.float32)[:, :3]
        return odom


def record(bag: Path, config: str, out: Path, overrides: list[str], max_frames: int | None) -> None:
    from slam.io.source import open_source
    from slam.pipeline import Pipeline
    from slam.run import disable_loops

    cfg = load_config(config, overrides)
    disable_loops(cfg)
    rec = Recorder(plugins.instantiate("slam.frontends", cfg.frontend, "frontend"))
    pipe = Pipeline(cfg, frontend=rec)
    t0 = time.process_time()
    pipe.run(open_source(bag, topic=cfg.source.topic), max_frames=max_frames)
    cpu = time.process_time() - t0
    rows = rec.rows
    idx = np.array(sorted(rec.clouds), dtype=np.int64)
    sizes = np.array([len(rec.clouds[i]) for i in idx], dtype=np.int64)
    np.savez(
        out,
        stamps=np.array([r["stamp"] for r in rows]),
        poses=np.stack([r["pose"] for r in rows]),
        is_kf=np.array([r["kf"] for r in rows]),
        relative=np.stack([r["relative"] for r in rows]),
        info=np.stack([r["info"] for r in rows]),
        info_raw=np.stack([r["info_raw"] for r in rows]),
        cloud_frames=idx,
        cloud_sizes=sizes,
        clouds=np.concatenate([rec.clouds[i] for i in idx]) if len(idx) else np.zeros((0, 3)),
        extras=json.dumps([r["extras"] for r in rows]),
        meta=json.dumps({"bag": str(bag), "config": config, "overrides": overrides,
                         "cpu_seconds": cpu}),
    )  # fmt: skip
    print(f"recorded {len(rows)} frames, {len(idx)} keyframes, {cpu:.0f} CPU s -> {out}")


class ReplayFrontend:
    """Plays a recording back as the front end emitted it."""

    def __init__(self, rec: dict[str, Any]):
        self.rec = rec
        off = np.concatenate([[0], np.cumsum(rec["cloud_sizes"])])
        self.cloud = {
            int(f): rec["clouds"][off[k] : off[k + 1]] for k, f in enumerate(rec["cloud_frames"])
        }
        self.extras = json.loads(str(rec["extras"]))

    def process(self, scan: Scan) -> Odometry:
        i = scan.index
        r = self.rec
        return Odometry(
            float(r["stamps"][i]), r["poses"][i], bool(r["is_kf"][i]), r["relative"][i],
            r["info"][i], self.cloud.get(i), dict(self.extras[i]),
        )  # fmt: skip


def load_recording(path: Path) -> dict[str, Any]:
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def replay(
    rec: dict[str, Any], config: str, overrides: list[str], out: Path, gt: Path | None
) -> dict[str, Any]:
    """Run the pipeline over the recording; outputs in ``out``; APE and false loops."""
    from slam.outputs import write_outputs
    from slam.pipeline import Pipeline, resolved_config

    cfg = load_config(config, [*overrides, "source.beam_scans=0"])
    pipe = Pipeline(cfg, frontend=ReplayFrontend(rec))
    scans = (Scan(float(t), np.zeros((0, 3)), index=i) for i, t in enumerate(rec["stamps"]))
    t0 = time.process_time()
    pipe.run(scans)
    cpu = time.process_time() - t0
    out.mkdir(parents=True, exist_ok=True)
    write_outputs(pipe, out, resolved_config=resolved_config(cfg))
    res: dict[str, Any] = {"cpu_seconds": round(cpu, 1), "loops_closed": pipe.state.loops_closed}
    if gt is not None:
        from slam.eval.metrics import evaluate

        res["ape_odometry"] = evaluate(out / "odometry.tum", gt).ape_trans["rmse"]
        res["ape_loop"] = evaluate(out / "trajectory.tum", gt).ape_trans["rmse"]
        if (out / "loops.csv").exists():
            res.update(summary(audit(out, gt)))
    (out / "replay.json").write_text(json.dumps(res, indent=2))
    return res


def figures(runs: list[str], gt: Path, out: Path, prefix: str) -> list[Path]:
    """Figures in paper 001's style for replayed loop runs (``name=RUN_DIR``): the
    odometry of the first and every run's optimised trajectory over the truth (xy), their
    APE over time, and per run the trajectory coloured by its APE and its APE over time."""
    from slam.eval.metrics import evaluate
    from slam.eval.plots import (
        ape_colormap_figure,
        ape_figure,
        ape_overlay_figure,
        overlay_figure,
        save_png,
    )

    out.mkdir(parents=True, exist_ok=True)
    results = {}
    for k, spec in enumerate(runs):
        name, _, run = spec.partition("=")
        if k == 0:
            results[f"{name} odometry"] = evaluate(Path(run) / "odometry.tum", gt)
        results[name] = evaluate(Path(run) / "trajectory.tum", gt)
    files = [save_png(overlay_figure(results, "xy"), out / f"{prefix}_overlay_xy.png")]
    files.append(save_png(ape_overlay_figure(results), out / f"{prefix}_ape_overlay.png"))
    for name, res in results.items():
        safe = name.replace(" ", "_")
        files.append(save_png(ape_colormap_figure(res), out / f"{prefix}_{safe}_heatmap.png"))
        files.append(save_png(ape_figure(res), out / f"{prefix}_{safe}_ape_time.png"))
    return files


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("bag", type=Path)
    r.add_argument("out", type=Path)
    r.add_argument("--config", required=True)
    r.add_argument("--set", dest="overrides", action="append", default=[])
    r.add_argument("--max-frames", type=int)
    p = sub.add_parser("replay")
    p.add_argument("recording", type=Path)
    p.add_argument("--config", required=True)
    p.add_argument("--set", dest="overrides", action="append", default=[])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--gt", type=Path)
    f = sub.add_parser("figures", help="paper-style figures of replayed runs")
    f.add_argument("gt", type=Path)
    f.add_argument("runs", nargs="+", help="name=RUN_DIR (the first one's odometry is drawn too)")
    f.add_argument("--out", type=Path, required=True)
    f.add_argument("--prefix", default="replay")
    a = ap.parse_args(argv)
    if a.cmd == "record":
        record(a.bag, a.config, a.out, a.overrides, a.max_frames)
    elif a.cmd == "figures":
        for path in figures(a.runs, a.gt, a.out, a.prefix):
            print(path)
    else:
        res = replay(load_recording(a.recording), a.config, a.overrides, a.out, a.gt)
        print(json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
