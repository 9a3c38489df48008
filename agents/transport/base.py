"""What every transport offers an agent: named byte messages in, byte messages out, liveliness.

A transport never interprets payloads. Received messages land in bounded :class:`Inbox` es owned by
the event loop; an inbox that is full drops its *oldest* message (stacks are latest-wins, so the
newest copy is the one worth keeping) and counts the drop.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import threading
import time
from dataclasses import dataclass, field
from typing import Literal, Protocol

from estimator.models import ROBOT_ID_RULE
from protocol.validate import valid_id

Kind = Literal["put", "alive", "gone"]


@dataclass(frozen=True, slots=True)
class Message:
    """One delivery: ``kind`` "put" carries ``payload``; "alive"/"gone" are liveliness changes of
    the token ``key``; ``at``: when it arrived (``time.monotonic``), for holding times."""

    key: str
    payload: bytes
    kind: Kind = "put"
    at: float = field(default_factory=time.monotonic, compare=False)


class TransportError(RuntimeError):
    """A transport that could not open: bad endpoint, port taken, bad configuration file."""


class Inbox:
    """A bounded FIFO of :class:`Message`, filled from any thread and drained by the event loop.

    Bounded in count (``capacity``) and in payload bytes (``max_bytes``). When a message does not
    fit, older messages *on the same key* go first (stacks are latest-wins: the newest copy is the
    one worth keeping), then the oldest of all; every drop is counted. A message larger than
    ``max_message_bytes`` (default: ``max_bytes``) is dropped at once, so that messages its
    reader would refuse unread never take room from the others. :meth:`put` may be called from
    a transport's own threads: it never waits for the loop, and it wakes the loop at most once
    per batch, so a busy loop cannot make the hand-off grow without bound.
    """

    def __init__(
        self, capacity: int, max_bytes: int = 256 * 1024 * 1024, max_message_bytes: int = 0
    ) -> None:
        if capacity < 1 or max_bytes < 1 or max_message_bytes < 0:
            raise ValueError(f"inbox capacity and bytes must be ≥ 1, got {capacity}, {max_bytes}")
        self._items: collections.deque[Message] = collections.deque()
        self.capacity = capacity
        self.max_bytes = max_bytes
        self.max_message_bytes = min(max_message_bytes or max_bytes, max_bytes)
        self.bytes = 0
        self.dropped = 0
        self.received = 0
        self._lock = threading.Lock()
        self._event = asyncio.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._wake_pending = False
        self._doorbells: list[asyncio.Event] = []
        self._loud: frozenset[str] | None = None  # the keys whose messages wake (None: all)

    def __len__(self) -> int:
        return len(self._items)

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """The loop to wake when a message is put from another thread."""
        self._loop = loop

    def wake_for(self, keys: frozenset[str] | None) -> None:
        """Only messages on ``keys`` wake the loop (None: every message); the others are queued
        quietly and taken with the next batch (:meth:`drain`; :meth:`wait` and :meth:`get` see
        them as they look). A message already queued on a key that becomes loud wakes the loop
        now, as it would have on arrival."""
        with self._lock:
            self._loud = keys
            wake = not self._wake_pending and any(
                keys is None or m.key in keys for m in self._items
            )
            self._wake_pending |= wake
        if wake:
            self._wake()

    def ring(self, doorbell: asyncio.Event) -> None:
        """Set ``doorbell`` too whenever this inbox wakes its loop: one event that several inboxes
        ring is waited for at the cost of one (a consumer of several inboxes clears it, drains
        them all, and waits for it only if they were all empty)."""
        self._doorbells.append(doorbell)

    def put(self, message: Message) -> None:
        """Enqueue, from the loop or from any other thread (after :meth:`bind`)."""
        size = len(message.payload)
        with self._lock:
            self.received += 1
            if size > self.max_message_bytes:
                self.dropped += 1
                return
            self._make_room(message.key, size)
            self._items.append(message)
            self.bytes += size
            if self._wake_pending or (self._loud is not None and message.key not in self._loud):
                return
            self._wake_pending = True
        self._wake()

    def _make_room(self, key: str, size: int) -> None:
        """Drop until ``size`` more bytes and one more message fit (lock held)."""

        def full() -> bool:
            return len(self._items) >= self.capacity or self.bytes + size > self.max_bytes

        if not full():
            return
        same = [m for m in self._items if m.key == key]
        for m in same:
            if not full():
                break
            self._items.remove(m)
            self.bytes -= len(m.payload)
            self.dropped += 1
        while full() and self._items:
            m = self._items.popleft()
            self.bytes -= len(m.payload)
            self.dropped += 1

    def _wake(self) -> None:
        loop = self._loop
        try:
            running = asyncio.get_running_loop()
        except RuntimeError:
            running = None
        if loop is None or running is loop:
            self._set()
        else:
            with contextlib.suppress(RuntimeError):  # a closed loop: shutting down
                loop.call_soon_threadsafe(self._set)

    def _set(self) -> None:
        self._event.set()
        for doorbell in self._doorbells:
            doorbell.set()

    def drain(self) -> list[Message]:
        """Everything queued, oldest first, without waiting."""
        with self._lock:
            items = list(self._items)
            self._items.clear()
            self.bytes = 0
            self._wake_pending = False
            self._event.clear()
        return items

    async def get(self) -> Message:
        """The oldest message, waiting for one."""
        while True:
            with self._lock:
                if self._items:
                    message = self._items.popleft()
                    self.bytes -= len(message.payload)
                    if not self._items:
                        self._wake_pending = False
                        self._event.clear()
                    return message
                self._wake_pending = False
                self._event.clear()
            await self._event.wait()

    async def wait(self, timeout: float | None = None) -> bool:
        """Wait until something is queued; False on timeout."""
        with self._lock:
            if self._items:
                return True
            self._wake_pending = False
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

    def unsubscribe(self, key_expr: str, inbox: Inbox) -> None:
        """Stop delivering puts on ``key_expr`` into ``inbox`` (a subscription made with exactly
        these two; nothing if there is none)."""
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

    def links(self) -> dict[str, int]:
        """To how many other nodes the session has a ``stream`` link (TCP, TLS) and a
        ``datagram`` link (UDP) now."""
        ...


@dataclass(frozen=True, slots=True)
class Keys:
    """The key expressions of one fleet (docs/wire.md): everything lives under
    ``semfleet/<fleet>/``."""

    fleet: str

    def __post_init__(self) -> None:
        if not valid_id(self.fleet):
            raise ValueError(f"fleet name {self.fleet!r}: {ROBOT_ID_RULE}")

    @property
    def prefix(self) -> str:
        return f"semfleet/{self.fleet}"

    def stack(self, robot: str) -> str:
        return f"{self.prefix}/stack/{_robot(robot)}"

    def stack_to(self, robot: str, to: str) -> str:
        """A stack for ``to`` alone: a push of the slots it asked for (docs/wire.md, "Asks")."""
        return f"{self.prefix}/stack/{_robot(robot)}/to/{_robot(to)}"

    def stack_sender(self, key: str) -> str | None:
        """The robot of a :meth:`stack` or :meth:`stack_to` key (None: neither, or a bad id)."""
        head = f"{self.prefix}/stack/"
        parts = key[len(head) :].split("/") if key.startswith(head) else []
        ok = len(parts) == 1 or (len(parts) == 3 and parts[1] == "to" and valid_id(parts[2]))
        return parts[0] if ok and valid_id(parts[0]) else None

    def alive(self, robot: str) -> str:
        return f"{self.prefix}/alive/{_robot(robot)}"

    def frames(self, robot: str) -> str:
        return f"{self.prefix}/frames/{_robot(robot)}"

    def estimate(self, robot: str) -> str:
        return f"{self.prefix}/estimate/{_robot(robot)}"

    def sim_links(self, robot: str) -> str:
        """Simulations only: whom ``robot`` hears at step k, as decided by the simulator."""
        return f"{self.prefix}/sim/links/{robot}"

    def sim_listen(self, robot: str) -> str:
        """Simulations only: whom ``robot`` will hear at step k, sent by the simulator a step
        ahead, for subscriptions only (who is heard is decided by :meth:`sim_links`)."""
        return f"{self.prefix}/sim/listen/{robot}"

    def ctl(self, *parts: str) -> str:
        return "/".join((self.prefix, "ctl", *parts))

    def robot_of(self, key: str) -> str | None:
        """The robot id a per-robot key ends with (None if the last chunk is not a valid id)."""
        last = key.rsplit("/", 1)[-1]
        return last if valid_id(last) else None


def _robot(robot: str) -> str:
    """A robot id, or the wildcard ``*`` (all robots) for subscriptions."""
    if robot != "*" and not valid_id(robot):
        raise ValueError(f"robot id {robot!r}: {ROBOT_ID_RULE}")
    return robot


def key_matches(key_expr: str, key: str) -> bool:
    """Zenoh's wildcards on '/'-separated chunks: ``*`` one chunk, ``**`` zero or more chunks."""
    return _match(key_expr.split("/"), key.split("/"))


def _match(pattern: list[str], chunks: list[str]) -> bool:
    if not pattern:
        return not chunks
    head, rest = pattern[0], pattern[1:]
    if head == "**":
        return any(_match(rest, chunks[i:]) for i in range(len(chunks) + 1))
    if not chunks:
        return False
    return (head == "*" or head == chunks[0]) and _match(rest, chunks[1:])
