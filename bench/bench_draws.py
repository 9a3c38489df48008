"""The Monte Carlo error of the weights: one set of draws shared by every parent of a step
(common random numbers, the default) against independent draws per parent, at 500 and 200 draws.

Pruning compares the weights of hypotheses, so what matters is the error of *relative*
log-weights. The evidence computations of real steps are captured on three bundled worlds (local
beliefs, all parents of a step with at least one detection); for each, the children's
log-weights of eight random class assignments of the detections are estimated six times per
estimator and compared, centred over parents and assignments, with a 20 000-draw reference.
Reported: the mean and the largest RMS error (nats) over the captured steps of each world.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.special import logsumexp

from bench import Result
from deploy.build import belief_model, belief_rng
from estimator import hybrid
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


def _captured(world: str) -> list[Case]:
    """Evidence calls of the first two robots' local beliefs on ``world`` (seed ``SEED``)."""
    s = load_scenario(world)
    model = belief_model(s)
    frames = Simulator(s, SEED).all_frames()
    caught: list[Case] = []
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
    finally:
        hybrid.geo_conditioned_batch = real
    return caught[:: max(1, len(caught) // CASES)][:CASES]


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


def run() -> list[Result]:
    rows = []
    for world in WORLDS:
        cases = _captured(world)
        if not cases:
            continue
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
