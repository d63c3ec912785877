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
    loop = np.array([is_loop(f) for f in factors], dtype=bool)
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
