"""What a robot's perception process imports: :class:`RobotLink`, its link to the robot's agent.

The perception process publishes the robot's sensor frames on ``frames/<robot>`` and reads the
estimates the agent publishes on ``estimate/<robot>``. It also answers the agent's
``ctl/need/<robot>`` (``agents.control.NeedFrames``: after a restart or a lost frame the agent asks
for its frames from step k on) by re-publishing, from a bounded buffer, the frames it has sent from
k on. A published frame never carries a simulator's pose: :meth:`RobotLink.publish_frame` sends
the robot's own data only.

Usage (the agent listens on tcp/10.0.0.5:7448; its config's ``[zenoh] listen``)::

    import asyncio

    from agents.perception import RobotLink
    from agents.transport.zenoh_transport import ZenohSettings
    from estimator.models import Detection, SensorFrame

    async def main() -> None:
        settings = ZenohSettings(connect=("tcp/10.0.0.5:7448",), gossip=False)
        async with RobotLink("r1", "demo", settings) as link:
            await link.wait_for_agent()
            estimates = link.estimates()  # subscribed from here on
            for frame in my_perception():  # SensorFrame("r1", k, odometry, detections, nan3)
                link.publish_frame(frame)
                await asyncio.sleep(0.5)
            async for estimate in estimates:  # protocol.estimate.EstimateMessage
                print(estimate.k, estimate.beliefs["distributed"].weights)
"""

from __future__ import annotations

import asyncio
import collections
import logging
from collections.abc import AsyncIterator
from dataclasses import dataclass, replace
from types import TracebackType

import numpy as np

from agents.control import NeedFrames, decode_control
from agents.transport.base import Inbox, Keys, Message, Transport
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport
from estimator.models import SensorFrame
from protocol.errors import RemoteProtocolError
from protocol.estimate import EstimateLimits, EstimateMessage, decode_estimate
from protocol.frames import encode_frame

log = logging.getLogger(__name__)

HISTORY = 1000  # frames kept for ctl/need: 8 min at 2 Hz, about 1 MB for small frames
ESTIMATE_INBOX = 64  # estimates are latest-wins: a slow reader loses the oldest
INVALID_LOG_PERIOD = 5.0  # seconds between two log records of invalid input
_CLOSED = Message("", b"", "gone")  # ends the estimate iterators when the link closes


@dataclass(slots=True)
class LinkCounters:
    frames_sent: int = 0
    frames_resent: int = 0  # re-published for a ctl/need
    need_requests: int = 0
    need_unserved: int = 0  # asked for frames older than the buffer holds
    invalid_control: int = 0
    invalid_estimates: int = 0


class RobotLink:
    """Robot ``robot``'s perception side of fleet ``fleet``, as an async context manager.

    ``zenoh``: the session's endpoints (connect to the agent's listen endpoints); ``history``: how
    many of the latest frames are kept to answer ``ctl/need``; an agent that needs older ones
    cannot catch up (counted in ``counters.need_unserved`` and logged). ``transport`` replaces
    the Zenoh session (tests use ``agents.transport.MemoryTransport``).
    """

    def __init__(
        self,
        robot: str,
        fleet: str,
        zenoh: ZenohSettings | None = None,
        *,
        history: int = HISTORY,
        estimate_limits: EstimateLimits | None = None,
        transport: Transport | None = None,
    ) -> None:
        if history < 1:
            raise ValueError(f"history must be ≥ 1 frame, got {history}")
        self.keys = Keys(fleet)
        self.robot = robot
        self._frames_key = self.keys.frames(robot)  # also validates the robot id
        self.transport = transport or ZenohTransport(zenoh or ZenohSettings())
        self.counters = LinkCounters()
        self._sent: collections.deque[tuple[int, bytes]] = collections.deque(maxlen=history)
        self._estimate_limits = estimate_limits or EstimateLimits()
        self._needs = Inbox(16)
        self._alive = Inbox(16)
        self._agent_alive = False
        self._streams: list[Inbox] = []
        self._server: asyncio.Task[None] | None = None
        self._last_invalid_log = -float("inf")

    async def __aenter__(self) -> RobotLink:
        self.transport.subscribe(self.keys.ctl("need", self.robot), self._needs)
        self.transport.watch_alive(self.keys.alive(self.robot), self._alive)
        await self.transport.open()
        self._server = asyncio.create_task(self._serve_needs())
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if self._server is not None:
            self._server.cancel()
            self._server = None
        await self.transport.close()
        for inbox in self._streams:
            inbox.put(_CLOSED)

    # -- frames ------------------------------------------------------------------------------

    def publish_frame(self, frame: SensorFrame) -> None:
        """Send ``frame`` (its robot's own data, nothing else) on ``frames/<robot>`` and keep it for
        ``ctl/need``. Steps never go backwards; publishing the latest step again re-sends it (an
        agent that already has it answers with its latest estimate). Raises ``ValueError`` for
        another robot's frame or a step behind the last, ``LocalProtocolError`` for a frame the
        wire refuses, ``RuntimeError`` outside ``async with``."""
        if self._server is None:
            raise RuntimeError("RobotLink is not open: use `async with RobotLink(...)`")
        if frame.robot != self.robot:
            raise ValueError(f"frame of robot {frame.robot!r} on {self.robot!r}'s link")
        last = self._sent[-1][0] if self._sent else 0
        if frame.k < last:
            raise ValueError(f"step {frame.k} after step {last}: steps never go backwards")
        own = replace(frame, true_pose=np.full(3, np.nan))
        data = encode_frame(own)
        if frame.k == last:
            self._sent.pop()
        self._sent.append((frame.k, data))
        self.transport.publish(self._frames_key, data)
        self.counters.frames_sent += 1

    async def _serve_needs(self) -> None:
        while True:
            self._answer((await self._needs.get()).payload)

    def _answer(self, payload: bytes) -> None:
        try:
            need = decode_control(payload)
        except RemoteProtocolError as exc:
            self._invalid("ctl/need", exc)
            self.counters.invalid_control += 1
            return
        if not isinstance(need, NeedFrames) or need.robot != self.robot:
            self._invalid("ctl/need", ValueError(f"not a frame request for {self.robot}: {need}"))
            self.counters.invalid_control += 1
            return
        self.counters.need_requests += 1
        if self._sent and need.k < self._sent[0][0]:
            self.counters.need_unserved += 1
            log.warning(
                "%s: the agent needs frames from step %d, the oldest kept is step %d",
                self.robot,
                need.k,
                self._sent[0][0],
            )
        for k, data in self._sent:
            if k >= need.k:
                self.transport.publish(self._frames_key, data)
                self.counters.frames_resent += 1

    # -- the agent ---------------------------------------------------------------------------

    @property
    def agent_alive(self) -> bool:
        """Whether the robot's agent holds its liveliness token (``alive/<robot>``) now."""
        for m in self._alive.drain():
            self._agent_alive = m.kind == "alive"
        return self._agent_alive

    async def wait_for_agent(self) -> None:
        """Until the robot's agent is alive (wrap it in ``asyncio.timeout`` to bound the wait)."""
        while not self.agent_alive:
            await self._alive.wait()

    def estimates(self, robot: str | None = None) -> AsyncIterator[EstimateMessage]:
        """The estimates of ``robot`` (default: this link's robot; ``"*"``: every robot of the
        fleet), decoded, from this call on, until the link closes. Invalid ones are counted in
        ``counters.invalid_estimates`` and skipped. Each call subscribes once more, for the
        link's lifetime; a reader that falls behind loses the oldest of 64."""
        inbox = Inbox(ESTIMATE_INBOX)
        self.transport.subscribe(self.keys.estimate(robot or self.robot), inbox)
        self._streams.append(inbox)
        return self._decoded(inbox)

    async def _decoded(self, inbox: Inbox) -> AsyncIterator[EstimateMessage]:
        while (m := await inbox.get()) is not _CLOSED:
            try:
                estimate = decode_estimate(m.payload, self._estimate_limits)
            except RemoteProtocolError as exc:
                self.counters.invalid_estimates += 1
                self._invalid(m.key, exc)
                continue
            yield estimate

    def _invalid(self, source: str, exc: Exception) -> None:
        now = asyncio.get_running_loop().time()
        if now - self._last_invalid_log >= INVALID_LOG_PERIOD:
            self._last_invalid_log = now
            log.warning("%s: invalid input on %s: %s", self.robot, source, exc)
