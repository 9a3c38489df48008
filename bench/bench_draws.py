"""The Monte Carlo error of the weights: one set of draws shared by every parent of a step
(common random numbers, the default) against independent draws per parent, at 500 and 200 draws.

Pruning compares the weights of hypotheses, so what matters is the error of *relative*
log-weights. The evidence computations of real steps are captured on three bundled worlds (local
beliefs, all parents of a step with at least one detection); for each, the children's
log-weights of eight random class assignments of the detections are estimated six times per
estimator and compared, centred over parents and assignments, with a 20 000-draw reference.
Reported: the mean and the largest RMS error (nats) over the captured steps of each world; and,
in the notes, how much the hypotheses' Gaussians of an object differ (why shared draws cancel).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.special import logsumexp

from bench import Result
from deploy.base.build import belief_model, belief_rng
from estimator import hybrid
from estimator.factors import object_key
from estimator.hybrid import BeliefConfig, HybridBelief
from estimator.weights import InvolvedGaussian, SemanticTerms, geo_conditioned_batch
from sim.loader import load_scenario
from sim.sensors import Simulator

WORLDS = ("paper", "lanes", "rendezvous")
SEED = 2
CASES = 12
REPEATS = 6
ASSIGNMENTS = 8
REFERENCE_DRAWS = 20_000
ESTIMATORS = (("independent", 500), ("common", 500), ("common", 200))

Case = tuple[list[InvolvedGaussian], SemanticTerms, Any]


def _spread(belief: HybridBelief) -> list[tuple[float, float]]:
    """Per object and axis (x, y): the weighted spread of its mean across the hypotheses over
    its σ, and the largest over the smallest σ across them."""
    w = belief.weights()
    out = []
    for j in belief.object_ids:
        key = object_key(j)
        xy = np.array([h.pose(key)[:2] for h in belief.hypotheses])
        var = np.array([np.diag(h.isam.marginalCovariance(key))[:2] for h in belief.hypotheses])
        spread = np.sqrt(w @ (xy - w @ xy) ** 2) / np.sqrt(w @ var)
        ratio = np.sqrt(var.max(axis=0) / var.min(axis=0))
        out += list(zip(spread.tolist(), ratio.tolist(), strict=True))
    return out


def _captured(world: str) -> tuple[list[Case], list[tuple[float, float]]]:
    """Evidence calls of the first two robots' local beliefs on ``world`` (seed ``SEED``), and
    ``_spread`` at every 15th step."""
    s = load_scenario(world)
    model = belief_model(s)
    frames = Simulator(s, SEED).all_frames()
    caught: list[Case] = []
    spreads: list[tuple[float, float]] = []
    real = hybrid.geo_conditioned_batch

    def spy(gs: Sequence[InvolvedGaussian], terms: SemanticTerms, m: Any, eps: Any) -> Any:
        if len(gs) >= 2 and len(terms.z) >= 1:
            caught.append((list(gs), terms, m))
        return real(gs, terms, m, eps)

    hybrid.geo_conditioned_batch = spy  # type: ignore[assignment]
    try:
        for r in s.robot_ids[:2]:
            belief = HybridBelief(model, {r: s.robot(r).start}, BeliefConfig())
            rng = belief_rng(SEED, [r])
            for k in range(1, s.steps + 1):
                belief.step([frames[r][k - 1]], rng)
                if k % 15 == 0 and len(belief.hypotheses) > 1:
                    spreads += _spread(belief)
    finally:
        hybrid.geo_conditioned_batch = real
    return caught[:: max(1, len(caught) // CASES)][:CASES], spreads


def _log_weights(case: Case, draws: int, rng: np.random.Generator, common: bool) -> Any:
    """(P, ASSIGNMENTS) children's log-weight increments of the fixed assignments."""
    gs, terms, model = case
    n = len(gs[0].info)
    if common:
        base, ll = geo_conditioned_batch(gs, terms, model, rng.standard_normal((draws, n)))
    else:  # independent draws: one parent at a time, each with draws of its own
        parts = [
            geo_conditioned_batch([g], terms, model, rng.standard_normal((draws, n))) for g in gs
        ]
        base = np.concatenate([b for b, _ in parts])
        ll = np.concatenate([x for _, x in parts])
    d = len(terms.z)
    assign = np.random.default_rng(7).integers(0, model.num_classes, (ASSIGNMENTS, d))
    total = base[:, :, None] + ll[:, :, np.arange(d)[None, :], assign].sum(axis=-1)
    return logsumexp(total, axis=1) - np.log(draws)


def _errors(cases: list[Case], draws: int, common: bool) -> tuple[list[float], float]:
    """Per case the RMS error of the centred log-weights (mean over repeats), and ms per call."""
    out, seconds, calls = [], 0.0, 0
    for case in cases:
        ref = _log_weights(case, REFERENCE_DRAWS, np.random.default_rng(1), True)
        ref = ref - ref.mean()
        errs = []
        for rep in range(REPEATS):
            t = time.perf_counter()
            est = _log_weights(case, draws, np.random.default_rng(100 + rep), common)
            seconds += time.perf_counter() - t
            calls += 1
            errs.append(float(np.sqrt(np.mean((est - est.mean() - ref) ** 2))))
        out.append(float(np.mean(errs)))
    return out, 1e3 * seconds / max(calls, 1)


_notes: list[str] = []


def notes() -> list[str]:
    return list(_notes)


def run() -> list[Result]:
    _notes.clear()
    rows = []
    for world in WORLDS:
        cases, spreads = _captured(world)
        if not cases:
            continue
        spread, ratio = np.array(spreads).T
        _notes.append(
            f"{world}: an object's mean across the hypotheses spreads by a median "
            f"{100 * np.median(spread):.2f} % of its σ "
            f"(p95 {100 * np.percentile(spread, 95):.1f} %, max {100 * spread.max():.1f} %); "
            f"its σ varies by a median {100 * (np.median(ratio) - 1):.2f} % across them "
            f"(max {100 * (ratio.max() - 1):.1f} %)"
        )
        for kind, draws in ESTIMATORS:
            errs, ms = _errors(cases, draws, kind == "common")
            how = "one call per parent" if kind == "independent" else "one call"
            rows.append(
                Result(
                    f"weights, {kind} draws × {draws} ({world})",
                    len(cases),
                    ms,
                    note=f"RMS error of relative log-weights vs {REFERENCE_DRAWS:,} draws: mean "
                    f"{np.mean(errs):.4f}, max {np.max(errs):.4f} nats over {len(cases)} steps; "
                    f"ms: a step's evidence ({how})",
                )
            )
    return rows
