"""Vectorised models against per-sample loops, and the sensor simulator's frame rate.

Baselines are measured in the same run on ``BASELINE_ITEMS`` items and scaled linearly to N, which
keeps the whole suite fast; a per-item Python loop has no economies of scale to lose.
"""

from __future__ import annotations

from functools import partial

import gtsam
import numpy as np
from scipy.stats import multivariate_normal

from bench import Result, median_seconds
from estimator.models import AliasedClassifier, SensorFrame, se2
from sim.generate import generate_scenario
from sim.loader import load_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator

SIZES = (1_000, 10_000)
BASELINE_ITEMS = 1_000
CLASSES = 5
SEED = 0


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) poses in a 40 m square with uniform headings."""
    return np.column_stack([rng.uniform(-20, 20, (n, 2)), rng.uniform(-np.pi, np.pi, n)])


def _scaled_baseline_ms(seconds_for_baseline_items: float, n: int) -> float:
    return 1e3 * seconds_for_baseline_items * n / BASELINE_ITEMS


def bench_retract() -> list[Result]:
    """se2.retract on (N, 3) poses and tangents vs a loop of gtsam.Pose2.retract."""
    rng = np.random.default_rng(SEED)
    poses = _random_poses(rng, max(SIZES))
    tangents = rng.normal(0.0, [0.3, 0.3, 0.1], (max(SIZES), 3))
    gtsam_poses = [gtsam.Pose2(*map(float, p)) for p in poses[:BASELINE_ITEMS]]
    gtsam_tangents = list(tangents[:BASELINE_ITEMS])

    def loop() -> list[gtsam.Pose2]:
        return [p.retract(v) for p, v in zip(gtsam_poses, gtsam_tangents, strict=True)]

    baseline = median_seconds(loop, repeats=3)
    rows = []
    for n in SIZES:
        seconds = median_seconds(partial(se2.retract, poses[:n], tangents[:n]))
        rows.append(
            Result(
                "se2.retract",
                n,
                1e3 * seconds,
                _scaled_baseline_ms(baseline, n),
                n / seconds,
                "poses",
                f"vs gtsam.Pose2.retract loop, Pose2s prebuilt ({BASELINE_ITEMS}, scaled)",
            )
        )
    return rows


def bench_log_likelihood() -> list[Result]:
    """AliasedClassifier.log_likelihood (M = 5) on N scores vs a scipy logpdf loop."""
    rng = np.random.default_rng(SEED)
    model = AliasedClassifier.random(CLASSES, rng)
    psi = rng.uniform(-np.pi, np.pi, max(SIZES))
    z = model.mean(0, psi) + rng.normal(0.0, 0.35, (max(SIZES), CLASSES))
    # The loop gets its means and covariance for free: only the density is timed.
    means = model.mean(0, psi[:BASELINE_ITEMS])
    cov = model.cov(0, 0.0)
    z_base = z[:BASELINE_ITEMS]

    def loop() -> list[float]:
        return [
            multivariate_normal.logpdf(zi, mi, cov) for zi, mi in zip(z_base, means, strict=True)
        ]

    baseline = median_seconds(loop, repeats=3)
    rows = []
    for n in SIZES:
        seconds = median_seconds(partial(model.log_likelihood, z[:n], 0, psi[:n]))
        rows.append(
            Result(
                f"AliasedClassifier.log_likelihood M={CLASSES}",
                n,
                1e3 * seconds,
                _scaled_baseline_ms(baseline, n),
                n / seconds,
                "scores",
                f"vs scipy logpdf loop, means given ({BASELINE_ITEMS}, scaled)",
            )
        )
    return rows


def _simulator_row(label: str, scenario: Scenario) -> Result:
    def simulate() -> dict[str, list[SensorFrame]]:
        return Simulator(scenario, SEED).all_frames()

    frames = simulate()
    n_frames = sum(len(f) for f in frames.values())
    n_detections = sum(len(f.detections) for fs in frames.values() for f in fs)
    seconds = median_seconds(simulate, repeats=3)
    note = f"{len(scenario.robot_ids)} robots, {len(scenario.objects)} objects, {n_detections} det."
    return Result(
        label, n_frames, 1e3 * seconds, per_second=n_frames / seconds, unit="frames", note=note
    )


def bench_simulator() -> list[Result]:
    """Simulator(...).all_frames() on the paper scenario and on a generated 10-robot world."""
    generated = generate_scenario(robots=10, objects=200, classes=CLASSES, seed=SEED)
    return [
        _simulator_row("Simulator.all_frames paper", load_scenario("paper")),
        _simulator_row("Simulator.all_frames r10-o200-c5", generated),
    ]


def run() -> list[Result]:
    return bench_retract() + bench_log_likelihood() + bench_simulator()
