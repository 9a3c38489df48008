"""iSAM2's partial relinearisation check (``BeliefConfig.partial_relinearization``, the default)
against checking every variable: the local beliefs' step times and accuracy on three worlds.

Every robot's local belief runs once with each setting, one right after the other (so a machine
whose speed drifts treats both alike), on ``paper``, ``lanes`` and ``rendezvous`` with seeds 0–2.
Accuracy every 15th step and at the last: the weighted mean object position's error against the
truth and the class log-loss of the true class (clipped at 1e-12), over every known object.
"""

from __future__ import annotations

import time

import numpy as np

from bench import Result
from deploy.base.build import belief_model, belief_rng
from deploy.study.runner import true_objects
from estimator.factors import object_key
from estimator.hybrid import BeliefConfig, HybridBelief
from sim.loader import load_scenario
from sim.sensors import Simulator

WORLDS = ("paper", "lanes", "rendezvous")
SEEDS = (0, 1, 2)
SCORE_EVERY = 15
SETTINGS = {
    "partial check": BeliefConfig(),
    "full check": BeliefConfig(partial_relinearization=False),
}

_notes: list[str] = []


def notes() -> list[str]:
    return list(_notes)


def _runs() -> dict[str, dict[str, list[float]]]:
    out: dict[str, dict[str, list[float]]] = {
        name: {"ms": [], "error": [], "log_loss": []} for name in SETTINGS
    }
    for world in WORLDS:
        s = load_scenario(world)
        model = belief_model(s)
        truth = true_objects(s)
        for seed in SEEDS:
            frames = Simulator(s, seed).all_frames()
            for robot in s.robot_ids:
                for name, config in SETTINGS.items():
                    belief = HybridBelief(model, {robot: s.robot(robot).start}, config)
                    rng = belief_rng(seed, [robot])
                    got = out[name]
                    for k in range(1, s.steps + 1):
                        t = time.perf_counter()
                        belief.step([frames[robot][k - 1]], rng)
                        got["ms"].append(1e3 * (time.perf_counter() - t))
                        if k % SCORE_EVERY == 0 or k == s.steps:
                            _score(belief, truth, got)
    return out


def _score(
    belief: HybridBelief, truth: dict[int, tuple[np.ndarray, int]], got: dict[str, list[float]]
) -> None:
    w = belief.weights()
    marginals = belief.class_marginals()
    for i, j in enumerate(belief.object_ids):
        mean = w @ np.array([h.pose(object_key(j))[:2] for h in belief.hypotheses])
        pose, true_class = truth[j]
        got["error"].append(float(np.linalg.norm(mean - pose[:2])))
        got["log_loss"].append(-float(np.log(max(marginals[i, true_class], 1e-12))))


def run() -> list[Result]:
    _notes.clear()
    out = _runs()
    base = np.array(out["full check"]["ms"])
    rows = []
    for name, got in out.items():
        ms = np.array(got["ms"])
        p50, p95, p99 = np.percentile(ms, [50, 95, 99])
        b50, b95, b99 = np.percentile(base, [50, 95, 99])
        rows.append(
            Result(
                f"local step, {name} (3 worlds × 3 seeds)",
                len(ms),
                float(p50),
                float(b50),
                note=f"p95 {p95:.0f} ms ({b95 / p95:.2f}×), p99 {p99:.0f} ms ({b99 / p99:.2f}×), "
                f"max {ms.max():.0f} ms, all steps {ms.sum() / 1e3:.1f} s "
                f"({base.sum() / ms.sum():.2f}×); baseline: full check",
            )
        )
        _notes.append(
            f"{name}: object position error mean {np.mean(got['error']):.4f} m "
            f"(p95 {np.percentile(got['error'], 95):.4f}), class log-loss mean "
            f"{np.mean(got['log_loss']):.4f} (max {np.max(got['log_loss']):.3f}) over "
            f"{len(got['error'])} (object, scored step) pairs"
        )
    return rows
