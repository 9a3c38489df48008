"""The operator's Zenoh session and what it does with it: ask for a status, watch, stop.

The session only dials out (``--connect``, never listens); the fleet's liveliness tokens and
estimates flow into a :class:`~deploy.operator.fleet_view.FleetView`. :class:`StopProgress` is the
sans-I/O timing of a stop; the asyncio functions only open the session, pump messages in, send
what they are told and wait.
"""

from __future__ import annotations

import asyncio
import math
import signal
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from agents.control import Status, Stop, encode_control
from agents.transport.base import Inbox, Keys
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport
from deploy.base.errors import RunFailure
from deploy.operator.fleet_view import FleetView

# Liveliness history and the first answers to ctl/status arrive within milliseconds on loopback;
# a status waits at least this long for robots reached through another robot to show up.
SETTLE_S = 0.5
# ctl/status and ctl/stop are re-sent this often to robots that have not reacted (lost puts,
# robots that appeared late).
RESEND_S = 0.5
# A stop is confirmed once no token has been alive for this long: a client whose router robot
# stopped fails over to its next --connect endpoint and sees the remaining tokens again (within
# 0.1 s on loopback, measured).
STOP_CONFIRM_S = 1.0


def session_settings(
    endpoints: tuple[str, ...], mode: str = "client", config_file: Path | None = None
) -> ZenohSettings:
    """An operator's session: dials ``endpoints``, never listens; ``mode`` "client" or "peer"
    (with gossip scouting)."""
    return ZenohSettings(connect=endpoints, config_file=config_file, mode=mode)


class Session:
    """The operator's Zenoh session: the fleet's tokens and estimates flow into a
    :class:`FleetView`."""

    def __init__(
        self, settings: ZenohSettings, keys: Keys, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.keys = keys
        self.clock = clock
        self.view = FleetView(keys)
        self.transport = ZenohTransport(settings)
        self.endpoints = ", ".join(settings.connect)
        self.inbox = Inbox(100_000)

    async def __aenter__(self) -> Session:
        self.transport.watch_alive(self.keys.alive("*"), self.inbox)
        self.transport.subscribe(self.keys.estimate("*"), self.inbox)
        try:
            await self.transport.open()
        except Exception as exc:  # zenoh.ZError, which only the transport module may name
            first = str(exc).split(" at /", 1)[0].strip()
            raise RunFailure(f"cannot reach {self.endpoints}: {first}") from None
        return self

    async def __aexit__(self, *_: object) -> None:
        await self.transport.close()

    def send(self, message: Status | Stop, name: str) -> None:
        self.transport.publish(self.keys.ctl(name), encode_control(message))

    async def pump(self, timeout: float) -> bool:
        """Wait up to ``timeout`` for deliveries and feed them to the view; True if it changed."""
        await self.inbox.wait(max(0.0, timeout))
        now = self.clock()
        changed = False
        for m in self.inbox.drain():
            changed |= self.view.on_message(m, now)
        return changed

    def nobody(self, waited: float) -> RunFailure:
        return RunFailure(
            f"no robot of fleet {self.keys.fleet!r} answered within {waited:g} s "
            f"at {self.endpoints}"
        )


async def collect_status(
    settings: ZenohSettings, keys: Keys, timeout: float
) -> tuple[FleetView, float, float]:
    """Ask for every robot's estimate; return the view once every robot whose token showed up
    answered (after at least :data:`SETTLE_S`), or at ``timeout``; with the seconds it took and
    the seconds from the request to the last answer (NaN without one)."""
    async with Session(settings, keys) as s:
        start = s.clock()
        s.send(Status(), "status")
        asked = start
        while (now := s.clock()) < start + timeout:
            settled = now >= start + min(SETTLE_S, timeout)
            if settled and s.view.answered() and not s.view.unanswered():
                break
            if s.view.unanswered() and now - asked >= RESEND_S:
                s.send(Status(), "status")
                asked = now
            await s.pump(min(0.05, start + timeout - now))
        elapsed = s.clock() - start
        if not s.view.robots:
            raise s.nobody(timeout)
        received = [st.received for st in s.view.robots.values() if st.estimate is not None]
        return s.view, elapsed, max(received, default=math.nan) - start


async def watch_fleet(
    settings: ZenohSettings,
    keys: Keys,
    duration: float | None,
    timeout: float,
    on_change: Callable[[FleetView, float], None],
) -> tuple[FleetView, float]:
    """Follow the fleet until ``duration`` s, SIGINT or SIGTERM; ``on_change(view, now)`` on
    every change and at least once a second. Robots that show up without an estimate are asked
    for one (``ctl/status``, at most every :data:`RESEND_S`). No robot within ``timeout`` s is an
    :class:`~deploy.base.errors.RunFailure`."""
    ended = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        loop.add_signal_handler(sig, ended.set)
    try:
        async with Session(settings, keys) as s:
            start = s.clock()
            s.send(Status(), "status")
            asked = shown = start
            end = math.inf if duration is None else start + duration
            while not ended.is_set() and (now := s.clock()) < end:
                if not s.view.robots and now >= start + timeout:
                    raise s.nobody(timeout)
                if s.view.unanswered() and now - asked >= RESEND_S:
                    s.send(Status(), "status")
                    asked = now
                changed = await s.pump(min(0.25, end - now))
                if changed or s.clock() - shown >= 1.0:
                    shown = s.clock()
                    on_change(s.view, shown)
            return s.view, s.clock() - start
    finally:
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.remove_signal_handler(sig)


@dataclass(slots=True)
class StopProgress:
    """The timing of a stop, from whether any token is alive and ``now``: ``ctl/stop`` again
    every :data:`RESEND_S` while some token is alive; over once none has been for
    :data:`STOP_CONFIRM_S`, because a client whose robot just left fails over to its next
    endpoint and may see the others' tokens again."""

    sent: float
    last_sent: float = math.nan
    quiet_since: float | None = None

    def __post_init__(self) -> None:
        if math.isnan(self.last_sent):
            self.last_sent = self.sent

    def step(self, anyone_alive: bool, now: float) -> Literal["resend", "wait", "done"]:
        if anyone_alive:
            self.quiet_since = None
            if now - self.last_sent >= RESEND_S:
                self.last_sent = now
                return "resend"
            return "wait"
        if self.quiet_since is None:
            self.quiet_since = now
        return "done" if now - self.quiet_since >= STOP_CONFIRM_S else "wait"


async def stop_fleet(
    settings: ZenohSettings, keys: Keys, reason: str, timeout: float
) -> tuple[list[str], list[str], float]:
    """Publish ``ctl/stop`` and follow the tokens (:class:`StopProgress`) until the stop is over
    or ``timeout``; (stopped, still alive, seconds from the stop to the last token gone)."""
    async with Session(settings, keys) as s:
        start = s.clock()
        while s.clock() < start + min(SETTLE_S, timeout):
            await s.pump(0.05)
        seen = s.view.alive()
        if not seen:
            raise s.nobody(min(SETTLE_S, timeout))
        progress = StopProgress(s.clock())
        s.send(Stop(reason), "stop")
        while (now := s.clock()) < progress.sent + timeout:
            action = progress.step(bool(s.view.alive()), now)
            if action == "done":
                break
            if action == "resend":
                s.send(Stop(reason), "stop")
            await s.pump(0.05)
        seen = sorted(set(seen) | set(s.view.robots))
        still = s.view.alive()
        stopped = [r for r in seen if r not in still]
        return stopped, still, (progress.quiet_since or s.clock()) - progress.sent
