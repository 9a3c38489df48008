"""The Zenoh transport: the only module that imports ``zenoh`` (design/zenoh-transport.md).

Peer mode, multicast scouting always off, explicit listen/connect endpoints, shared memory off for
simulations. ``zenoh.open`` and ``Session.close`` block, so they run in a worker thread (a close
is waited for at most ``CLOSE_WAIT_S``). Zenoh's callbacks run on its own threads: they only copy
the payload and hand it to the event loop with
``call_soon_threadsafe``; a slow callback would stall every subscription of the session. Puts use
``CongestionControl.DROP``: gossip is latest-wins, and a blocked put could stall the loop for
seconds. Zenoh peers never forward for each other, so multi-hop relay is the stacks' job.

Over 300 lines for a reason: the session's settings (the merge of a JSON5 file with the fields,
the mutual-TLS and loopback checks) and the session itself are the one place that knows Zenoh's
configuration keys, and this is the only module allowed to import ``zenoh``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, ClassVar

import json5
import zenoh

from agents.transport.base import Inbox, Kind, Message, TransportError, key_matches
from agents.transport.zenoh_errors import open_error, without_build_paths

log = logging.getLogger(__name__)


# The TLS file fields of a Zenoh config: a relative path in a JSON5 file is resolved against the
# file's folder, so that a fleet's folder can be copied onto a robot as it is.
TLS_FILES = (
    "root_ca_certificate",
    "listen_certificate",
    "listen_private_key",
    "connect_certificate",
    "connect_private_key",
)
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "[::1]", "::1")


class ZenohConfigError(ValueError):
    """A Zenoh JSON5 file that cannot be read, or that contradicts the settings given with it
    (names the file and the field)."""


# Gossip is latest-wins and re-sent every period, so it is put best-effort: over a session's
# UDP link when it has one (a healed cut lets the next stack through at once, where TCP would
# still be backing off its retransmissions for seconds), over its TCP link otherwise.
BEST_EFFORT_KEYS = ("**/stack/*", "**/stack/*/to/*")  # stacks, and pushes to one robot
# How long close() waits for Zenoh's Session.close: it flushes and closes every link, which on a
# lossy network can take seconds of TCP retransmissions. Then the process goes on (and exits: the
# kernel closes the sockets), so that an agent's shutdown stays bounded — a launcher kills an
# agent that has not exited 2.2 s after ctl/stop, before its stop record is written.
CLOSE_WAIT_S = 0.5


@dataclass(frozen=True, slots=True)
class ZenohSettings:
    """How one session joins the fleet network. ``gossip``: Zenoh's gossip scouting, which links
    every reachable peer (keep it on for local simulations, off on a real fleet so Zenoh links
    match radio links); ``config_file``: a JSON5 file (TLS, access control…).

    The file and the fields are merged, never silently overwritten: a field left ``None`` (or an
    empty endpoint list) takes the file's value, else the default (gossip on, shared memory off,
    lease 3000 ms); a field that is set must agree with the file where the file sets it too, or
    :meth:`config` raises :class:`ZenohConfigError` naming both. Multicast scouting is always off
    (a file that turns it on is refused); ``mode`` is ``peer`` unless ``mode`` says otherwise."""

    listen: tuple[str, ...] = ()
    connect: tuple[str, ...] = ()
    gossip: bool | None = None
    shared_memory: bool | None = None
    lease_ms: int | None = None
    config_file: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    mode: str = "peer"

    def document(self) -> dict[str, Any]:
        """The merged configuration as a JSON-able document (see the class docstring)."""
        doc = read_json5(self.config_file) if self.config_file else {}
        where = str(self.config_file)
        fields: list[tuple[str, Any, Any]] = [
            ("mode", self.mode, None),
            ("listen/endpoints", list(self.listen) or None, None),
            ("connect/endpoints", list(self.connect) or None, None),
            ("scouting/gossip/enabled", self.gossip, True),
            ("transport/link/tx/lease", self.lease_ms, 3000),
            ("transport/shared_memory/enabled", self.shared_memory, False),
        ]
        for path, value, default in fields:
            held = _get(doc, path)
            if value is not None and held is not None and held != value:
                raise ZenohConfigError(
                    f"{where}: {path} is {json.dumps(held)} but the settings say "
                    f"{json.dumps(value)} (remove one of the two)"
                )
            if held is None:
                chosen = value if value is not None else default
                if chosen is not None:
                    _set(doc, path, chosen)
        if _get(doc, "scouting/multicast/enabled") is True:
            raise ZenohConfigError(f"{where}: scouting/multicast/enabled must be false")
        _set(doc, "scouting/multicast/enabled", False)
        # Recovery after a cut heals: a dialled peer is re-dialled every 100–250 ms. An attempt
        # keeps Zenoh's open timeout (10 s; `transport/unicast/open_timeout`): with 2 s, the
        # handshakes of a 50-agent launch on 2 cores were abandoned and its late agents never
        # got a frame. A file that sets either wins.
        if _get(doc, "connect/retry") is None:
            retry = {"period_init_ms": 100, "period_max_ms": 250, "period_increase_factor": 2}
            _set(doc, "connect/retry", retry)
        # A UDP endpoint next to the TCP ones makes each session two links (multilink): the
        # reliable one for control, the best-effort one for gossip (``BEST_EFFORT_KEYS``).
        if _get(doc, "transport/unicast/max_links") is None and any(
            e.startswith("udp/") for e in _endpoints(doc)
        ):
            _set(doc, "transport/unicast/max_links", 2)
        for key, value in self.extra.items():
            _set(doc, key, value)
        return doc

    def config(self) -> zenoh.Config:
        try:
            return zenoh.Config.from_json5(json.dumps(self.document()))
        except zenoh.ZError as exc:
            where = self.config_file or "zenoh settings"
            raise ZenohConfigError(f"{where}: {without_build_paths(str(exc))}") from None

    def endpoints(self) -> tuple[tuple[str, ...], tuple[str, ...]]:
        """The endpoints listened on and dialled, of the file and the fields merged."""
        doc = self.document()
        listen = _get(doc, "listen/endpoints") or []
        connect = _get(doc, "connect/endpoints") or []
        return tuple(str(e) for e in listen), tuple(str(e) for e in connect)

    def dialling(self, endpoints: Sequence[str]) -> ZenohSettings:
        """These settings (the file's TLS identity and access control included) for a session
        that listens on nothing and dials ``endpoints`` only, whatever the file says."""
        extra = {**self.extra, "listen/endpoints": [], "connect/endpoints": list(endpoints)}
        return replace(self, listen=(), connect=(), extra=extra)

    def mutual_tls(self) -> bool:
        """Whether every endpoint, listened on or dialled, is TLS with a root CA and client
        certificates required (mutual TLS)."""
        doc = self.document()
        tls = _get(doc, "transport/link/tls") or {}
        configured = bool(tls.get("enable_mtls")) and bool(tls.get("root_ca_certificate"))
        return configured and all(e.startswith("tls/") for e in _endpoints(doc))

    def off_loopback(self) -> list[str]:
        """The endpoints (listened on or dialled) whose host is not a loopback address."""
        return [e for e in _endpoints(self.document()) if not _loopback(e)]


def _endpoints(doc: dict[str, Any]) -> list[str]:
    listen = _get(doc, "listen/endpoints") or []
    connect = _get(doc, "connect/endpoints") or []
    return [str(e) for e in (*listen, *connect)]


def read_json5(path: Path) -> dict[str, Any]:
    """A Zenoh JSON5 file as a document; relative TLS file paths resolved against its folder."""
    try:
        doc = json5.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ZenohConfigError(f"{path}: {exc.strerror}") from None
    except (ValueError, RecursionError) as exc:  # RecursionError: nesting too deep to read
        raise ZenohConfigError(f"{path}: not JSON5: {type(exc).__name__}: {exc}") from None
    if not isinstance(doc, dict):
        raise ZenohConfigError(f"{path}: expected a JSON5 object at the top")
    tls = _get(doc, "transport/link/tls")
    if isinstance(tls, dict):
        for name in TLS_FILES:
            value = tls.get(name)
            if isinstance(value, str) and not Path(value).is_absolute():
                tls[name] = str((path.parent / value).resolve())
    return doc


def _loopback(endpoint: str) -> bool:
    locator = endpoint.split("/", 1)[-1].split("#", 1)[0].split("?", 1)[0]
    host = locator.rsplit(":", 1)[0] if ":" in locator else locator
    return host in LOOPBACK_HOSTS or host.startswith("127.")


def _get(doc: dict[str, Any], path: str) -> Any:
    node: Any = doc
    for part in path.split("/"):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def _set(doc: dict[str, Any], path: str, value: Any) -> None:
    parts = path.split("/")
    node = doc
    for part in parts[:-1]:
        child = node.get(part)
        if not isinstance(child, dict):
            child = node[part] = {}
        node = child
    node[parts[-1]] = value


class ZenohTransport:
    """The :class:`~agents.transport.base.Transport` protocol over one Zenoh session."""

    # Sessions this process opened: one that did must not tear its interpreter down while Zenoh's
    # threads may still call into it (``deploy.cli.main.entry``).
    sessions_opened: ClassVar[int] = 0

    def __init__(self, settings: ZenohSettings) -> None:
        self.settings = settings
        self._session: zenoh.Session | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._pending_subs: list[tuple[str, Inbox]] = []
        self._pending_tokens: list[str] = []
        self._pending_watches: list[tuple[str, Inbox]] = []
        self._handles: list[Any] = []
        # Declared subscribers by (key expression, id of the inbox), for ``unsubscribe``.
        self._subscribers: dict[tuple[str, int], list[zenoh.Subscriber[None]]] = {}
        self._publishers: dict[str, zenoh.Publisher] = {}
        self.sent = 0
        self.send_errors = 0
        self.close_timeouts = 0  # closes that did not finish within CLOSE_WAIT_S

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
            ZenohTransport.sessions_opened += 1
        except ZenohConfigError as exc:
            raise TransportError(str(exc)) from None
        except zenoh.ZError as exc:
            raise TransportError(open_error(str(exc), *self.settings.endpoints())) from None
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
        self._subscribers.clear()
        self._publishers.clear()
        loop = asyncio.get_running_loop()
        closed: asyncio.Future[None] = loop.create_future()

        def done() -> None:
            if not closed.done():
                closed.set_result(None)

        def close() -> None:  # on a daemon thread: one that hangs does not hold the exit
            try:
                session.close()
            finally:
                with contextlib.suppress(RuntimeError):  # the loop is gone: nobody waits
                    loop.call_soon_threadsafe(done)

        threading.Thread(target=close, name="zenoh-close", daemon=True).start()
        try:
            await asyncio.wait_for(asyncio.shield(closed), CLOSE_WAIT_S)
        except TimeoutError:
            self.close_timeouts += 1
            log.warning("the Zenoh session did not close within %.1f s: left to exit", CLOSE_WAIT_S)

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

    def unsubscribe(self, key_expr: str, inbox: Inbox) -> None:
        self._pending_subs = [
            (e, i) for e, i in self._pending_subs if not (e == key_expr and i is inbox)
        ]
        for subscriber in self._subscribers.pop((key_expr, id(inbox)), []):
            if self._session is not None:
                subscriber.undeclare()

    def publish(self, key: str, payload: bytes, attachment: bytes | None = None) -> None:
        """Put ``payload`` on ``key``; ``attachment``, if given, travels with it (rmw_zenoh's
        per-sample metadata, agents/ros2/wire.py)."""
        if self._session is None:
            return
        publisher = self._publishers.get(key)
        if publisher is None:
            best_effort = any(key_matches(e, key) for e in BEST_EFFORT_KEYS)
            publisher = self._session.declare_publisher(
                key,
                congestion_control=zenoh.CongestionControl.DROP,
                reliability=zenoh.Reliability.BEST_EFFORT if best_effort else None,
            )
            self._publishers[key] = publisher
        try:
            publisher.put(payload, attachment=attachment)
            self.sent += 1
        except zenoh.ZError as exc:  # a closing session; gossip is retried on the next period
            self.send_errors += 1
            log.debug("put on %s failed: %s", key, exc)

    def links(self) -> dict[str, int]:
        if self._session is None:
            return {"stream": 0, "datagram": 0}
        links = self._session.info.links()
        streamed = {str(link.zid) for link in links if link.is_streamed}
        datagram = {str(link.zid) for link in links if not link.is_streamed}
        return {"stream": len(streamed), "datagram": len(datagram)}

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

        def on_sample(sample: zenoh.Sample) -> None:
            callback(sample.payload.to_bytes())

        # On the receiving Zenoh thread, as the agent's own subscriptions (_declare_subscriber).
        self._handles.append(
            self._session.declare_subscriber(
                key_expr, zenoh.handlers.Callback(on_sample, indirect=False)
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
        # Called on the Zenoh thread that received the sample (``indirect=False``), not handed to
        # a Python thread of Zenoh's first: the hand-off is one locked append and at most one
        # wake-up of the loop, and the extra thread hop per sample cost more than both.
        subscriber = self._session.declare_subscriber(
            key_expr, zenoh.handlers.Callback(self._handoff(inbox), indirect=False)
        )
        self._subscribers.setdefault((key_expr, id(inbox)), []).append(subscriber)

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
