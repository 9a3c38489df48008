"""Chaos: the faults of a launch — loss, partitions, kills, restarts — and the garbage generator.

Loss and partitions are the simulator's (the conductor's link model decides who hears whom);
kills and restarts happen after the named step is done, a kill before a restart of the same step;
garbage stacks are published on the stack keys while the run goes on.
"""

from __future__ import annotations

import asyncio
import math
import random
import time
from collections.abc import Sequence
from dataclasses import dataclass

import msgpack
import numpy as np

from agents.links import Partition
from agents.transport.base import Keys, Transport
from deploy.launch.errors import PlanError
from estimator.summary import LocalSummary, ObjectClasses, Realisation, Xi

GARBAGE_BURST = 200
KILL, RESTART = "kill", "restart"


@dataclass(frozen=True, slots=True)
class Faults:
    """Chaos: seeded loss, partitions, kills and restarts (robot, step), garbage per second."""

    drop: float = 0.0
    partitions: tuple[Partition, ...] = ()
    kills: tuple[tuple[str, int], ...] = ()
    restarts: tuple[tuple[str, int], ...] = ()
    garbage_rate: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.drop <= 1.0:
            raise PlanError(f"drop {self.drop:g}: a probability needs 0 ≤ p ≤ 1")
        if not (math.isfinite(self.garbage_rate) and self.garbage_rate >= 0):
            raise PlanError(f"garbage {self.garbage_rate:g}: stacks per second need a rate ≥ 0")

    def schedule(self) -> list[tuple[int, str, str]]:
        """(step, kill|restart, robot) in the order they happen: by step, a kill before a
        restart of the same step."""
        events = [(k, KILL, r) for r, k in self.kills] + [(k, RESTART, r) for r, k in self.restarts]
        return sorted(events)  # "kill" < "restart"

    def check(self, robots: Sequence[str], steps: int, lockstep: bool) -> None:
        """Raise :class:`PlanError` unless every fault names a robot of the run and a step in
        1..``steps``, and every restart follows a kill of the same robot. In lock-step a killed
        robot must restart at the same step: the next round waits for every robot."""
        known = ", ".join(robots)
        for p in self.partitions:
            what = f"partition {describe_partition(p)}"
            unknown = sorted(set(p.group) - set(robots))
            if unknown:
                raise PlanError(f"{what}: no robot {', '.join(unknown)} in this run ({known})")
            if not 1 <= p.first <= p.last <= steps:
                raise PlanError(f"{what}: steps outside the run's 1..{steps}")
        down: dict[str, int] = {}
        for k, kind, r in self.schedule():
            what = f"{kind} {r}@{k}"
            if r not in robots:
                raise PlanError(f"{what}: no robot {r} in this run ({known})")
            if not 1 <= k <= steps:
                raise PlanError(f"{what}: step outside the run's 1..{steps}")
            if kind == KILL and r in down:
                raise PlanError(f"{what}: {r} is down since its kill at step {down[r]}")
            if kind == RESTART and r not in down:
                raise PlanError(f"{what}: a restart needs an earlier kill of {r}")
            if kind == RESTART and lockstep and down[r] != k:
                raise PlanError(f"{what}: in lock-step a killed robot restarts at its kill step")
            if kind == KILL:
                down[r] = k
            else:
                del down[r]
        if lockstep and down:
            r, k = next(iter(down.items()))
            raise PlanError(f"kill {r}@{k}: in lock-step a killed robot restarts at its kill step")

    def describe(self) -> str:
        """One line for people: ``drop 0.2, partition r1 | rest at steps 5–10, kill r2@5, ...``."""
        parts = [f"drop {self.drop:g}"]
        parts += [f"partition {describe_partition(p)}" for p in self.partitions]
        parts += [f"{kind} {r}@{k}" for k, kind, r in self.schedule()]
        parts.append(f"garbage {self.garbage_rate:g} stacks/s")
        return ", ".join(parts)


def describe_partition(p: Partition) -> str:
    """As the command line spells it: ``r1,r2:5-10``."""
    return f"{','.join(sorted(p.group))}:{p.first}-{p.last}"


class Garbage:
    """Malformed, truncated, NaN-laden and oversized stacks on the stack keys of ``robots`` and
    of a robot that does not exist, at ``rate`` per second; ``sent`` counts them."""

    def __init__(self, robots: Sequence[str], rate: float, seed: int) -> None:
        self.robots = list(robots)
        self.rate = rate
        self.rng = random.Random(seed ^ 0x6A5BA6E)
        self.sent = 0

    async def run(self, transport: Transport, keys: Keys) -> None:
        """Publish until cancelled. asyncio wakes a sleeper about once a millisecond at best, and
        later on a busy loop: every wake-up publishes what is due by then (at most
        ``GARBAGE_BURST``), or high rates would never be reached."""
        rng = self.rng
        start, due_before = time.monotonic(), 0
        while True:
            due = int((time.monotonic() - start) * self.rate) + 1
            for _ in range(min(due - due_before, GARBAGE_BURST)):
                data = garbage_stack(rng)
                robot = "chaos" if rng.random() < 0.5 else rng.choice(self.robots)
                transport.publish(keys.stack(robot), data)
                self.sent += 1
            due_before = due
            await asyncio.sleep(1.0 / self.rate)


def forged_summary(object_id: int, num_classes: int, classes: str) -> LocalSummary:
    """A slot's content that no robot made: one object of class 0 at (5, 5), of the fleet's class
    representation (``BeliefConfig.classes``), so that the victims would fuse it."""
    xi = Xi(np.array([[5.0, 5.0, 0.0]]), 100.0 * np.eye(3), np.zeros(3))
    if classes == "per_object":
        phi = np.full((1, num_classes), -50.0)
        phi[0, 0] = 0.0
        return LocalSummary((object_id,), (), ObjectClasses(phi, xi))
    return LocalSummary((object_id,), (Realisation((0,), 0.0, xi),))


def garbage_stack(rng: random.Random) -> bytes:
    """One invalid stack message: random bytes, wrong types, NaNs, too many slots or an unknown
    version."""
    kind = rng.randrange(5)
    if kind == 0:
        return rng.randbytes(rng.randrange(0, 512))
    if kind == 1:
        return _pack(
            {"v": 1, "type": "stack", "sender": "chaos", "k": 1, "pos": None, "slots": "x"}
        )
    if kind == 2:
        nan = np.full(3, np.nan).astype("<f8").tobytes()
        real = {"c": b"\x00", "phi": 0.0, "lin": nan, "info": nan * 2, "eta": nan}
        slot = {"owner": "chaos", "stamp": 1, "objects": [1], "real": [real]}
        pos = [float("nan"), 0.0]
        return _pack(
            {"v": 1, "type": "stack", "sender": "chaos", "k": 1, "pos": pos, "slots": [slot]}
        )
    if kind == 3:
        slots = [{"owner": f"o{i}", "stamp": 1, "objects": [], "real": []} for i in range(100)]
        return _pack(
            {"v": 1, "type": "stack", "sender": "chaos", "k": 1, "pos": None, "slots": slots}
        )
    return _pack({"v": 99, "type": "stack"})


def _pack(message: dict[str, object]) -> bytes:
    return bytes(msgpack.packb(message))
