"""Loop edges of a planar pose graph that are really switched off when they disagree.

A robust kernel (Cauchy) only down-weights an edge: a wrong loop edge 1 m off still pulls,
and a few of them bend the front end's trajectory where nothing else says so. Here every
loop edge (a between factor whose vertices are not consecutive: the odometry chain is
never gated) is checked after each optimisation by its Mahalanobis residual under its own
claimed noise (the Gaussian inside the robust model); an edge beyond ``gate_sigma`` is
left out and the graph re-optimised, until the set of edges left out stops changing
(at most ``rounds`` times). An edge left out is checked again at the next estimate and
comes back when it agrees (a switch, not a deletion).

``disagreement`` then measures what the result does to the front end: the Mahalanobis
residual of every odometry factor (the front end's relative poses under their claimed
noise) at the final estimate, reported in metrics.json by the ``region_graph`` back end.

``frontend_check`` asks whether the loop edges show the front end wrong at all: the front
end's own poses (the odometry chain composed from the first vertex) are scored against
every loop edge kept at the result. When each lies within ``sigma`` of its claimed noise,
nothing the edges measured contradicts the front end, and the graph's corrections are
below the edges' own noise: moving the trajectory by them adds that noise (measured on a
real log, FR079: the front end within 1.7 sigma of all 264 edges, and the optimised
trajectory 0.1 - 0.2 cm worse than the front end at revisits). The front end is kept then.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import gtsam
import numpy as np


@dataclass
class GateResult:
    """The optimised values, which factors were left out, and the residuals (sigmas) of
    every factor at those values (NaN for factors that are not between factors)."""

    values: gtsam.Values
    off: np.ndarray
    sigmas: np.ndarray
    rounds: int


def _base_noise(factor) -> gtsam.noiseModel.Base:
    model = factor.noiseModel()
    return model.noise() if isinstance(model, gtsam.noiseModel.Robust) else model


def is_between(factor) -> bool:
    return isinstance(factor, (gtsam.BetweenFactorPose2, gtsam.BetweenFactorPose3))


def is_loop(factor) -> bool:
    """A between factor whose keys are not consecutive (not the odometry chain)."""
    if not is_between(factor):
        return False
    a, b = factor.keys()
    return abs(int(b) - int(a)) != 1


def is_gated(factor) -> bool:
    """A loop edge under a robust kernel: the gate may switch it off. A loop edge its plugin
    gives without one (a front end's own re-anchor on its map, ``region_edges``) is vouched
    for and stays."""
    return is_loop(factor) and isinstance(factor.noiseModel(), gtsam.noiseModel.Robust)


def residual_sigmas(factors: Sequence, values: gtsam.Values) -> np.ndarray:
    """Mahalanobis norm of each between factor's error under its claimed (non-robust)
    noise at ``values``; NaN for other factors or missing keys."""
    out = np.full(len(factors), np.nan)
    for n, f in enumerate(factors):
        if not is_between(f) or not all(values.exists(k) for k in f.keys()):
            continue
        out[n] = float(np.linalg.norm(_base_noise(f).whiten(f.unwhitenedError(values))))
    return out


def optimize_gated(
    factors: Sequence,
    start: gtsam.Values,
    optimize: Callable[[gtsam.NonlinearFactorGraph, gtsam.Values], gtsam.Values],
    gate_sigma: float,
    rounds: int = 3,
) -> GateResult:
    """Optimise ``factors`` from ``start`` with ``optimize``; loop edges beyond
    ``gate_sigma`` at the result are switched off and the rest re-optimised (module
    docstring). ``gate_sigma`` <= 0: no gate (one optimisation)."""
    loop = np.array([is_gated(f) for f in factors], dtype=bool)
    off = np.zeros(len(factors), dtype=bool)
    values, done = start, 0
    while True:
        graph = gtsam.NonlinearFactorGraph()
        for f, o in zip(factors, off, strict=True):
            if not o:
                graph.add(f)
        values = optimize(graph, values)
        done += 1
        sig = residual_sigmas(factors, values)
        if gate_sigma <= 0 or done > rounds:
            return GateResult(values, off, sig, done)
        new_off = loop & (sig > gate_sigma)
        if np.array_equal(new_off, off):
            return GateResult(values, off, sig, done)
        off = new_off


def chain_values(factors: Sequence, start: gtsam.Values) -> gtsam.Values | None:
    """The front end's poses: the first vertex of ``start`` (keys in ascending order)
    composed with the odometry chain (between factors of consecutive keys, Pose2); None
    when the chain does not join every vertex."""
    keys = sorted(int(k) for k in start.keys())
    chain = {}
    for f in factors:
        if isinstance(f, gtsam.BetweenFactorPose2) and not is_loop(f):
            a, b = (int(k) for k in f.keys())
            chain[b if b > a else a] = (a, f.measured()) if b > a else (b, f.measured().inverse())
    out = gtsam.Values()
    out.insert(keys[0], start.atPose2(keys[0]))
    for k in keys[1:]:
        link = chain.get(k)
        if link is None or not out.exists(link[0]):
            return None
        out.insert(k, out.atPose2(link[0]).compose(link[1]))
    return out


@dataclass
class FrontendCheck:
    """The front end's poses scored against the loop edges kept at the result: the largest
    residual (claimed sigmas), and whether the front end is kept (every edge within
    ``sigma``); values: the front end's poses (None without a full chain)."""

    max_sigma: float
    keep_frontend: bool
    values: gtsam.Values | None


def frontend_check(factors: Sequence, gate: GateResult, sigma: float) -> FrontendCheck:
    """Does any loop edge kept at the result contradict the front end by more than
    ``sigma`` of its claimed noise? If none does, the front end is kept (module docstring).
    ``sigma`` <= 0: never kept."""
    fe = chain_values(factors, gate.values) if len(gate.values.keys()) else None
    loop = np.array([is_loop(f) for f in factors], dtype=bool) & ~gate.off
    if fe is None or not loop.any():
        return FrontendCheck(float("nan"), False, fe)
    res = residual_sigmas([f for f, k in zip(factors, loop, strict=True) if k], fe)
    worst = float(np.nanmax(res)) if np.isfinite(res).any() else float("nan")
    return FrontendCheck(worst, bool(sigma > 0 and worst <= sigma), fe)


def disagreement(factors: Sequence, sigmas: np.ndarray, off: np.ndarray) -> dict[str, float]:
    """How far the result lies from the front end (odometry factors, in their sigmas) and
    from the loop edges kept, with the count of loop edges switched off."""
    loop = np.array([is_loop(f) for f in factors], dtype=bool)
    chain = np.array([is_between(f) for f in factors], dtype=bool) & ~loop
    odo = sigmas[chain & np.isfinite(sigmas)]
    kept = sigmas[loop & ~off & np.isfinite(sigmas)]
    odo = odo if len(odo) else np.zeros(1)
    kept = kept if len(kept) else np.zeros(1)
    return {
        "frontend_residual_max_sigma": float(odo.max()),
        "frontend_residual_p99_sigma": float(np.percentile(odo, 99)),
        "frontend_factors_over_3_sigma": float(np.sum(odo > 3.0)),
        # sum of squared residuals per degree of freedom (3 per planar factor): ~1 when
        # the result keeps the front end within its claimed noise, >> 1 when bent
        "frontend_chi2_per_dof": float(np.sum(odo**2) / (3 * len(odo))),
        "loop_residual_max_sigma": float(kept.max()),
        "loop_edges": float(loop.sum()),
        "loop_edges_off": float((loop & off).sum()),
    }
