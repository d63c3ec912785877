"""Loop-closure experiments without re-running the front end: record once, replay many.

The front end never sees the back end (DESIGN.md), so a run's odometry and keyframe clouds
do not depend on the loop closure: :func:`record` runs a recipe's front end once over a bag
and stores every frame's Odometry (pose, relative motion, information, keyframe flag, the
keyframes' clouds and scalar extras) in one .npz; :func:`replay` feeds those to a Pipeline
with any factor / back-end settings and writes the usual run outputs. A replay gives the
same trajectory as ``slam run`` of the same recipe (the loop plugin reads only keyframes and
estimates).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from slam import plugins
from slam.bench.loop_audit import audit, summary
from slam.config import load_config
from slam.types import FrameDiagnostics, Odometry, Scan


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


def save_recording(rec: Recorder, path: Path, meta: dict[str, Any]) -> None:
    """What ``rec`` kept, as the .npz that :func:`load_recording` reads (``meta`` as JSON)."""
    rows = rec.rows
    idx = np.array(sorted(rec.clouds), dtype=np.int64)
    np.savez(
        path,
        stamps=np.array([r["stamp"] for r in rows]),
        poses=np.stack([r["pose"] for r in rows]),
        is_kf=np.array([r["kf"] for r in rows]),
        relative=np.stack([r["relative"] for r in rows]),
        info=np.stack([r["info"] for r in rows]),
        info_raw=np.stack([r["info_raw"] for r in rows]),
        cloud_frames=idx,
        cloud_sizes=np.array([len(rec.clouds[i]) for i in idx], dtype=np.int64),
        clouds=np.concatenate([rec.clouds[i] for i in idx]) if len(idx) else np.zeros((0, 3)),
        extras=json.dumps([r["extras"] for r in rows]),
        meta=json.dumps(meta),
    )


def record(bag: Path, config: str, out: Path, overrides: list[str], max_frames: int | None) -> None:
    """The recipe's front end (loop closure off) over ``bag``, recorded to ``out`` (.npz)."""
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
    meta = {"bag": str(bag), "config": config, "overrides": overrides, "cpu_seconds": cpu}
    save_recording(rec, out, meta)
    print(f"recorded {len(rec.rows)} frames, {len(rec.clouds)} keyframes, {cpu:.0f} CPU s -> {out}")


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
            diagnostics=_diagnostics(self.extras[i]),
        )  # fmt: skip


def _diagnostics(flat: dict[str, Any]) -> FrameDiagnostics:
    """The recorded flat scalars as typed diagnostics (the run averages their counts)."""
    numbers = {
        k: float(v)
        for k, v in flat.items()
        if isinstance(v, (int, float)) and not isinstance(v, bool) and k != "rejected"
    }
    return FrameDiagnostics(
        rejected=bool(flat.get("rejected", False)),
        skipped=flat.get("skipped") if isinstance(flat.get("skipped"), str) else None,
        degenerate=bool(flat.get("degenerate", False)),
        counts={k: v for k, v in numbers.items() if not k.endswith("_ms")},
        timings_ms={k: v for k, v in numbers.items() if k.endswith("_ms")},
    )


def load_recording(path: Path) -> dict[str, Any]:
    """A recording of :func:`record` / :func:`save_recording`: array name -> array."""
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
