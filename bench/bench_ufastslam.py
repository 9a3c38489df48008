"""Semantic UFastSLAM: ms per filter step against the particle count, on the `rectangle` world
(about 1.5 observations per step), for plain UFastSLAM and Semantic UFastSLAM with oracle relations.

Baselines, measured in the same run: for plain UFastSLAM, a per-particle loop — one 1-particle
filter step (the same code with a batch of one) times N; for the semantic filter, plain UFastSLAM
at the same N, so the speed-up column shows the relations' overhead (below 1×).
Target (issue 6): ≤ 2 ms per step at 50 particles.
"""

from __future__ import annotations

import numpy as np

from bench import Result, median_seconds
from deploy.study.ufastslam import filter_config
from estimator.ufastslam import Observation, UFastSLAM, UFastSLAMConfig
from sim.ufastslam import Run, UWorld, load_world, simulate

PARTICLES = (10, 50, 100, 200)
WORLD = "rectangle"
SEED = 0
TARGET_PARTICLES = 50
TARGET_MS = 2.0

_notes: list[str] = []


def notes() -> list[str]:
    return list(_notes)


def _replay(world: UWorld, run: Run, config: UFastSLAMConfig, oracle: bool) -> None:
    """Every step of one run, as the command drives it (observations built outside the timer
    would be cheaper by a few µs per step; building them is part of a real step)."""
    slam = UFastSLAM(config, world.start)
    rng = np.random.default_rng(SEED)
    for frame in run.frames:
        obs = [
            Observation(int(i), (float(z[0]), float(z[1])), world.labels[int(i)] if oracle else ())
            for i, z in zip(frame.ids, frame.z, strict=True)
        ]
        slam.step(run.odometry[frame.k - 1], obs, rng)


def _ms_per_step(world: UWorld, run: Run, particles: int, relations: str) -> float:
    config = filter_config(world, particles, relations)
    seconds = median_seconds(lambda: _replay(world, run, config, relations == "labels"), repeats=3)
    return 1e3 * seconds / world.steps


def run() -> list[Result]:
    world = load_world(WORLD)
    sim_run = simulate(world, SEED)
    per_step = sum(len(f.ids) for f in sim_run.frames) / world.steps
    one = _ms_per_step(world, sim_run, 1, "off")
    rows = []
    at_target = None
    for n in PARTICLES:
        plain = _ms_per_step(world, sim_run, n, "off")
        semantic = _ms_per_step(world, sim_run, n, "labels")
        rows.append(
            Result(
                "UFastSLAM step",
                n,
                plain,
                one * n,
                1e3 / plain,
                "steps",
                f"vs a per-particle loop (1-particle step × N); {per_step:.2f} obs/step",
            )
        )
        rows.append(
            Result(
                "Semantic UFastSLAM step (oracle)",
                n,
                semantic,
                plain,
                1e3 / semantic,
                "steps",
                "vs plain UFastSLAM at the same N",
            )
        )
        if n == TARGET_PARTICLES:
            at_target = (plain, semantic)
    if at_target is not None:
        met = "met" if max(at_target) <= TARGET_MS else "NOT met"
        _notes.append(
            f"UFastSLAM target ≤ {TARGET_MS} ms/step at {TARGET_PARTICLES} particles: {met} "
            f"(plain {at_target[0]:.2f} ms, semantic {at_target[1]:.2f} ms, {WORLD} seed {SEED}, "
            f"{per_step:.2f} observations per step, {world.steps} steps)"
        )
    return rows
