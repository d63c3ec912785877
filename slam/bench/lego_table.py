"""The runs of paper 001's Table 1 (benchmarks/table_lego.py): the jobs of a scene (main
configs, the ablation of LeGO-LOAM-LPB read from its resolved recipe, the ground factor
added to other front ends), one job run through ``slam.run.run_one`` into a table row, and
the ground rows as replays of the plain run's recorded front end (the ground factor is a
back-end plugin: the front end never sees it)."""

from __future__ import annotations

import json
import signal
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from slam.bench.loop_audit import audit, summary
from slam.bench.loop_replay import Recorder, load_recording, replay, save_recording

BASELINE = "lego_loam"
FULL = "lego_lpb"
NOT_MODULES = ("prior", "odometry")
# Modules switched off by a value rather than an ``enabled`` flag: (key path under
# ``frontend``, label, value that switches it off).
VALUE_SWITCHES = ((("registration", "ground_weight"), "no ground residual", 0.0),)


def available(name: str) -> bool:
    """Whether the recipe ``name`` loads and its front end plugin is installed."""
    from slam.config import load_config
    from slam.errors import SlamError
    from slam.pipeline import resolved_config

    try:
        resolved_config(load_config(name))
    except (SlamError, ImportError, LookupError):
        return False
    return True


def _switches(name: str) -> dict[str, list[str]]:
    """label -> overrides switching off each enabled module of the resolved recipe:
    frontend sections with ``enabled: true``, :data:`VALUE_SWITCHES` and enabled factor
    plugins other than prior / odometry."""
    from slam.config import load_config
    from slam.pipeline import resolved_config

    resolved = resolved_config(load_config(name))
    out: dict[str, list[str]] = {}

    def walk(node: dict, path: list[str]) -> None:
        for key, value in node.items():
            if isinstance(value, dict):
                if value.get("enabled") is True:
                    label = f"no {'.'.join(path[1:] + [key])}"
                    out[label] = [".".join(path + [key, "enabled"]) + "=false"]
                walk(value, path + [key])

    walk(resolved["frontend"], ["frontend"])
    for path, label, off in VALUE_SWITCHES:
        node = resolved["frontend"]
        for key in path:
            node = node.get(key) if isinstance(node, dict) else None
        if node not in (None, off):
            out[label] = [f"frontend.{'.'.join(path)}={off}"]
    for fname, params in resolved["factors"].items():
        if fname not in NOT_MODULES and params.get("enabled", True):
            out[f"no {fname} factor"] = [f"factors.{fname}.enabled=false"]
    return out


def ablation_overrides(name: str = FULL, baseline: str = BASELINE) -> list[tuple[str, list[str]]]:
    """(label, overrides) switching off, one at a time, each module that ``name`` adds to
    ``baseline`` (enabled in ``name``, not enabled in the baseline recipe)."""
    mine = _switches(name)
    base = _switches(baseline) if available(baseline) else {}
    return [(label, over) for label, over in mine.items() if base.get(label) != over]


GROUND_PLUGIN = "slam.ground_factor:GroundFactorPlugin"


def ground_factor_overrides() -> list[str] | None:
    """Overrides adding the ground factor plugin to a recipe: by its entry-point name
    ``ground`` when registered, else by import path; None when it does not exist."""
    from slam import plugins

    for spec, over in (("ground", []), (GROUND_PLUGIN, [f"factors.ground.plugin={GROUND_PLUGIN}"])):
        try:
            plugins.load("slam.factors", spec)
        except Exception:  # noqa: BLE001, S112 - any failure means: not installed
            continue
        return [*over, "factors.ground.enabled=true"]
    return None


def z_errors(res) -> dict:
    """z error (m) of the matched poses: after the table's SE(3) alignment, and from the
    start (the first estimate pose put on the first true pose: the accumulated z drift)."""
    dz = res.est_poses[:, 2, 3] - res.gt_poses[:, 2, 3]
    start = res.gt_poses[0] @ np.linalg.inv(res.est_poses[0])
    dz0 = (start @ res.est_poses)[:, 2, 3] - res.gt_poses[:, 2, 3]
    return {
        "z_rmse": float(np.sqrt(np.mean(dz**2))),
        "z_max": float(np.max(np.abs(dz))),
        "z_drift_rmse": float(np.sqrt(np.mean(dz0**2))),
        "z_drift_end": float(dz0[-1]),
    }


REUSE_KEYS = ("scene", "bag", "gt", "frames", "config", "overrides")


def _same(a, b) -> bool:
    """Equal, overrides compared without the ground plugin's import path (the same
    plugin by entry-point name or by path)."""
    if isinstance(a, list) and isinstance(b, list):
        a, b = ([o for o in x if not o.startswith("factors.ground.plugin=")] for x in (a, b))
    return a == b


def loop_columns(out: Path, gt: Path) -> dict:
    """Odometry APE RMSE, loops, false loops and the median constraint error (m) of a loop
    run (empty without loops.csv)."""
    if not (out / "loops.csv").is_file() or not (out / "graph.g2o").is_file():
        return {}
    from slam.eval.metrics import evaluate

    s = summary(audit(out, gt))
    return {
        "ape_odom_rmse": evaluate(out / "odometry.tum", gt).ape_trans["rmse"],
        "loop_edges": s["loops"],
        "false_loops": s["false"],
        "loop_err_median": s["err_median_m"],
        "loop_err_max": s["err_max_m"],
    }


def run_job(job: dict) -> dict:
    """One config (+ overrides) on one sequence, in its own process; with ``reuse`` the
    row of an earlier identical run in the same folder (``row.json``) is returned."""
    from slam.config import load_config
    from slam.run import run_one

    # a worker started from a background job inherits SIGINT ignored (POSIX): restore
    # Python's handler so that `kill -INT <worker>` stops the run the way Ctrl-C does
    # (the pipeline keeps and evaluates the frames done so far)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    saved = Path(job["out"]) / "row.json"
    if job.get("reuse") and saved.is_file():
        row = json.loads(saved.read_text())
        if all(_same(row.get(k), job[k]) for k in REUSE_KEYS) and "error" not in row:
            keep = {k: job[k] for k in ("index", "label", "group", "out") if k in job}
            return {**row, **keep, "reused": True}
    if job.get("tabulate_only"):
        return {**job, "not_run": True}
    if job.get("replay_of"):
        return replay_job(job)
    config = load_config(job["config"], job["overrides"])
    if job["frames"]:
        config.source.max_frames = job["frames"]
    out = Path(job["out"])
    t0 = time.perf_counter()
    try:
        with recording(job.get("record")) as recorder:
            summary = run_one(Path(job["bag"]), config, out, gt=Path(job["gt"]), quiet=True)
        if recorder is not None:
            _save_recording(recorder, Path(job["record"]), job)
    except Exception as exc:  # noqa: BLE001 - one failing run must not end the table
        return {**job, "error": f"{type(exc).__name__}: {exc}"}
    wall = time.perf_counter() - t0
    metrics = json.loads((out / "metrics.json").read_text())
    return finish_row(job, summary, metrics, wall)


def finish_row(job: dict, summary: dict, metrics: dict, wall: float) -> dict:
    """The table row of a finished run (also saved as ``row.json`` in its folder)."""
    out = Path(job["out"])
    res = summary.get("eval")
    row = {
        **job,
        "frames_run": summary["frames"],
        "keyframes": summary["keyframes"],
        "stopped_by": summary["stopped_by"],
        "fps": metrics.get("frames_per_second"),
        "wall_s": round(wall, 1),
        "loops": metrics.get("loops_closed"),
        "lost": (metrics.get("frontend_counts") or {}).get("tracking_lost"),
    }
    if res is not None:
        row.update(
            ape=res.ape_trans,
            ape_rot=res.ape_rot,
            drift_pct=(res.kitti or {}).get("t_rel_pct"),
            path_m=res.path_length,
            ape_notes=list(res.notes),
            **z_errors(res),
        )
        row.update(loop_columns(out, Path(job["gt"])))
    (out / "row.json").write_text(json.dumps(row, indent=2, default=str))
    return row


@contextmanager
def recording(path: str | None):
    """While active, the front end every Pipeline instantiates is wrapped in a
    :class:`Recorder` (yielded; None without ``path``): run_one builds its own
    Pipeline, so its plugin lookup is wrapped for the duration."""
    if path is None:
        yield None
        return
    from slam import plugins

    holder: list = []
    original = plugins.instantiate

    def instantiate(group, *args, **kwargs):
        obj = original(group, *args, **kwargs)
        if group == "slam.frontends":
            obj = Recorder(obj)
            holder.append(obj)
        return obj

    plugins.instantiate = instantiate
    try:
        yield holder
    finally:
        plugins.instantiate = original


def _save_recording(holder: list, path: Path, job: dict) -> None:
    """The recorded front end output in loop_replay's .npz format."""
    if len(holder) != 1:
        raise RuntimeError(f"expected one recorded front end, got {len(holder)}")
    meta = {"bag": job["bag"], "config": job["config"], "overrides": job["overrides"]}
    save_recording(holder[0], path, meta)


def replay_job(job: dict) -> dict:
    """A back-end variant (the ground factor) of a recorded run: the recording replayed
    with the job's overrides; the row as ``run_job``'s, fps the recorded run's."""
    from slam.run import evaluate_run

    src = Path(job["replay_of"])
    if not src.is_file():
        return {**job, "error": f"no recording {src} (its plain run failed?)"}
    out = Path(job["out"])
    t0 = time.perf_counter()
    try:
        rec = load_recording(src)  # made with the same --frames
        replay(rec, job["config"], job["overrides"], out, None)
        res = evaluate_run(out, Path(job["gt"]), None, title=job["label"])
    except Exception as exc:  # noqa: BLE001 - one failing run must not end the table
        return {**job, "error": f"{type(exc).__name__}: {exc}"}
    wall = time.perf_counter() - t0
    metrics = json.loads((out / "metrics.json").read_text())
    plain = src.parent / "row.json"
    if plain.is_file():
        metrics["frames_per_second"] = json.loads(plain.read_text()).get("fps")
    n = len(rec["stamps"])
    summary = {"frames": n, "keyframes": int(np.sum(rec["is_kf"])), "stopped_by": None,
               "eval": res}  # fmt: skip
    return {**finish_row(job, summary, metrics, wall), "replayed": str(src)}


def jobs_for(
    scene: str, seq, configs, frames, out: Path, ablation: bool, ground_configs=(),
    replay_ground: bool = True,
) -> list[dict]:  # fmt: skip
    base = {"scene": scene, "bag": str(seq.bag), "gt": str(seq.ground_truth), "frames": frames}
    jobs = []

    def add(label: str, config: str, overrides: list[str], group: str) -> None:
        safe = label.replace(" ", "_").replace("/", "_")
        jobs.append({**base, "label": label, "config": config, "overrides": overrides,
                     "group": group, "out": str(out / scene / safe)})  # fmt: skip

    for name in configs:
        add(name, name, [], "main")
    if ablation and FULL in configs:
        for label, over in ablation_overrides(FULL):
            add(f"{FULL} {label}", FULL, over, "ablation")
    ground = ground_factor_overrides() if ground_configs else None
    if ground is not None:
        for name in configs:
            if name in ground_configs:
                add(f"{name} + ground factor", name, ground, "ground")
                if replay_ground:  # the plain run records its front end, this replays it
                    plain = next(j for j in jobs if j["label"] == name)
                    plain["record"] = str(Path(plain["out"]) / "record.npz")
                    jobs[-1]["replay_of"] = plain["record"]
    return jobs
