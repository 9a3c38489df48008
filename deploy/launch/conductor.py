"""The conductor of a simulated fleet: the world's side of a launch.

It publishes every robot's sensor frames (``frames/<robot>``), orders lock-step rounds
(``ctl/step``) with the links the scenario's link model allows on ground truth, answers agents'
requests for missing frames (``ctl/need``), and collects their estimates (``estimate/<robot>``).
A :class:`~deploy.launch.scoring.Scorer` scores them against ground truth; besides the links it
is the only user of the truth.

Over 300 lines for a reason: everything the world's side publishes and observes over one
Zenoh session (frames, orders, links, need answers, estimates, stacks and the relay check on
them), around one pump; the scoring itself is in :mod:`deploy.launch.scoring`.
"""

from __future__ import annotations

import collections
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from agents.control import NeedFrames, StepOrder, Stop, decode_control, encode_control
from agents.links import LinkModel
from agents.transport.base import Inbox, Keys, Transport
from deploy.launch.scoring import Scorer
from estimator.models import SensorFrame
from protocol.codec import decode
from protocol.errors import RemoteProtocolError, SenderMismatch
from protocol.estimate import EstimateMessage, decode_estimate, decode_estimate_head
from protocol.frames import encode_frame
from sim.scenario import Scenario

log = logging.getLogger(__name__)

Array = NDArray[np.float64]


# A lock-step round's re-sends back off to this many retry periods: a re-sent order names the
# robots it still waits for, and only those answer it (with their estimate), so its cost does not
# grow with the fleet.
RESEND_MAX = 8
# Estimates are scored against the truth after the run, or while more than this many bytes of
# them wait: the scoring is the conductor's largest cost (8.5 ms an estimate of a 20-robot world),
# and during a run it competes with the agents for the cores (20 agents on 2 cores: the conductor,
# minutes of scoring behind, heard only the first 9–15 of 20 steps by the end of a run whose agents
# had all finished; a bound of 256 estimates started the scoring at step 13 of 20, 17 % of the
# machine, and every agent fell two steps further behind). They wait as the bytes that came (a
# decoded estimate takes 5 times as much memory), decoded again when scored: 64 MiB is ~6,000
# estimates of a 20-robot world, 300 steps of 20 agents.
MAX_UNSCORED_BYTES = 64 * 2**20


class ConductorError(RuntimeError):
    """The run cannot go on (an agent is gone, a deadline passed)."""


@dataclass(slots=True)
class Collected:
    """What came back: metrics per belief (robots, steps), class-ECE bin statistics per belief
    (robots, steps, 3, bins), step times and the agents' counters. ``received`` counts every
    estimate of a robot, ``repeated`` those of a step already scored (answers to re-sent orders
    and frames): each (robot, step) is scored, and its step times kept, once. ``invalid``
    counts the estimates refused: a head (robot, step, counters) that is not valid or came on
    another robot's key, as it comes; arrays that are not, when the estimate is scored."""

    metrics: dict[str, dict[str, Array]]
    calibration: dict[str, Array] = field(default_factory=dict)
    step_ms: dict[str, list[float]] = field(default_factory=dict)
    counters: dict[str, dict[str, int]] = field(default_factory=dict)
    received: dict[str, int] = field(default_factory=dict)
    repeated: int = 0
    invalid: int = 0
    last_step: dict[str, int] = field(default_factory=dict)
    # Real time: each robot's last step the conductor had heard of one period after the last
    # frame, when every robot should have taken it (then ``settle`` lets the late ones finish).
    on_time: dict[str, int] = field(default_factory=dict)
    estimates: dict[tuple[str, int], EstimateMessage] = field(default_factory=dict)
    # observe_stacks: (arrival time, robot, {owner: stamp}) of every stack a robot published.
    stack_log: list[tuple[float, str, dict[str, int]]] = field(default_factory=list)
    # observe_stacks: (arrival time, robot, {owner: stamp}) of the slots each stack carried (a
    # delta stack's slots are what the robot forwarded; ``stack_log`` has what it held).
    slot_log: list[tuple[float, str, dict[str, int]]] = field(default_factory=list)
    # Real time: when the links of each step were published (time.monotonic(), as stack_log).
    links_published: dict[int, float] = field(default_factory=dict)
    # Real time: seconds from the publication of a step (its links, then its frames) to the
    # arrival of a robot's first estimate of it, per (robot, step): how close to the next frame
    # each step ended (a robot that skipped a step's estimate while catching up has none).
    answered_s: dict[tuple[str, int], float] = field(default_factory=dict)
    # When each robot's first estimate of each step arrived (time.monotonic(), as stack_log):
    # the end of its step k, for the age of information (deploy.launch.aoi).
    ended: dict[tuple[str, int], float] = field(default_factory=dict)
    # (arrival, robot, step, {owner: stamp}) of every first estimate of a step that said which
    # peer versions its fusion had integrated (``EstimateMessage.fused``).
    fused_log: list[tuple[float, str, int, dict[str, int]]] = field(default_factory=list)
    # (arrival, robot, step, ms) of every such estimate whose counters give the age of every
    # peer version it fused by holding times (``peer_age_max_ms``: agents.ages): what the agents
    # say without a shared clock, beside what ``fused_log`` and ``ended`` measure with one.
    age_log: list[tuple[float, str, int, int]] = field(default_factory=list)


def without_truth(frame: SensorFrame) -> SensorFrame:
    """The frame an agent gets: the simulator keeps the true pose for its metrics."""
    return replace(frame, true_pose=np.full(3, np.nan))


def links_at(
    links: LinkModel, frames: Mapping[str, Sequence[SensorFrame]], robots: Sequence[str], k: int
) -> dict[str, tuple[str, ...]]:
    """Who hears whom at the start of step k, on the true poses of step k (as the in-process
    runner delivers)."""
    pos = {r: frames[r][k - 1].true_pose for r in robots}
    return {
        receiver: tuple(
            s
            for s in robots
            if s != receiver and links.allowed(s, receiver, k, pos[s], pos[receiver])
        )
        for receiver in robots
    }


class Conductor:
    """Drives ``robots`` of ``scenario`` through its steps over ``transport``."""

    def __init__(
        self,
        scenario: Scenario,
        frames: Mapping[str, Sequence[SensorFrame]],
        robots: Sequence[str],
        transport: Transport,
        keys: Keys,
        links: LinkModel,
        retry_period: float = 0.5,
        keep_estimates: bool = False,
        observe_stacks: bool = False,
        on_links: Callable[[int, dict[str, tuple[str, ...]]], None] | None = None,
    ) -> None:
        """``keep_estimates``: keep every decoded estimate in ``collected.estimates``;
        ``observe_stacks``: log (time, robot, {owner: stamp}) of every stack heard;
        ``on_links(k, verdict)``: a realtime run's links of step k, before they are published
        (a netns run applies them to real packets)."""
        self.scenario = scenario
        self.frames = frames
        self.robots = list(robots)
        self.transport = transport
        self.keys = keys
        self.links = links
        self.retry_period = retry_period
        self.keep_estimates = keep_estimates
        self.observe_stacks = observe_stacks
        self.on_links = on_links
        # Each message keeps its arrival time (``Message.at``): the conductor drains its inboxes
        # only every 50 ms or on an estimate, too coarse to time a stack's publication (or an
        # estimate's arrival, which it drains at once but may share the machine with busy
        # agents) by.
        self.stacks = Inbox(100_000)
        self.estimates = Inbox(100_000)
        self.control = Inbox(10_000)
        self.alive_events = Inbox(10_000)
        self.alive: set[str] = set()
        self.k = 0
        self.published_up_to: dict[str, int] = {r: 0 for r in self.robots}
        self.scorer = Scorer(scenario, frames, self.robots)
        self.collected = Collected(self.scorer.metrics, self.scorer.calibration)
        self._index = {r: i for i, r in enumerate(self.robots)}
        self._acked: dict[str, int] = {r: 0 for r in self.robots}
        self._scored: set[tuple[str, int]] = set()
        self._unscored: collections.deque[bytes] = collections.deque()  # validated estimates
        self._unscored_bytes = 0
        self._need_order_t = -math.inf  # when a frame request last made the order go again
        # Real time: the links last sent a step ahead, and their step.
        self._links_ahead: tuple[int, dict[str, tuple[str, ...]]] = (-1, {})

    async def open(self) -> None:
        self.transport.subscribe(self.keys.estimate("*"), self.estimates)
        self.transport.subscribe(self.keys.ctl("need", "*"), self.control)
        self.transport.watch_alive(self.keys.alive("*"), self.alive_events)
        if self.observe_stacks:
            self.transport.subscribe(self.keys.stack("*"), self.stacks)
            self.transport.subscribe(self.keys.stack_to("*", "*"), self.stacks)  # pushes
        await self.transport.open()

    # -- helpers -----------------------------------------------------------------------------

    def _publish_frames(self, robot: str, first: int, last: int) -> None:
        """Frames as a robot's perception would send them: without ground truth."""
        for k in range(max(first, 1), last + 1):
            frame = without_truth(self.frames[robot][k - 1])
            self.transport.publish(self.keys.frames(robot), encode_frame(frame))
        self.published_up_to[robot] = max(self.published_up_to[robot], last)

    def _order(self, k: int) -> None:
        """Order round k, naming the robots whose estimate of it is still missing: only those
        answer a re-sent order (each answer can be a large estimate)."""
        waiting = tuple(r for r in self.robots if self._acked[r] < k)
        order = StepOrder(k, links_at(self.links, self.frames, self.robots, k), waiting)
        self.transport.publish(self.keys.ctl("step"), encode_control(order))

    def _publish_links(self, k: int) -> None:
        """Realtime simulations: who hears whom at step k, decided here on the true poses and
        obeyed only by agents configured as simulated (``simulation = true``); and who will at
        step k + 1, for their subscriptions (``sim/listen``)."""
        sent, verdict = self._links_ahead
        if sent != k:
            verdict = links_at(self.links, self.frames, self.robots, k)
        if self.on_links is not None:
            self.on_links(k, verdict)
        self.collected.links_published[k] = time.monotonic()
        self._publish_rows(self.keys.sim_links, k, verdict)
        if all(k < len(self.frames[r]) for r in self.robots):
            # A step ahead, on its own key: an agent subscribes to the stacks of a robot it is
            # about to hear before it hears it, but still obeys only the links of sim/links.
            # ``links_at`` is a pure function of the step: this is the verdict sent at k + 1,
            # kept for it.
            ahead = links_at(self.links, self.frames, self.robots, k + 1)
            self._links_ahead = (k + 1, ahead)
            self._publish_rows(self.keys.sim_listen, k + 1, ahead)

    def _publish_rows(
        self, key: Callable[[str], str], k: int, verdict: Mapping[str, tuple[str, ...]]
    ) -> None:
        """Each robot's row of ``verdict`` on its own key (``sim/links/<robot>``): a robot reads
        whom it hears, not the N² ids of the whole table."""
        for r in self.robots:
            row = StepOrder(k, {r: verdict.get(r, ())})
            self.transport.publish(key(r), encode_control(row))

    def pump(self) -> None:
        """Handle everything that arrived: liveliness, frame requests, estimates."""
        for m in self.alive_events.drain():
            robot = self.keys.robot_of(m.key)
            if robot in self._index:
                (self.alive.add if m.kind == "alive" else self.alive.discard)(robot)
        for m in self.control.drain():
            try:
                need = decode_control(m.payload)
            except RemoteProtocolError:
                continue
            if isinstance(need, NeedFrames) and need.robot in self._index and self.k > 0:
                self._publish_frames(need.robot, need.k, self.k)
                now = time.monotonic()
                # The order too (a restarted agent lacks it), at most once a retry period: it
                # goes to every agent, and each answers it with its estimate.
                if need.k <= self.k and now - self._need_order_t >= self.retry_period:
                    self._need_order_t = now
                    self._order(self.k)
        for m in self.estimates.drain():
            self._on_estimate(m.payload, m.key, m.at)
        while self._unscored_bytes > MAX_UNSCORED_BYTES:
            self._score(self._unscored.popleft())
        for m in self.stacks.drain():
            robot = self.keys.stack_sender(m.key)
            if robot not in self._index:
                continue
            try:
                message = decode(m.payload)
            except RemoteProtocolError:
                continue
            if message.sender == robot:
                # What the robot holds: a delta stack's digest, or a full stack's slots.
                held = carried = message.stack.stamps()
                if message.have is not None:
                    held = {owner: stamp for owner, (_, stamp) in message.have.items()}
                at = m.at
                self.collected.stack_log.append((at, robot, held))
                if carried:
                    self.collected.slot_log.append((at, robot, carried))

    def _on_estimate(self, data: bytes, key: str | None = None, at: float | None = None) -> None:
        """An estimate as it comes: its robot, step and counters are read and checked at once;
        its beliefs' arrays (nine tenths of the decoding) when it is scored, unless every
        estimate is kept decoded (``keep_estimates``). In real time the conductor shares the
        agents' CPU, and decoding 20 estimates a period in full took 2-3 % of the machine.
        ``at``: when it arrived (``time.monotonic()``), for :attr:`Collected.answered_s`."""
        try:
            est = decode_estimate(data) if self.keep_estimates else decode_estimate_head(data)
        except RemoteProtocolError as exc:
            self._refused(exc)
            return
        if key is not None and key != self.keys.estimate(est.robot):
            # Only robot r speaks for r (on a secure fleet the access control already refuses
            # a put of another identity on r's key; this also holds on an open one).
            self._refused(SenderMismatch(f"an estimate of {est.robot!r} on {key!r}", "robot"))
            return
        if est.robot not in self._index or not 1 <= est.k <= self.scenario.steps:
            return
        c = self.collected
        c.received[est.robot] = c.received.get(est.robot, 0) + 1
        c.counters[est.robot] = dict(est.counters)
        if self.keep_estimates:
            c.estimates[(est.robot, est.k)] = est
        c.last_step[est.robot] = max(c.last_step.get(est.robot, 0), est.k)
        self._acked[est.robot] = max(self._acked[est.robot], est.k)
        # A step's estimate comes again whenever an order or a frame is re-sent (lock-step
        # agents answer each with it): the first is scored, the others only refresh the
        # counters. Scoring every hypothesis against the truth is the conductor's largest cost:
        # with 50 agents, re-scoring the repeats kept it minutes behind the fleet.
        if (est.robot, est.k) in self._scored:
            c.repeated += 1
            return
        self._scored.add((est.robot, est.k))
        if at is not None and est.k in c.links_published:
            c.answered_s[(est.robot, est.k)] = at - c.links_published[est.k]
        if at is not None:
            c.ended[(est.robot, est.k)] = at
            if est.fused is not None:
                c.fused_log.append((at, est.robot, est.k, est.fused))
                peers = len([o for o in est.fused if o != est.robot])
                if peers and est.counters.get("peers_aged") == peers:
                    c.age_log.append((at, est.robot, est.k, est.counters["peer_age_max_ms"]))
        self._unscored.append(data)
        self._unscored_bytes += len(data)
        for belief, key in (("local", "step_us_local"), ("distributed", "step_us_distributed")):
            if key in est.counters:
                c.step_ms.setdefault(belief, []).append(est.counters[key] / 1e3)

    def _score(self, data: bytes) -> None:
        self._unscored_bytes -= len(data)
        try:
            est = decode_estimate(data)  # its head was checked when it came
        except RemoteProtocolError as exc:
            self._refused(exc)  # its arrays are not what they should be: not scored
            return
        for belief, snap in est.beliefs.items():
            self.scorer.record(belief, est.robot, est.k, snap)

    def _refused(self, exc: RemoteProtocolError) -> None:
        self.collected.invalid += 1
        log.warning("invalid estimate: %s", exc)

    def score_pending(self) -> None:
        """Score every estimate received and not scored yet (``collected.metrics`` and
        ``calibration`` are complete after this; the launcher calls it when the run is over)."""
        while self._unscored:
            self._score(self._unscored.popleft())

    def acked(self, robot: str) -> int:
        return self._acked[robot]

    # -- runs --------------------------------------------------------------------------------

    async def wait_alive(self, timeout: float, check: Callable[[], None] | None = None) -> None:
        deadline = time.monotonic() + timeout
        while set(self.robots) - self.alive:
            if check is not None:
                check()
            if time.monotonic() > deadline:
                missing = sorted(set(self.robots) - self.alive)
                raise ConductorError(f"agents {missing} did not come up within {timeout:.0f} s")
            await self.alive_events.wait(0.1)
            self.pump()

    async def run_lockstep(
        self,
        steps: int,
        on_step: Callable[[int], None] | None = None,
        check: Callable[[], None] | None = None,
        step_timeout: float = 120.0,
    ) -> None:
        """Round by round: order round k, send frame k, wait for every agent's estimate of k
        (re-sending the order and the late agents' frames after ``retry_period``, then twice as
        long each time up to ``RESEND_MAX`` × ``retry_period``; a re-sent order names the
        robots it waits for, and only those answer it with their estimate). A round
        fails when no agent acknowledged it for ``step_timeout`` seconds: a slow round that keeps
        making progress (many agents on few cores) is waited for; a stuck one is not."""
        for k in range(1, steps + 1):
            self.k = k
            self._order(k)
            for r in self.robots:
                self._publish_frames(r, k, k)
            deadline = time.monotonic() + step_timeout
            last_send, wait = time.monotonic(), self.retry_period
            late = [r for r in self.robots if self._acked[r] < k]
            while late:
                if check is not None:
                    check()
                await self.estimates.wait(0.05)
                self.pump()
                now = time.monotonic()
                still = [r for r in self.robots if self._acked[r] < k]
                if len(still) < len(late):
                    deadline = now + step_timeout  # progress
                late = still
                if late and now > deadline:
                    raise ConductorError(
                        f"step {k}: no estimate from {late} in the last {step_timeout} s"
                    )
                if late and now - last_send > wait:
                    last_send, wait = now, min(2 * wait, RESEND_MAX * self.retry_period)
                    self._order(k)
                    for r in self.robots:
                        if self._acked[r] < k:
                            self._publish_frames(r, k, k)
            if on_step is not None:
                on_step(k)

    async def run_realtime(
        self,
        steps: int,
        period: float,
        on_step: Callable[[int], None] | None = None,
        check: Callable[[], None] | None = None,
        settle: float = 10.0,
    ) -> None:
        """One frame per robot every ``period`` seconds whatever the agents do; then up to
        ``settle`` seconds for the last estimates. Every put is best-effort (a congested link
        drops it), so while waiting the last frame is sent again every ``retry_period`` to the
        robots not heard from: one that already took that step answers with its estimate again,
        one still behind ignores the duplicate (or gets a frame it lost)."""
        start = time.monotonic()
        for k in range(1, steps + 1):
            self.k = k
            self._publish_links(k)
            for r in self.robots:
                self._publish_frames(r, k, k)
            if on_step is not None:
                on_step(k)
            while time.monotonic() < start + k * period:
                if check is not None:
                    check()
                await self.estimates.wait(
                    max(0.0, min(0.05, start + k * period - time.monotonic()))
                )
                self.pump()
        self.collected.on_time = {r: self._acked[r] for r in self.robots}
        deadline = time.monotonic() + settle
        last_send = time.monotonic()
        while any(self._acked[r] < steps for r in self.robots) and time.monotonic() < deadline:
            if check is not None:
                check()
            await self.estimates.wait(0.05)
            self.pump()
            if time.monotonic() - last_send > self.retry_period:
                last_send = time.monotonic()
                for r in self.robots:
                    if self._acked[r] < steps:
                        self._publish_frames(r, steps, steps)

    def relayed(self) -> bool:
        """Whether every robot's latest observed stack holds every robot's final own slot (the
        newest stamp the owner itself published)."""
        own: dict[str, int] = {}
        latest: dict[str, dict[str, int]] = {}
        for _, robot, stamps in self.collected.stack_log:
            own[robot] = max(own.get(robot, 0), stamps.get(robot, 0))
            latest[robot] = stamps
        if set(latest) != set(self.robots):
            return False
        return all(
            latest[holder].get(owner, 0) >= own[owner]
            for holder in self.robots
            for owner in self.robots
        )

    async def linger(self, timeout: float, check: Callable[[], None] | None = None) -> None:
        """After the run: keep pumping (the agents keep gossiping) until :meth:`relayed`, at
        most ``timeout`` seconds. How long multi-hop relay takes once the steps are done is then
        in ``collected.stack_log``, whatever the machine's load was during the run."""
        deadline = time.monotonic() + timeout
        while not self.relayed() and time.monotonic() < deadline:
            if check is not None:
                check()
            await self.stacks.wait(0.05)
            self.pump()

    def stop_agents(self, reason: str = "run complete") -> None:
        self.transport.publish(self.keys.ctl("stop"), encode_control(Stop(reason)))
