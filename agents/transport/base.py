"""What every transport offers an agent: named byte messages in, byte messages out, liveliness.

A transport never interprets payloads. Received messages land in bounded :class:`Inbox` es owned by
the event loop; an inbox that is full drops its *oldest* message (stacks are latest-wins, so the
newest copy is the one worth keeping) and counts the drop.
"""

from __future__ import annotations

import asyncio
import collections
from dataclasses import dataclass
from typing import Literal, Protocol

from protocol.validate import valid_id

Kind = Literal["put", "alive", "gone"]


@dataclass(frozen=True, slots=True)
class Message:
    """One delivery: ``kind`` "put" carries ``payload``; "alive"/"gone" are liveliness changes of
    the token ``key``."""

    key: str
    payload: bytes
    kind: Kind = "put"


class Inbox:
    """A bounded FIFO of :class:`Message` used from the event loop only; full → drop the oldest."""

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError(f"inbox capacity must be ≥ 1, got {capacity}")
        self._items: collections.deque[Message] = collections.deque()
        self.capacity = capacity
        self.dropped = 0
        self.received = 0
        self._event = asyncio.Event()

    def __len__(self) -> int:
        return len(self._items)

    def put(self, message: Message) -> None:
        """Enqueue (event-loop thread only)."""
        if len(self._items) >= self.capacity:
            self._items.popleft()
            self.dropped += 1
        self._items.append(message)
        self.received += 1
        self._event.set()

    def drain(self) -> list[Message]:
        """Everything queued, oldest first, without waiting."""
        items = list(self._items)
        self._items.clear()
        self._event.clear()
        return items

    async def get(self) -> Message:
        """The oldest message, waiting for one."""
        while not self._items:
            self._event.clear()
            await self._event.wait()
        message = self._items.popleft()
        if not self._items:
            self._event.clear()
        return message

    async def wait(self, timeout: float | None = None) -> bool:
        """Wait until something is queued; False on timeout."""
        if self._items:
            return True
        self._event.clear()
        try:
            await asyncio.wait_for(self._event.wait(), timeout)
        except TimeoutError:
            return False
        return True


class Transport(Protocol):
    """Byte messages on key expressions. ``open``/``close`` are awaited once each; ``close`` is
    safe to call twice and after a failed ``open``."""

    async def open(self) -> None: ...

    async def close(self) -> None: ...

    def subscribe(self, key_expr: str, inbox: Inbox) -> None:
        """Deliver every put on ``key_expr`` (wildcards allowed) into ``inbox``."""
        ...

    def publish(self, key: str, payload: bytes) -> None:
        """Send without blocking the loop (a congested link drops the message)."""
        ...

    def declare_alive(self, key: str) -> None:
        """Hold a liveliness token on ``key`` until closed."""
        ...

    def watch_alive(self, key_expr: str, inbox: Inbox) -> None:
        """Deliver "alive"/"gone" messages for tokens matching ``key_expr`` (current ones too)."""
        ...


@dataclass(frozen=True, slots=True)
class Keys:
    """The key expressions of one fleet (docs/wire.md): everything lives under
    ``semfleet/<fleet>/``."""

    fleet: str

    def __post_init__(self) -> None:
        if not valid_id(self.fleet):
            raise ValueError(f"fleet name {self.fleet!r}: 1–32 of A–Z a–z 0–9 _ -")

    @property
    def prefix(self) -> str:
        return f"semfleet/{self.fleet}"

    def stack(self, robot: str) -> str:
        return f"{self.prefix}/stack/{_robot(robot)}"

    def alive(self, robot: str) -> str:
        return f"{self.prefix}/alive/{_robot(robot)}"

    def frames(self, robot: str) -> str:
        return f"{self.prefix}/frames/{_robot(robot)}"

    def estimate(self, robot: str) -> str:
        return f"{self.prefix}/estimate/{_robot(robot)}"

    def ctl(self, *parts: str) -> str:
        return "/".join((self.prefix, "ctl", *parts))

    def robot_of(self, key: str) -> str | None:
        """The robot id a per-robot key ends with (None if the last chunk is not a valid id)."""
        last = key.rsplit("/", 1)[-1]
        return last if valid_id(last) else None


def _robot(robot: str) -> str:
    """A robot id, or the wildcard ``*`` (all robots) for subscriptions."""
    if robot != "*" and not valid_id(robot):
        raise ValueError(f"robot id {robot!r}: 1–32 of A–Z a–z 0–9 _ -")
    return robot
