"""Many objects first seen in one step (issue 10): time and peak memory of that step.

Branching assigns the new objects' classes one object at a time and prunes in between, so the
step's cost should grow linearly with the number of new objects (enumerating all M^|new| class
combinations, as before, could not run 20 objects of 10 classes at all: 10^20 children). Each case
runs in a fresh spawned process so that its peak RSS is its own. Targets: 20 new objects of 10
classes in < 1 s and < 500 MB peak; the baseline is the same world with five new objects, scaled
by the number of objects (linear cost gives a ratio near 1, sub-linear above 1).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import resource
import time

import numpy as np

from bench import Result

TARGET_S = 1.0
TARGET_MB = 500.0
CROWD_SIZES = (1, 5, 10, 20)
CROWD_CLASSES = 10


def _header(name: str, steps: int, alias: list[int], views: list[float]) -> str:
    """A scenario's fields up to its robots: M = len(alias) aliased classes, paper noise, a
    50° / 5 m sensor, range communication."""
    return f"""format = 1
name = "{name}"
steps = {steps}
[classes]
count = {len(alias)}
[classifier]
model = "aliased"
alias = {alias}
best_view_deg = {views}
noise_std = 0.35
[noise]
odometry_var = [0.003, 0.003, 0.001]
geometric_var = [0.1, 0.1, 0.01]
[sensor]
half_angle_deg = 50.0
range = 5.0
[communication]
mode = "range"
range = 10.0
"""


def _object(j: int, x: float, y: float, yaw: float, c: int) -> str:
    return f"\n[[objects]]\nid = {j}\npose = [{x:.4f}, {y:.4f}, {yaw:.4f}]\nclass = {c}\n"


def crowd_text(objects: int, classes: int, seed: int = 0) -> str:
    """One robot at the origin facing +x and ``objects`` objects in its 50° / 5 m view."""
    rng = np.random.default_rng(seed)
    alias = [(c + 1) % classes + 1 for c in range(classes)]
    views = [round(360.0 * c / classes - 180.0, 3) for c in range(classes)]
    text = _header(f"crowd-{objects}", 3, alias, views)
    text += '\n[[robots]]\nid = "r1"\nstart = [0.0, 0.0, 0.0]\nspeed = 0.1\nturns = [[3, 0.0]]\n'
    for j in range(objects):
        r = 1.5 + 3.0 * rng.random()
        a = math.radians(-35.0 + 70.0 * rng.random())
        yaw = float(rng.uniform(-math.pi, math.pi))
        c = int(rng.integers(1, classes + 1))
        text += _object(j + 1, r * math.cos(a), r * math.sin(a), yaw, c)
    return text


def meeting_text(seed: int = 0) -> str:
    """Four robots, 4 classes, 9 objects first seen at step 1 (3 + 2 + 2 + 2)."""
    rng = np.random.default_rng(seed)
    text = _header("four-at-once", 10, [2, 1, 4, 3], [90.0, 90.0, 0.0, 180.0])
    j = 0
    for i, (y, count) in enumerate(((0.0, 3), (8.0, 2), (16.0, 2), (24.0, 2))):
        text += f'\n[[robots]]\nid = "r{i + 1}"\nstart = [0.0, {y}, 0.0]\n'
        text += "speed = 0.25\nturns = [[10, 0.0]]\n"
        for _ in range(count):
            j += 1
            x, dy = 2.0 + 2.0 * rng.random(), rng.uniform(-1.0, 1.0)
            yaw, c = float(rng.uniform(-math.pi, math.pi)), int(rng.integers(1, 5))
            text += _object(j, x, y + dy, yaw, c)
    return text


def _measure(text: str, centralized: bool, queue: mp.Queue[object]) -> None:
    from deploy.base.build import belief_model, belief_rng
    from estimator.hybrid import BeliefConfig, HybridBelief
    from sim.loader import parse_scenario
    from sim.sensors import Simulator

    s = parse_scenario(text, "bench.toml")
    frames = Simulator(s, 0).all_frames()
    robots = list(s.robot_ids) if centralized else [s.robot_ids[0]]
    belief = HybridBelief(belief_model(s), {r: s.robot(r).start for r in robots}, BeliefConfig())
    rng = belief_rng(0, robots)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    times, new = [], []
    for k in range(s.steps):
        known = len(belief.object_ids)
        t = time.perf_counter()
        belief.step([frames[r][k] for r in robots], rng)
        times.append(time.perf_counter() - t)
        new.append(len(belief.object_ids) - known)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    queue.put((times, new, before, peak, len(belief.hypotheses)))


def _run(text: str, centralized: bool = False) -> tuple[list[float], list[int], float, float, int]:
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_measure, args=(text, centralized, queue))
    proc.start()
    out = queue.get(timeout=600)
    proc.join()
    return out


def run() -> list[Result]:
    rows = []
    first_step = {}
    for n in CROWD_SIZES:
        times, new, before, peak, hyps = _run(crowd_text(n, CROWD_CLASSES))
        k = int(np.argmax(new))
        first_step[n] = (times[k], new[k], peak, before, hyps)
    # Per new object, from the 5-object step (a 1-object step has too few children to be typical).
    unit = first_step[5][0] / max(first_step[5][1], 1)
    for n in CROWD_SIZES[1:]:
        t, seen, peak, before, hyps = first_step[n]
        met = "met" if t < TARGET_S and peak < TARGET_MB else "NOT met"
        rows.append(
            Result(
                f"step seeing {seen} new objects of {CROWD_CLASSES} classes",
                seen,
                1e3 * t,
                baseline_ms=1e3 * unit * seen,
                note=(
                    f"baseline: the 5-object step × {seen}/5 (linear cost ≈ 1x); peak RSS "
                    f"{peak:.0f} MB (process before the steps {before:.0f} MB); {hyps} hypotheses; "
                    f"target < {TARGET_S:g} s and < {TARGET_MB:g} MB {met}"
                ),
            )
        )
    times, new, before, peak, hyps = _run(meeting_text(), centralized=True)
    rows.append(
        Result(
            "centralized step, 4 robots see 9 new objects of 4 classes",
            new[0],
            1e3 * times[0],
            note=(
                f"max step {1e3 * max(times):.0f} ms over {len(times)} steps; "
                f"peak RSS {peak:.0f} MB (before {before:.0f} MB); {hyps} hypotheses at the end"
            ),
        )
    )
    return rows
