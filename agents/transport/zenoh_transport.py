"""The Zenoh transport: the only module that imports ``zenoh`` (design/zenoh-transport.md).

Peer mode, multicast scouting always off, explicit listen/connect endpoints, shared memory off for
simulations. ``zenoh.open`` and ``Session.close`` block, so they run in a worker thread. Zenoh's
callbacks run on its own threads: they only copy the payload and hand it to the event loop with
``call_soon_threadsafe``; a slow callback would stall every subscription of the session. Puts use
``CongestionControl.DROP``: gossip is latest-wins, and a blocked put could stall the loop for
seconds. Zenoh peers never forward for each other, so multi-hop relay is the stacks' job.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from agents.transport.base import Inbox, Kind, Message, TransportError

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class ZenohSettings:
    """How one session joins the fleet network. ``gossip``: Zenoh's gossip scouting, which links
    every reachable peer (keep it on for local simulations, off on a real fleet so Zenoh links
    match radio links); ``config_file``: a JSON5 file applied first (TLS, access control…), the
    fields here then override it."""

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    gossip: bool = True
    shared_memory: bool = False
    lease_ms: int = 3000
    config_file: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    def config(self) -> zenoh.Config:
        cfg = zenoh.Config.from_file(str(self.config_file)) if self.config_file else zenoh.Config()
        cfg.insert_json5("mode", '"peer"')
        cfg.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        cfg.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        cfg.insert_json5(
            "connect/retry",
            json.dumps({"period_init_ms": 100, "period_max_ms": 500, "period_increase_factor": 2}),
        )
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("scouting/gossip/enabled", json.dumps(self.gossip))
        cfg.insert_json5("transport/link/tx/lease", str(self.lease_ms))
        cfg.insert_json5("transport/shared_memory/enabled", json.dumps(self.shared_memory))
        for key, value in self.extra.items():
            cfg.insert_json5(key, json.dumps(value))
        return cfg


class ZenohTransport:
    """The :class:`~agents.transport.base.Transport` protocol over one Zenoh session."""

    def __init__(self, settings: ZenohSettings) -> None:
        self.settings = settings
        self._session: zenoh.Session | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._pending_subs: list[tuple[str, Inbox]] = []
        self._pending_tokens: list[str] = []
        self._pending_watches: list[tuple[str, Inbox]] = []
        self._handles: list[Any] = []
        self._publishers: dict[str, zenoh.Publisher] = {}
        self.sent = 0
        self.send_errors = 0

    @property
    def is_open(self) -> bool:
        return self._session is not None

    async def open(self) -> None:
        if self._session is not None:
            return
        self._loop = asyncio.get_running_loop()
        try:
            config = self.settings.config()
            self._session = await asyncio.to_thread(zenoh.open, config)
        except zenoh.ZError as exc:
            endpoints = ", ".join((*self.settings.listen, *self.settings.connect)) or "none"
            raise TransportError(f"Zenoh session (endpoints {endpoints}): {exc}") from None
        for expr, inbox in self._pending_subs:
            self._declare_subscriber(expr, inbox)
        for key in self._pending_tokens:
            self._declare_token(key)
        for expr, inbox in self._pending_watches:
            self._declare_watch(expr, inbox)

    async def close(self) -> None:
        session, self._session = self._session, None
        if session is None:
            return
        self._handles.clear()
        self._publishers.clear()
        await asyncio.to_thread(session.close)

    def close_now(self) -> None:
        """Close from a synchronous context (e.g. an ``atexit`` fallback)."""
        session, self._session = self._session, None
        if session is not None:
            session.close()

    # -- Transport --------------------------------------------------------------------------

    def subscribe(self, key_expr: str, inbox: Inbox) -> None:
        self._pending_subs.append((key_expr, inbox))
        if self._session is not None:
            self._declare_subscriber(key_expr, inbox)

    def publish(self, key: str, payload: bytes) -> None:
        if self._session is None:
            return
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.DROP
            )
            self._publishers[key] = publisher
        try:
            publisher.put(payload)
            self.sent += 1
        except zenoh.ZError as exc:  # a closing session; gossip is retried on the next period
            self.send_errors += 1
            log.debug("put on %s failed: %s", key, exc)

    def declare_alive(self, key: str) -> None:
        self._pending_tokens.append(key)
        if self._session is not None:
            self._declare_token(key)

    def watch_alive(self, key_expr: str, inbox: Inbox) -> None:
        self._pending_watches.append((key_expr, inbox))
        if self._session is not None:
            self._declare_watch(key_expr, inbox)

    def subscribe_raw(self, key_expr: str, callback: Callable[[bytes], None]) -> None:
        """``callback(payload)`` on Zenoh's own thread, with no hand-off to the loop: for
        measuring the raw transport only (benchmarks). The session must be open."""
        assert self._session is not None, "open the session first"
        self._handles.append(
            self._session.declare_subscriber(
                key_expr, lambda sample: callback(sample.payload.to_bytes())
            )
        )

    # -- declarations -----------------------------------------------------------------------

    def _handoff(self, inbox: Inbox) -> Callable[[zenoh.Sample], None]:
        loop = self._loop
        assert loop is not None

        inbox.bind(loop)

        def on_sample(sample: zenoh.Sample) -> None:
            # A Zenoh thread: copy the bytes into the bounded inbox, which wakes the loop once.
            inbox.put(Message(str(sample.key_expr), sample.payload.to_bytes()))

        return on_sample

    def _declare_subscriber(self, key_expr: str, inbox: Inbox) -> None:
        assert self._session is not None
        self._handles.append(self._session.declare_subscriber(key_expr, self._handoff(inbox)))

    def _declare_token(self, key: str) -> None:
        assert self._session is not None
        self._handles.append(self._session.liveliness().declare_token(key))

    def _declare_watch(self, key_expr: str, inbox: Inbox) -> None:
        assert self._session is not None
        loop = self._loop
        assert loop is not None

        inbox.bind(loop)

        def on_change(sample: zenoh.Sample) -> None:
            kind: Kind = "alive" if sample.kind == zenoh.SampleKind.PUT else "gone"
            inbox.put(Message(str(sample.key_expr), b"", kind))

        self._handles.append(
            self._session.liveliness().declare_subscriber(key_expr, on_change, history=True)
        )


def loopback_endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def settings_for(
    listen_port: int, connect_ports: Sequence[int], gossip: bool = True
) -> ZenohSettings:
    """A simulation session on loopback: listen on one port, dial the given ones."""
    return ZenohSettings(
        listen=(loopback_endpoint(listen_port),),
        connect=tuple(loopback_endpoint(p) for p in connect_ports),
        gossip=gossip,
    )
