"""An in-memory transport for unit tests: one :class:`MemoryBus` per event loop, any number of
:class:`MemoryTransport` s on it. Deliveries are scheduled on the loop (never synchronous), as
they would arrive from a network thread."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

from agents.transport.base import Inbox, Kind, Message, key_matches


@dataclass
class MemoryBus:
    """Who subscribed to what, and which liveliness tokens exist."""

    transports: list[MemoryTransport] = field(default_factory=list)
    published: int = 0

    def tokens(self) -> list[str]:
        return [t for tr in self.transports if tr.is_open for t in tr.tokens]


class MemoryTransport:
    """The :class:`~agents.transport.base.Transport` protocol over a :class:`MemoryBus`."""

    def __init__(self, bus: MemoryBus) -> None:
        self.bus = bus
        self.subscriptions: list[tuple[str, Inbox]] = []
        self.watches: list[tuple[str, Inbox]] = []
        self.tokens: list[str] = []
        self.is_open = False
        self.sent = 0

    async def open(self) -> None:
        self.is_open = True
        self.bus.transports.append(self)
        for token in self.tokens:
            self._announce(token, "alive")

    async def close(self) -> None:
        if not self.is_open:
            return
        self.is_open = False
        self.bus.transports.remove(self)
        for token in self.tokens:
            self._announce(token, "gone")

    def subscribe(self, key_expr: str, inbox: Inbox) -> None:
        self.subscriptions.append((key_expr, inbox))

    def unsubscribe(self, key_expr: str, inbox: Inbox) -> None:
        self.subscriptions = [
            (e, i) for e, i in self.subscriptions if not (e == key_expr and i is inbox)
        ]

    def publish(self, key: str, payload: bytes) -> None:
        if not self.is_open:
            return
        loop = asyncio.get_running_loop()
        self.sent += 1
        self.bus.published += 1
        for other in self.bus.transports:
            for expr, inbox in other.subscriptions:
                if key_matches(expr, key):
                    loop.call_soon(inbox.put, Message(key, bytes(payload)))

    def declare_alive(self, key: str) -> None:
        self.tokens.append(key)
        if self.is_open:
            self._announce(key, "alive")

    def links(self) -> dict[str, int]:
        return {"stream": 0, "datagram": 0}  # a bus, not a network

    def watch_alive(self, key_expr: str, inbox: Inbox) -> None:
        self.watches.append((key_expr, inbox))
        loop = asyncio.get_running_loop()
        for token in self.bus.tokens():
            if key_matches(key_expr, token):
                loop.call_soon(inbox.put, Message(token, b"", "alive"))

    def _announce(self, token: str, kind: Kind) -> None:
        loop = asyncio.get_running_loop()
        for other in self.bus.transports + ([self] if not self.is_open else []):
            for expr, inbox in other.watches:
                if key_matches(expr, token):
                    loop.call_soon(inbox.put, Message(token, b"", kind))
