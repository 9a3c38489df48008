"""The asyncio shell around one :class:`~agents.core.AgentCore`: an agent of the fleet.

It subscribes the agent's keys — frames (``frames/<robot>``), stacks (``stack/*``; in a simulated
real time run ``stack/<peer>`` of the peers in range), run control (``ctl/stop``, ``ctl/step``,
``ctl/status``; ``ctl/need/*`` in an inbox of its own) and, in a
simulation, the simulator's links (``sim/links``) — into bounded inboxes, holds a liveliness
token (``alive/<robot>``), and carries out the core's actions: publish, journal (append, commit,
quarantine, cut), listen (whose stacks to subscribe to: the core's first ``Listen``), hear
(whose stacks wake the loop: the others wait in the inbox for the next batch), flush (send the
stack event-driven relay held back, when its push window ends), halt.

The estimator never runs on the event loop. Every message goes to the core in one worker thread
(decoding, merging and stepping take as long as they take there), while the loop goes on with the
gossip timer (the core's :meth:`~agents.core.AgentCore.on_timer`, which reads only what the worker
published whole), liveliness and control. Journal writes happen in the worker too, in the order
the core gives them, before the publications that acknowledge them.

With a :class:`~agents.ros2.bridge.Ros2Link` (docs/ros2.md) the agent also speaks ROS 2 over
rmw_zenoh: it holds the ROS graph's liveliness tokens, publishes every estimate's distributed
belief as ROS 2 messages (converted on the loop, right after the estimate itself) and turns the
robot's ROS 2 odometry and detections into frames (in the worker, ahead of the core).

Modes (``CoreSettings.mode``; docs/agents.md): ``realtime`` steps when the next frame is there;
``lockstep`` follows a conductor's orders, bit for bit the in-process runner.

Over 300 lines for a reason: the shell's three loops (messages, gossip timer, loop watch), its
one worker thread and the carrying out of the core's actions share one event loop, one set of
inboxes and one shutdown order (the worker's step, then the journal); split, that order would be
spread over modules.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import functools
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from agents.core import (
    Action,
    AgentCore,
    Append,
    Commit,
    CoreCounters,
    CoreSettings,
    CutJournal,
    Flush,
    Halt,
    Hear,
    Listen,
    Publish,
    Quarantine,
)
from agents.journal import Journal, MemoryLog, Record
from agents.node import RobotNode
from agents.transport.base import Inbox, Keys, Message, Transport, TransportError
from agents.transport.subscriptions import StackSubscriptions

if TYPE_CHECKING:
    from agents.ros2.bridge import Ros2Link

log = logging.getLogger(__name__)

STACK_INBOX_BYTES = 64 * 1024 * 1024
FRAME_INBOX_BYTES = 16 * 1024 * 1024
CONTROL_INBOX_BYTES = 4 * 1024 * 1024
REQUEST_INBOX_BYTES = 1024 * 1024
ORDER_KEYS = ("stop", "step", "status")  # ctl/<key>: the operator's and the conductor's
SHUTDOWN_STEP_WAIT_S = 1.0
LISTEN_ECHO_S = 0.05  # after subscribing to new peers' stacks (a declaration takes ~3 ms here)
LINKS_SAMPLE_S = 1.0  # how often the gossip timer counts the session's links (a call into Zenoh)
ROS2_RETRY_S = 2.0  # between attempts to reach the robot's ROS 2 router


def execute_journal_actions(log: Journal | MemoryLog, actions: Sequence[Action]) -> list[Action]:
    """Carry out a core's journal actions (append, commit, quarantine, cut) on ``log``, in order;
    return the other actions (publications, halts) for the caller."""
    rest: list[Action] = []
    for a in actions:
        if isinstance(a, Append):
            log.append(a.kind, a.body)
        elif isinstance(a, Commit):
            log.commit()
        elif isinstance(a, Quarantine):
            log.quarantine(a.kind, a.body, a.reason, a.index)
        elif isinstance(a, CutJournal):
            log.cut(a.index)
        else:
            rest.append(a)
    return rest


@dataclass(slots=True)
class ShellGauges:
    """What the shell itself measures, which the core reports with its estimates (its
    ``shell_counters`` port, :meth:`values`): messages its inboxes dropped, the longest the loop
    was held and the longest gap between two gossip ticks, the most links seen, and the ROS 2
    side's counters."""

    inboxes: tuple[Inbox, ...] = ()
    loop_lag_max_s: float = 0.0  # the longest the loop was held beyond a 50 ms tick
    gossip_gap_max_s: float = 0.0  # the longest time between two gossip ticks
    links_max: dict[str, int] = field(default_factory=lambda: {"stream": 0, "datagram": 0})
    ros2: Ros2Link | None = None

    def values(self) -> dict[str, int]:
        ros2 = self.ros2.bridge.counter_values() if self.ros2 is not None else {}
        return {
            "inbox_dropped": sum(i.dropped for i in self.inboxes),
            "loop_lag_max_us": round(1e6 * self.loop_lag_max_s),
            "gossip_gap_max_us": round(1e6 * self.gossip_gap_max_s),
            **{f"links_{kind}_max": n for kind, n in self.links_max.items()},
            **ros2,
        }


def new_agent(
    make_node: Callable[[], RobotNode],
    keys: Keys,
    transport: Transport,
    settings: CoreSettings | None = None,
    journal: Journal | None = None,
    wall_clock: Callable[[], float] | None = None,
    clock: Callable[[], float] = time.monotonic,
    ros2: Ros2Link | None = None,
) -> Agent:
    """An agent on ``transport`` whose core is built with its ports: the journal reader (the
    records of ``journal``, or of a log in memory), ``wall_clock`` (slot versions' bound), the
    step clock (``time.perf_counter``), the shell's gauges and ``clock`` (holding times)."""
    log: Journal | MemoryLog = journal if journal is not None else MemoryLog()
    gauges = ShellGauges()
    core = AgentCore(
        make_node, keys, settings, log.records, wall_clock, time.perf_counter, gauges.values, clock
    )
    return Agent(core, transport, log, gauges, clock, ros2)


class Agent:
    """One robot of the fleet: ``core`` on ``transport``, its records in ``log`` (the journal
    the core reads, :func:`new_agent`), the shell's measures in ``gauges`` (the core reports
    them). ``clock`` gives the ``now`` of every event; ``ros2``, if given, its ROS 2 side."""

    def __init__(
        self,
        core: AgentCore,
        transport: Transport,
        log: Journal | MemoryLog,
        gauges: ShellGauges,
        clock: Callable[[], float] = time.monotonic,
        ros2: Ros2Link | None = None,
    ) -> None:
        self.core = core
        self.robot = core.robot
        self.keys = core.keys
        self.settings = core.settings
        self.transport = transport
        self.log = log
        self.gauges = gauges
        self.clock = clock
        largest = self.settings.max_control_bytes
        # Orders (the operator's and the conductor's keys) and the requests any member may put
        # (``ctl/need/<robot>``) wait in inboxes of their own: a flood of requests never
        # displaces a Stop or a step order (issue 43, finding 3).
        self.control = Inbox(1024, CONTROL_INBOX_BYTES, largest)
        self.requests = Inbox(256, REQUEST_INBOX_BYTES, largest)
        self.frames = Inbox(4096, FRAME_INBOX_BYTES)
        self.stacks = Inbox(1024, STACK_INBOX_BYTES)
        self.stack_subscriptions = StackSubscriptions(transport, self.keys, self.stacks, self.robot)
        self.ros2 = ros2
        self.ros2_in = Inbox(4096, FRAME_INBOX_BYTES)
        ros2_inboxes = (self.ros2_in,) if ros2 is not None else ()
        self.inboxes = (self.control, self.requests, self.frames, self.stacks, *ros2_inboxes)
        gauges.inboxes, gauges.ros2 = self.inboxes, ros2
        self._doorbell = asyncio.Event()  # rung by every inbox: one wait for all of them
        for inbox in self.inboxes:
            inbox.ring(self._doorbell)
        self.stop_reason = ""
        self.worker_busy_s = 0.0
        self._links_sampled = -math.inf
        self._worker = concurrent.futures.ThreadPoolExecutor(1, f"agent-{self.robot}")
        self._stop = asyncio.Event()

    @property
    def node(self) -> RobotNode:
        return self.core.node

    @property
    def counters(self) -> CoreCounters:
        return self.core.counters

    # -- lifecycle ---------------------------------------------------------------------------

    def replay(self, records: Sequence[Record]) -> None:
        """Rebuild the belief from journal records (before :meth:`run`)."""
        execute_journal_actions(self.log, self.core.replay(records))

    def stop(self, reason: str = "") -> None:
        self.stop_reason = self.stop_reason or reason
        self._stop.set()

    async def run(self, on_open: Callable[[], None] = lambda: None) -> None:
        """Until :meth:`stop` (or a ``ctl/stop``): always closes the transport and the journal.
        ``on_open`` is called once the transport is open (its endpoints bound), before the
        first step."""
        t, keys = self.transport, self.keys
        for order in ORDER_KEYS:
            t.subscribe(keys.ctl(order), self.control)
        if self.settings.mode == "lockstep":
            # Round requests, which only a lock-step agent answers. In real time every peer's
            # request for frames would reach every agent to be read and ignored: N² messages.
            t.subscribe(keys.ctl("need", "*"), self.requests)
        if self.settings.simulation:
            # Its own row of the simulator's links only: the whole table is N² robot ids,
            # which every agent of a large simulated fleet would decode at every step.
            t.subscribe(keys.sim_links(self.robot), self.control)
            t.subscribe(keys.sim_listen(self.robot), self.control)
        t.subscribe(keys.frames(self.robot), self.frames)
        t.declare_alive(keys.alive(self.robot))
        if self.ros2 is not None:
            self.ros2.bridge.next_step = self.node.k + 1  # after a replay: the journal's next step
            for expr in self.ros2.bridge.inputs:
                self.ros2.transport.subscribe(expr, self.ros2_in)
            for token in self.ros2.bridge.tokens():
                self.ros2.transport.declare_alive(token)
        try:
            await t.open()
            on_open()
            self._carry_out(await self._in_worker(lambda: self.core.start(self.clock())))
            tasks = [
                asyncio.create_task(self._gossip_timer()),
                asyncio.create_task(self._main()),
                asyncio.create_task(self._watch_loop()),
            ]
            if self.ros2 is not None and self.ros2.own_session:
                tasks.append(asyncio.create_task(self._open_ros2(self.ros2.transport)))
            stop_wait = asyncio.create_task(self._stop.wait())
            done, _ = await asyncio.wait([stop_wait, *tasks], return_when=asyncio.FIRST_COMPLETED)
            for task in [stop_wait, *tasks]:
                task.cancel()
            for task in done:
                if not task.cancelled() and task.exception() is not None:
                    raise task.exception()  # type: ignore[misc]
        finally:
            try:
                if self.ros2 is not None and self.ros2.own_session:
                    await self.ros2.transport.close()
                await t.close()
            finally:
                # A step still running in the worker is waited for up to SHUTDOWN_STEP_WAIT_S,
                # then abandoned uncommitted (the process is about to exit; a torn commit is cut
                # at the next open). The journal is never closed under a running step.
                loop = asyncio.get_running_loop()
                idle = loop.run_in_executor(None, self._worker.shutdown)
                try:
                    await asyncio.wait_for(asyncio.shield(idle), SHUTDOWN_STEP_WAIT_S)
                except TimeoutError:
                    log.warning(
                        "%s: a step was still running at shutdown: not committed", self.robot
                    )
                else:
                    self.log.close()

    # -- loops -------------------------------------------------------------------------------

    async def _open_ros2(self, session: Transport) -> None:
        """The ROS 2 side's own session (a client of the robot's router), tried every
        ``ROS2_RETRY_S`` until the router answers, so that the agent runs whether rmw_zenohd
        starts before it or after; once open, Zenoh itself reconnects it to a restarted router.
        Then the task ends (the other loops go on)."""
        tries = 0
        while True:
            try:
                await session.open()
            except TransportError as exc:
                if tries == 0:
                    log.warning(
                        "%s: ROS 2 router not reachable, retrying every %.0f s: %s",
                        self.robot, ROS2_RETRY_S, exc, extra={"event": "ros2_waiting"},
                    )  # fmt: skip
                tries += 1
                await asyncio.sleep(ROS2_RETRY_S)
            else:
                log.info("%s: ROS 2 session open", self.robot, extra={"event": "ros2_open"})
                await self._stop.wait()
                return

    async def _gossip_timer(self) -> None:
        """On the loop, whatever the worker is doing; ticks on a fixed grid (no drift): a late
        tick does not delay the next ones."""
        period = self.settings.gossip_period
        last = due = time.perf_counter()
        while True:
            due += period
            now = time.perf_counter()
            if due < now - period:
                due = now  # the loop was held for more than a period: skip the missed ticks
            await asyncio.sleep(max(0.0, due - now))
            now = time.perf_counter()
            g = self.gauges
            g.gossip_gap_max_s = max(g.gossip_gap_max_s, now - last)
            last = now
            if now - self._links_sampled >= LINKS_SAMPLE_S:
                self._links_sampled = now
                links = self.transport.links()
                g.links_max = {k: max(n, links.get(k, 0)) for k, n in g.links_max.items()}
            self._carry_out(self.core.on_timer(self.clock()))

    async def _watch_loop(self, tick: float = 0.05) -> None:
        """Measures how long the loop is ever held: a 50 ms sleep that wakes late was held (a
        hold longer than the tick always delays a wake; 10 ms ticks cost 20 agents 3 % of the
        machine in wake-ups)."""
        while True:
            t0 = time.perf_counter()
            await asyncio.sleep(tick)
            lag = time.perf_counter() - t0 - tick
            self.gauges.loop_lag_max_s = max(self.gauges.loop_lag_max_s, lag)

    async def _main(self) -> None:
        while not self._stop.is_set():
            self._doorbell.clear()  # before draining: a message put after the drain rings it
            messages = [m for inbox in self.inboxes for m in inbox.drain()]
            if not messages:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._doorbell.wait(), self.settings.retry_period)
                continue
            actions = await self._in_worker(functools.partial(self._handle, messages))
            self._carry_out(actions)

    async def _in_worker(self, work: Callable[[], list[Action]]) -> list[Action]:
        loop = asyncio.get_running_loop()
        t0 = time.perf_counter()
        try:
            return await loop.run_in_executor(self._worker, work)
        finally:
            self.worker_busy_s += time.perf_counter() - t0

    def _handle(self, messages: list[Message]) -> list[Action]:
        """In the worker: every message through the core, journal actions carried out here (in
        order, before the publications that follow them); the rest goes back to the loop. ROS 2
        samples become the frames they complete, in their place."""
        puts, arrived = [], []
        frames_key = self.keys.frames(self.robot)
        now, mono = self.clock(), time.monotonic()
        for m in messages:
            if m.kind != "put":
                continue
            if self.ros2 is not None and self.ros2.bridge.input_type(m.key) is not None:
                frames = self.ros2.bridge.on_input(m.key, m.payload)
                puts += [(frames_key, f) for f in frames]
                arrived += [now] * len(frames)
            else:
                puts.append((m.key, m.payload))
                arrived.append(now - (mono - m.at))  # on the agent's clock (holding times)
        actions = self.core.on_messages(puts, now, arrived)
        return execute_journal_actions(self.log, actions)

    def _carry_out(self, actions: Sequence[Action]) -> None:
        """On the loop: publications and halts."""
        for a in actions:
            if isinstance(a, Publish):
                self.transport.publish(a.key, a.payload)
                if self.ros2 is not None and a.key == self.keys.estimate(self.robot):
                    for sample in self.ros2.bridge.on_estimate(a.payload, time.time_ns()):
                        self.ros2.publish(sample.key, sample.payload, sample.attachment)
            elif isinstance(a, Halt):
                self.stop(a.reason)
            elif isinstance(a, Hear):
                self.stacks.wake_for(a.keys)
            elif isinstance(a, Flush):
                delay = max(0.0, a.at - self.clock())
                asyncio.get_running_loop().call_later(delay, self._flush)
            elif isinstance(a, Listen) and self.stack_subscriptions.follow(a.peers):
                # What a new peer published while the subscription was being declared is lost:
                # gossip once more when the declaration is through, so that it learns now what
                # this agent lacks (and sends it: delta gossip) instead of at its next tick.
                asyncio.get_running_loop().call_later(LISTEN_ECHO_S, self._echo)
            else:
                execute_journal_actions(self.log, [a])

    def _flush(self) -> None:
        if not self._stop.is_set():
            self._carry_out(self.core.on_flush(self.clock()))

    def _echo(self) -> None:
        if not self._stop.is_set():
            self._carry_out(self.core.on_timer(self.clock(), announce=True))

    def counter_values(self) -> dict[str, int]:
        return self.core.counter_values()
