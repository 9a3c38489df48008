"""Issue 40's curves: how accuracy, time, bytes and memory grow with the map and with the mission.

Map size: generated worlds of n = 30, 60, 120, 300 objects at the dense world's density (120
objects in a 30 m square, `semfleet scenario generate --robots 4 --objects 120 --classes 4 --seed
9002 --steps 400 --area 30`), the mission long enough for each robot to see most of the map
(400 steps at 120 objects, in proportion to n). At a sparse density a robot's map grows only as
n^0.4 and hides the cost. Every point runs local, distributed and centralized once per class
representation (per-object classes with the sparse and the dense ξ, the dense ξ once more with
every slot linearised at its owner's local point instead of its fused estimate, the reference
before ``BeliefConfig.slot_linearisation``, and the joint table as the baseline), each in a
process of its own with a wall-time budget: a point that does not finish
within it is reported as such.

Per point: r1's own slot at the last step on the wire, per object (its ξ with the ids, and its
class data) and the stack header apart; the mean delivered stack; step p50 / p99 / max per
method; D − C and D − L at the last step (robot and object error, class log-loss); empty joins
and rebuilds; the worker's peak RSS.

Mission length: `--robots 3 --objects 60 --classes 3 --seed 9100 --area 40`, up to 2,000 steps,
and the same fleet on a map it knows by the third tenth (`--seed 9101 --area 20`; the sparse
and dense ξ and every pose only): the mean step of every method in each tenth of the mission,
the last tenth against the third, for each representation (per-object ones with the default
window of poses, ``BeliefConfig.window``), and for the per-object belief once more with every
pose kept (the baseline of the same run), with every pose and the relinearisation threshold
fixed at 10⁻³, and with the window's marginal linear (its first form): each row also gives
every method's robot and object error at the last step, so that the time is read beside the
accuracy.

``SEMFLEET_BENCH_MAPSCALE_SIZES`` (default ``30,60,120,300``), ``SEMFLEET_BENCH_MAPSCALE_STEPS``
(the long mission, default 2000) and ``SEMFLEET_BENCH_MAPSCALE_BUDGET`` (seconds per point,
default 900) shrink it for a quick look.
"""

from __future__ import annotations

import math
import os
import resource
import time
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from multiprocessing import get_context

import numpy as np

from bench import Result, format_table
from deploy.base.build import belief_model, belief_rng
from deploy.study.runner import run_single
from deploy.study.types import RunResult
from estimator.hybrid import BeliefConfig, HybridBelief
from estimator.slots import summarise
from estimator.summary import Slot
from protocol.codec import Limits, StackMessage, encode, with_wire
from protocol.stack import Stack
from sim.generate import generate_scenario
from sim.scenario import Scenario
from sim.sensors import Simulator

METHODS = ["local", "distributed", "centralized"]
DENSITY = 120 / 30.0**2  # objects per m² of the dense world
SIZES = tuple(
    int(n) for n in os.environ.get("SEMFLEET_BENCH_MAPSCALE_SIZES", "30,60,120,300").split(",")
)
LONG_STEPS = int(os.environ.get("SEMFLEET_BENCH_MAPSCALE_STEPS", "2000"))
BUDGET_S = float(os.environ.get("SEMFLEET_BENCH_MAPSCALE_BUDGET", "900"))
# Per-object classes with the sparse ξ and with the dense ξ (the default, xi = "auto", is the
# dense one up to 32 objects in a slot and the sparse one above; each with the default
# window of poses and slots linearised at the fused estimate), the dense ξ at L's own point, and
# the joint table (with the dense ξ, every pose) as the baseline each is measured against in the
# same run.
CLASSES = {
    "per_object sparse ξ": BeliefConfig(classes="per_object", xi="sparse"),
    "per_object dense ξ": BeliefConfig(classes="per_object", xi="dense"),
    "per_object dense ξ, slot at L's point": BeliefConfig(
        classes="per_object", xi="dense", slot_linearisation="local"
    ),
    "joint": BeliefConfig.joint(),
}
# The long mission also runs the per-object belief with every pose kept (the default before the
# window), once more with the relinearisation threshold fixed at 10⁻³ (the default before it
# followed the motion model), and with the window's marginal linear (its first form), so that the
# step's growth and the error are compared with each in the same run.
MISSION_ONLY = {
    "per_object dense ξ, every pose": BeliefConfig(classes="per_object", xi="dense", window=None),
    "per_object dense ξ, every pose, threshold 1e-3": BeliefConfig(
        classes="per_object", xi="dense", window=None, relinearize_threshold=1e-3
    ),
    "per_object dense ξ, linear marginal": BeliefConfig(
        classes="per_object", xi="dense", window_marginal="linear"
    ),
}
CONFIGS = {**CLASSES, **MISSION_ONLY}
SEED = 1

_notes: list[str] = []


def notes() -> list[str]:
    return list(_notes)


@dataclass(frozen=True)
class _Point:
    """One run of a sweep: the result and the worker's peak resident set in MiB."""

    result: RunResult
    peak_rss_mib: float
    slot: tuple[int, int, int, int]


def _run_point(
    robots: int, objects: int, classes: int, world: int, steps: int, area: float, kind: str
) -> _Point:
    s = generate_scenario(robots, objects, classes, world, steps=steps, area=area)
    scored = {max(1, round(steps * t / 10)) for t in range(1, 11)}
    result = run_single(s, METHODS, SEED, CONFIGS[kind], None, None, scored)
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return _Point(result, rss, _slot_bytes(s, kind))


def _slot_bytes(s: Scenario, kind: str) -> tuple[int, int, int, int]:
    """r1's own slot at the last step, on the wire: (objects, whole slot bytes, class bytes,
    bytes of a one-slot stack's header). Class bytes: 4·M per object (per-object φ) or the
    realisation table's classes and log φ."""
    config = CONFIGS[kind]
    belief = HybridBelief(belief_model(s), {"r1": s.robot("r1").start}, config)
    rng = belief_rng(SEED, ["r1"])
    for f in Simulator(s, SEED).all_frames()["r1"]:
        belief.step([f], rng)
    summary = summarise(belief)
    if summary is None:
        return 0, 0, 0, 0
    slot = with_wire(Slot("r1", s.steps, summary), Limits(num_classes=s.num_classes))
    assert slot.wire is not None
    n = len(summary.object_ids)
    if summary.per_object is not None:
        class_bytes = 4 * s.num_classes * n
    else:
        class_bytes = len(summary.realisations) * (n + 9)  # classes (1 B each) and log φ (f64)
    stack = encode(StackMessage("r1", None, Stack((slot,)), s.steps))
    return n, len(slot.wire.data), class_bytes, len(stack) - len(slot.wire.data)


def _in_process(budget: float, *args: object) -> _Point | None:
    """``_run_point(*args)`` in a fresh spawned process, None if it takes longer than ``budget``
    seconds (the process is then killed)."""
    pool = ProcessPoolExecutor(1, mp_context=get_context("spawn"))
    try:
        return pool.submit(_run_point, *args).result(timeout=budget)  # type: ignore[arg-type]
    except FutureTimeout:
        for p in list(getattr(pool, "_processes", {}).values()):
            p.kill()
        return None
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def _last(result: RunResult, method: str, metric: str) -> float:
    return float(np.nanmean(result.metrics[method][metric][:, -1]))


def _map_rows() -> list[Result]:
    rows = []
    for n in SIZES:
        area = math.sqrt(n / DENSITY)
        steps = max(100, round(400 * n / 120))
        for kind in CLASSES:
            start = time.perf_counter()
            point = _in_process(BUDGET_S, 4, n, 4, 9002, steps, area, kind)
            wall = time.perf_counter() - start
            name = f"map n={n} ({steps} steps, {area:.0f} m), {kind}"
            if point is None:
                rows.append(Result(name, n, 1e3 * wall, note=f"did not finish in {BUDGET_S:g} s"))
                continue
            r = point.result
            steps_ms = {m: np.percentile(r.step_ms[m], [50, 99, 100]) for m in METHODS}
            d_c = _last(r, "distributed", "robot_error") - _last(r, "centralized", "robot_error")
            d_l = _last(r, "distributed", "robot_error") - _last(r, "local", "robot_error")
            o_dc = _last(r, "distributed", "object_error") - _last(r, "centralized", "object_error")
            ll = {m: _last(r, m, "class_log_loss") for m in METHODS}
            times = "; ".join(f"{m} {v[0]:.1f}/{v[1]:.1f}/{v[2]:.0f}" for m, v in steps_ms.items())
            objects, slot_b, class_b, header_b = point.slot
            bytes_note = (
                f"r1's slot: {objects} objects, {slot_b / max(1, objects):,.0f} B/object "
                f"({(slot_b - class_b) / max(1, objects):,.0f} ξ and ids, "
                f"{class_b / max(1, objects):,.0f} classes), stack header {header_b} B; "
            )
            if r.stack_bytes.get("distributed"):
                bytes_note += f"stack mean {np.mean(r.stack_bytes['distributed']) / 1e3:,.0f} kB; "
            empty = sum(r.empty_joins.get("distributed", []))
            rebuilds = sum(r.rebuilds.get("distributed", []))
            bytes_note += f"empty joins {empty}, rebuilds {rebuilds}; "
            rows.append(
                Result(
                    name,
                    n,
                    1e3 * wall,
                    note=f"{bytes_note}step ms p50/p99/max {times}; last step: robot error D−C "
                    f"{d_c:+.3f} m, D−L {d_l:+.3f} m, object error D−C {o_dc:+.3f} m; class "
                    f"log-loss L/D/C {ll['local']:.3f}/{ll['distributed']:.3f}/"
                    f"{ll['centralized']:.3f}; peak RSS {point.peak_rss_mib:,.0f} MiB",
                )
            )
    return rows


def _tenths(ms: list[float], robots: int) -> np.ndarray:
    """Mean step (ms) in each tenth of the mission: ``ms`` holds one entry per robot step, robot
    by robot within a step."""
    per_step = np.asarray(ms, dtype=float).reshape(-1, robots).mean(axis=1)
    return np.array([chunk.mean() for chunk in np.array_split(per_step, 10)])


# The long missions: (world seed, area in m, the representations run on it). On the 40 m map each
# robot keeps finding objects until the end (r1 knows 25 in the third tenth, 56 in the last), so a
# step that follows the map grows with it; on the 20 m map each robot knows 50-59 of the 60 objects
# by the third tenth, so what grows there is the mission's own cost.
MISSIONS = (
    (9100, 40.0, tuple(CONFIGS)),
    (9101, 20.0, ("per_object sparse ξ", "per_object dense ξ", "per_object dense ξ, every pose")),
)


def _mission_rows() -> list[Result]:
    rows = []
    for world_seed, area, kinds in MISSIONS:
        rows += _missions(world_seed, area, kinds)
    return rows


def _missions(world_seed: int, area: float, kinds: tuple[str, ...]) -> list[Result]:
    rows = []
    for kind in kinds:
        start = time.perf_counter()
        point = _in_process(BUDGET_S, 3, 60, 3, world_seed, LONG_STEPS, area, kind)
        wall = time.perf_counter() - start
        name = f"mission {LONG_STEPS} steps (60 objects, 3 robots, {area:g} m), {kind}"
        if point is None:
            rows.append(
                Result(name, LONG_STEPS, 1e3 * wall, note=f"did not finish in {BUDGET_S:g} s")
            )
            continue
        r = point.result
        parts, errors = [], []
        for m in METHODS:
            t = _tenths(r.step_ms[m], 3 if m != "centralized" else 1)
            parts.append(f"{m} {t[2]:.1f} → {t[-1]:.1f} ms ({t[-1] / t[2]:.2f}×)")
            _notes.append(f"{name}: {m} mean step per tenth (ms) {np.round(t, 1).tolist()}")
            robot = float(np.nanmean(r.metrics[m]["robot_error"][:, -1]))
            obj = float(np.nanmean(r.metrics[m]["object_error"][:, -1]))
            errors.append(f"{m} {robot:.3f} / {obj:.3f} m")
        rows.append(
            Result(
                name,
                LONG_STEPS,
                1e3 * wall,
                note="third → last tenth mean step: " + "; ".join(parts) + " (target ≤ 1.5×); "
                "robot / object error at the last step: " + "; ".join(errors) + "; "
                f"peak RSS {point.peak_rss_mib:,.0f} MiB",
            )
        )
    return rows


def run() -> list[Result]:
    _notes.clear()
    return _map_rows() + _mission_rows()


if __name__ == "__main__":
    print(format_table(run()))
    for line in notes():
        print(f"- {line}")
