"""Link models of a simulated fleet: who can hear whom at step k. The simulator's side only — the
in-process runner and the conductor evaluate them on the true poses and tell simulated agents the
verdict (lock-step orders, ``sim/links``); no agent evaluates a link model itself."""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike


class LinkModel(Protocol):
    """Whether a stack sent by ``sender`` at step ``k`` reaches ``receiver``."""

    def allowed(
        self, sender: str, receiver: str, k: int, sender_pos: ArrayLike, receiver_pos: ArrayLike
    ) -> bool: ...


@dataclass(frozen=True, slots=True)
class Proximity:
    """Robots within ``range_m`` metres of each other hear each other."""

    range_m: float = 10.0

    def __post_init__(self) -> None:
        if not self.range_m > 0:
            raise ValueError(f"range must be positive, got {self.range_m}")

    def allowed(
        self, sender: str, receiver: str, k: int, sender_pos: ArrayLike, receiver_pos: ArrayLike
    ) -> bool:
        a, b = np.asarray(sender_pos, float), np.asarray(receiver_pos, float)
        return math.hypot(a[0] - b[0], a[1] - b[1]) <= self.range_m


@dataclass(frozen=True, slots=True)
class Schedule:
    """An explicit table of undirected edges ``(first_step, last_step, robot_a, robot_b)``."""

    edges: tuple[tuple[int, int, str, str], ...]

    def allowed(
        self, sender: str, receiver: str, k: int, sender_pos: ArrayLike, receiver_pos: ArrayLike
    ) -> bool:
        pair = {sender, receiver}
        return any(first <= k <= last and pair == {a, b} for first, last, a, b in self.edges)


@dataclass(frozen=True, slots=True)
class RandomDrop:
    """Each directed transmission is lost with probability ``p``, as a pure function of
    (seed, sender, receiver, k): the same run drops the same messages whatever the order."""

    p: float
    seed: int

    def __post_init__(self) -> None:
        if not 0.0 <= self.p <= 1.0:
            raise ValueError(f"drop probability must be in [0, 1], got {self.p}")

    def allowed(
        self, sender: str, receiver: str, k: int, sender_pos: ArrayLike, receiver_pos: ArrayLike
    ) -> bool:
        seq = np.random.SeedSequence(
            [self.seed, zlib.crc32(sender.encode()), zlib.crc32(receiver.encode()), k]
        )
        return float(np.random.default_rng(seq).random()) >= self.p


@dataclass(frozen=True, slots=True)
class AllOf:
    """A link works when every model allows it (e.g. schedule and range, with random loss)."""

    models: Sequence[LinkModel]

    def allowed(
        self, sender: str, receiver: str, k: int, sender_pos: ArrayLike, receiver_pos: ArrayLike
    ) -> bool:
        return all(m.allowed(sender, receiver, k, sender_pos, receiver_pos) for m in self.models)


@dataclass(frozen=True, slots=True)
class Partition:
    """Steps ``first``…``last``: robots in ``group`` hear only each other, the rest only the rest
    (a chaos fault; healed after ``last``)."""

    group: frozenset[str]
    first: int
    last: int

    def __post_init__(self) -> None:
        if not self.group:
            raise ValueError("a partition needs at least one robot")
        if not 0 <= self.first <= self.last:
            raise ValueError(f"partition steps {self.first}-{self.last}: need 0 ≤ first ≤ last")

    def allowed(
        self, sender: str, receiver: str, k: int, sender_pos: ArrayLike, receiver_pos: ArrayLike
    ) -> bool:
        if not self.first <= k <= self.last:
            return True
        return (sender in self.group) == (receiver in self.group)
