"""The asyncio shell around one :class:`~agents.node.RobotNode`: an agent of the fleet.

It consumes sensor frames (``frames/<robot>``), gossips its stack after every step and on a timer
(``stack/<robot>``), merges what its peers gossip, publishes its estimate (``estimate/<robot>``),
holds a liveliness token (``alive/<robot>``) and journals every frame and every accepted stack
before it acknowledges a step, so that a restart rebuilds exactly the belief it had.

Two modes. ``realtime``: a stack is merged as soon as it arrives if the link model lets it through
(evaluated with the sender's position from the message and the agent's own position), a frame is
processed as soon as it is the next one. ``lockstep``: a conductor orders round k
(:class:`~agents.control.StepOrder`) with the peers each robot hears; the agent merges exactly
those peers' stacks of round k − 1 and then steps, so the run repeats the in-process runner bit
for bit. In both modes an agent that sees a gap in its frames asks for them (``ctl/need``).
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from agents.control import NeedFrames, Status, StepOrder, Stop, decode_control, encode_control
from agents.journal import Journal, Record
from agents.links import LinkModel
from agents.node import RobotNode
from agents.transport.base import Inbox, Keys, Message, Transport
from estimator.models import SensorFrame
from protocol.codec import StackMessage
from protocol.errors import RemoteProtocolError
from protocol.estimate import EstimateMessage, encode_estimate
from protocol.frames import decode_frame

log = logging.getLogger(__name__)

MODES = ("lockstep", "realtime")


@dataclass(frozen=True, slots=True)
class RuntimeSettings:
    """``gossip_period`` (s) of the stack timer; ``retry_period`` (s) between requests for missing
    frames; ``stack_inbox`` capacity (drop-oldest); ``invalid_log_period`` (s) between two log
    lines about invalid input from one sender."""

    mode: str = "realtime"
    gossip_period: float = 0.5
    retry_period: float = 0.25
    stack_inbox: int = 256
    frame_inbox: int = 4096
    invalid_log_period: float = 5.0
    publish_local: bool = True

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode {self.mode!r} (known: {', '.join(MODES)})")
        if not (self.gossip_period > 0 and self.retry_period > 0):
            raise ValueError("gossip and retry periods must be positive")


@dataclass(slots=True)
class AgentCounters:
    """What the runtime adds to the node's counters."""

    ignored_out_of_range: int = 0
    invalid_frames: int = 0
    invalid_control: int = 0
    frames_processed: int = 0
    frames_duplicate: int = 0
    estimates_sent: int = 0
    need_requests: int = 0
    status_requests: int = 0
    replayed_frames: int = 0
    replayed_stacks: int = 0
    inbox_dropped: int = 0
    last_invalid: dict[str, float] = field(default_factory=dict)


class Agent:
    """One robot of the fleet on a :class:`~agents.transport.base.Transport`."""

    def __init__(
        self,
        node: RobotNode,
        transport: Transport,
        keys: Keys,
        links: LinkModel,
        settings: RuntimeSettings | None = None,
        journal: Journal | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.node = node
        self.robot = node.robot
        self.transport = transport
        self.keys = keys
        self.links = links
        self.settings = settings or RuntimeSettings()
        self.journal = journal
        self.clock = clock
        self.counters = AgentCounters()
        self.stacks = Inbox(self.settings.stack_inbox)
        self.frames = Inbox(self.settings.frame_inbox)
        self.control = Inbox(1024)
        self._pending_frames: dict[int, tuple[SensorFrame, bytes]] = {}
        self._orders: dict[int, StepOrder] = {}
        self._rounds: dict[tuple[str, int], tuple[StackMessage, bytes]] = {}
        self._last_estimate: bytes | None = None
        self._last_need = -math.inf
        self._step_us = (0, 0)
        self._last_stack: bytes | None = None
        self._previous_stack: bytes | None = None
        self._stop = asyncio.Event()
        self.stop_reason = ""

    # -- lifecycle ---------------------------------------------------------------------------

    def replay(self, records: Sequence[Record]) -> None:
        """Rebuild the belief from journal records (before :meth:`run`)."""
        for record in records:
            kind, body = record.kind, record.body
            if kind == "stack":
                self.node.on_stack(body)
                self.counters.replayed_stacks += 1
            elif kind == "frame":
                self.node.on_frame(decode_frame(body))
                self.counters.replayed_frames += 1
        if records:
            log.info(
                "%s: replayed %d frames and %d stacks from the journal (now at step %d)",
                self.robot,
                self.counters.replayed_frames,
                self.counters.replayed_stacks,
                self.node.k,
            )

    def stop(self, reason: str = "") -> None:
        self.stop_reason = self.stop_reason or reason
        self._stop.set()

    async def run(self) -> None:
        """Until :meth:`stop` (or a ``ctl/stop``): always closes the transport and the journal."""
        t = self.transport
        t.subscribe(self.keys.stack("*"), self.stacks)
        t.subscribe(self.keys.frames(self.robot), self.frames)
        t.subscribe(self.keys.ctl("**"), self.control)
        t.declare_alive(self.keys.alive(self.robot))
        try:
            await t.open()
            self._announce()
            tasks = [
                asyncio.create_task(self._gossip_timer()),
                asyncio.create_task(self._main()),
            ]
            stop_wait = asyncio.create_task(self._stop.wait())
            done, _ = await asyncio.wait([stop_wait, *tasks], return_when=asyncio.FIRST_COMPLETED)
            for task in [stop_wait, *tasks]:
                task.cancel()
            for task in done:
                if not task.cancelled() and task.exception() is not None:
                    raise task.exception()  # type: ignore[misc]
        finally:
            try:
                await t.close()
            finally:
                if self.journal is not None:
                    self.journal.close()

    # -- loops -------------------------------------------------------------------------------

    async def _gossip_timer(self) -> None:
        while True:
            await asyncio.sleep(self.settings.gossip_period)
            if self.settings.mode == "lockstep" and self._previous_stack is not None:
                # A peer still in round k may need our stack of round k − 1 (we may be ahead).
                self.transport.publish(self.keys.stack(self.robot), self._previous_stack)
            self._publish_stack()
            if self._frames_missing():
                self._ask_for_frames()

    async def _main(self) -> None:
        while not self._stop.is_set():
            self._drain()
            progressed = self._try_step()
            if not progressed:
                await self._wait_any(self.settings.retry_period)

    async def _wait_any(self, timeout: float) -> None:
        waits = [
            asyncio.create_task(i.wait(timeout)) for i in (self.stacks, self.frames, self.control)
        ]
        await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        for w in waits:
            w.cancel()

    def _drain(self) -> None:
        for m in self.control.drain():
            self._on_control(m)
        for m in self.frames.drain():
            self._on_frame_bytes(m.payload)
        for m in self.stacks.drain():
            self._on_stack_bytes(m)
        self.counters.inbox_dropped = self.stacks.dropped + self.frames.dropped

    # -- input -------------------------------------------------------------------------------

    def _on_control(self, m: Message) -> None:
        if not m.key.startswith(self.keys.ctl("")):
            return
        try:
            order = decode_control(m.payload)
        except RemoteProtocolError as exc:
            self.counters.invalid_control += 1
            self._log_invalid("ctl", exc)
            return
        if isinstance(order, StepOrder):
            if order.k > self.node.k:
                self._orders[order.k] = order
            elif order.k == self.node.k and self._last_estimate is not None:
                self._publish_estimate(self._last_estimate)  # the conductor missed our ack
        elif isinstance(order, Status):
            self.counters.status_requests += 1
            self._publish_estimate()  # fresh, with the counters of this moment
        elif isinstance(order, Stop):
            self.stop(order.reason or "stopped by the conductor")
        elif isinstance(order, NeedFrames):
            pass  # for the conductor

    def _on_frame_bytes(self, data: bytes) -> None:
        try:
            frame = decode_frame(data)
        except RemoteProtocolError as exc:
            self.counters.invalid_frames += 1
            self._log_invalid("frames", exc)
            return
        if frame.robot != self.robot:
            self.counters.invalid_frames += 1
            self._log_invalid("frames", ValueError(f"frame of robot {frame.robot}"))
            return
        if frame.k <= self.node.k:
            self.counters.frames_duplicate += 1
            if frame.k == self.node.k and self._last_estimate is not None:
                self._publish_estimate(self._last_estimate)
            return
        self._pending_frames.setdefault(frame.k, (frame, data))

    def _on_stack_bytes(self, m: Message) -> None:
        sender_key = self.keys.robot_of(m.key)
        if sender_key == self.robot:
            return  # our own publication, echoed by the session
        message = self.node.decode_stack(m.payload)
        if message is None:
            self._log_invalid(sender_key or m.key, ValueError(self.node.counters.last_error))
            return
        if message.sender == self.robot:
            return
        if self.settings.mode == "lockstep":
            if message.step >= self.node.k:
                self._rounds.setdefault((message.sender, message.step), (message, m.payload))
            return
        own = self.node.position
        sender_pos = message.position if message.position is not None else (math.nan, math.nan)
        receiver_pos = own if own is not None else (math.nan, math.nan)
        k = self.node.k + 1
        if not self.links.allowed(message.sender, self.robot, k, sender_pos, receiver_pos):
            # Before a robot's first step its position is unknown: no range to judge, so a stack
            # refused then is not counted as out of range (a neighbour's start-up announcement).
            if message.position is not None and own is not None:
                self.counters.ignored_out_of_range += 1
            return
        if self.node.merge(message) and self.journal is not None:
            self.journal.append("stack", m.payload)

    # -- stepping ----------------------------------------------------------------------------

    def _frames_missing(self) -> bool:
        nxt = self.node.k + 1
        if self.settings.mode == "lockstep":
            return nxt in self._orders and nxt not in self._pending_frames
        return bool(self._pending_frames) and nxt not in self._pending_frames

    def _try_step(self) -> bool:
        k = self.node.k + 1
        if k not in self._pending_frames:
            if self._frames_missing():
                self._ask_for_frames()
            return False
        if self.settings.mode == "lockstep":
            order = self._orders.get(k)
            if order is None:
                return False
            senders = order.links.get(self.robot, ())
            if any((s, k - 1) not in self._rounds for s in senders):
                return False
            for s in sorted(senders):
                message, data = self._rounds[(s, k - 1)]
                if self.node.merge(message) and self.journal is not None:
                    self.journal.append("stack", data)
        frame, data = self._pending_frames.pop(k)
        if self.journal is not None:
            self.journal.append("frame", data)
        # on_frame alone does the same; split to time the fusion + D and the L step separately.
        t0 = time.perf_counter()
        self.node.integrate_pending()
        t1 = time.perf_counter()
        self.node.track.advance(frame)
        t2 = time.perf_counter()
        self.node.on_frame(frame)
        t3 = time.perf_counter()
        self._step_us = (round(1e6 * (t2 - t1)), round(1e6 * ((t1 - t0) + (t3 - t2))))
        if self.journal is not None:
            self.journal.commit()  # acknowledged below only once it is on disk
        self.counters.frames_processed += 1
        self._forget_before(k)
        self._previous_stack = self._last_stack
        self._publish_stack()
        self._publish_estimate()
        return True

    def _forget_before(self, k: int) -> None:
        self._orders = {j: o for j, o in self._orders.items() if j > k}
        self._rounds = {key: v for key, v in self._rounds.items() if key[1] >= k}
        self._pending_frames = {j: f for j, f in self._pending_frames.items() if j > k}

    # -- output ------------------------------------------------------------------------------

    def _announce(self) -> None:
        """After start or restart: tell the fleet where this agent is."""
        self._publish_stack()
        if self.node.k > 0:
            self._publish_estimate()
        self._ask_for_frames()

    def _ask_for_frames(self) -> None:
        now = self.clock()
        if now - self._last_need < self.settings.retry_period:
            return
        self._last_need = now
        self.counters.need_requests += 1
        self.transport.publish(
            self.keys.ctl("need", self.robot),
            encode_control(NeedFrames(self.robot, self.node.k + 1)),
        )

    def _publish_stack(self) -> None:
        data = self.node.encoded_stack()
        self._last_stack = data
        self.transport.publish(self.keys.stack(self.robot), data)
        self.node.mark_sent(len(data))

    def _publish_estimate(self, data: bytes | None = None) -> None:
        if data is None:
            beliefs = {"distributed": self.node.distributed.snapshot(self.robot)}
            if self.settings.publish_local:
                beliefs["local"] = self.node.local.snapshot(self.robot)
            data = encode_estimate(
                EstimateMessage(self.robot, self.node.k, beliefs, self.counter_values())
            )
            self._last_estimate = data
        self.transport.publish(self.keys.estimate(self.robot), data)
        self.counters.estimates_sent += 1

    def counter_values(self) -> dict[str, int]:
        """Every counter of the node and the runtime, by name."""
        c, a = self.node.counters, self.counters
        return {
            "step": self.node.k,
            "stacks_sent": c.stacks_sent,
            "stacks_received": c.stacks_received,
            "stacks_merged": c.stacks_merged,
            "stacks_unchanged": c.stacks_unchanged,
            "stacks_invalid": c.invalid,
            "slots_rejected": c.rejected_slots,
            "empty_joins": c.empty_joins,
            "rebuilds": c.rebuilds,
            "ignored_out_of_range": a.ignored_out_of_range,
            "bytes_sent": c.bytes_sent,
            "bytes_received": c.bytes_received,
            "frames_processed": a.frames_processed,
            "frames_invalid": a.invalid_frames,
            "frames_duplicate": a.frames_duplicate,
            "control_invalid": a.invalid_control,
            "estimates_sent": a.estimates_sent,
            "need_requests": a.need_requests,
            "status_requests": a.status_requests,
            "replayed_frames": a.replayed_frames,
            "replayed_stacks": a.replayed_stacks,
            "inbox_dropped": a.inbox_dropped,
            "step_us_local": self._step_us[0],
            "step_us_distributed": self._step_us[1],
            "hypotheses_local": len(self.node.local.hypotheses),
            "hypotheses_distributed": len(self.node.distributed.hypotheses),
        }

    def _log_invalid(self, source: str, exc: Exception) -> None:
        """At most one line per source and ``invalid_log_period``."""
        now = self.clock()
        last = self.counters.last_invalid.get(source, -math.inf)
        if now - last >= self.settings.invalid_log_period:
            self.counters.last_invalid[source] = now
            log.warning("%s: invalid input from %s: %s", self.robot, source, exc)


def position_or_nan(position: tuple[float, float] | None) -> np.ndarray:
    return np.array(position if position is not None else (math.nan, math.nan), dtype=float)
