"""AgentCore: one agent of the fleet without any I/O (the aioquic pattern).

The core takes events — a message that arrived on a key (frame, stack, control, simulated links),
a timer tick — each with the current time ``now``, and returns *actions*: publish these bytes on
that key, append a record to the journal, commit it, quarantine an input, log. It owns the
:class:`~agents.node.RobotNode` and every bounded buffer around it; it never touches a socket, a
clock, a thread or a file. ``agents/runtime.py`` is the asyncio shell that feeds it.

Threading contract (what lets gossip go on during a long step): :meth:`on_message`,
:meth:`replay` and :meth:`start` may take as long as an estimator step and are called from one
thread at a time (the shell's worker). :meth:`on_timer` is cheap and may be called from another
thread meanwhile: it only reads values the worker publishes whole (the encoded stack, the next
missing step), never the node.

Fail-soft. A step that raises is never committed: the node is rebuilt from the committed records
(``committed()``, the journal), the slots merged since the last commit are refused for good, and
the step is tried again without them; if it fails again the frame is quarantined (a side file
next to the journal) and the step is taken with its odometry only, so the robot's trajectory goes
on. If even the odometry fails, the agent stays at its last good step, alive, until another frame
arrives for that step (the failing bytes are never tried again). Every buffer is bounded: frames,
orders, lock-step rounds and simulated links only within ``window`` steps ahead, control
messages by size, refused slot versions and failed frames by count.

Catching up (real time). An agent whose CPU cannot keep up — many agents on one machine, a long
step — finds the next frame already waiting when it starts a step. Such a step defers the
fusion of the peers' slots (and the own stack's publication) to the step that catches up, at
most ``catch_up`` steps in a row: the robot's own estimate stays current, and every held slot is
fused a step or a few later, as if it had come later (nothing is lost: fusion takes every slot
still newer than the version D used). A deferred step is journaled as ``frame_unfused``, and the
stacks merged before it stay uncommitted suspects until the step that fuses them, so that a
replay defers the same fusion and a fusion that fails rolls them back.

Over 300 lines for a reason: the agent's whole event logic (frames, stacks, control, links,
timers, roll-back and replay) is one state machine over one node; split, its invariants (what is
committed, what is refused) would be spread over modules that all mutate the same state.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import time
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from agents.control import (
    NeedFrames,
    NeedRound,
    Status,
    StepOrder,
    Stop,
    decode_control,
    encode_control,
)
from agents.journal import Record
from agents.node import RobotNode
from agents.transport.base import Keys
from estimator.models import SensorFrame
from protocol.codec import StackMessage
from protocol.errors import RemoteProtocolError, SenderMismatch
from protocol.estimate import EstimateMessage, encode_estimate
from protocol.frames import decode_frame, encode_frame
from protocol.stack import Stack

log = logging.getLogger(__name__)

MODES = ("lockstep", "realtime")
DIGEST_LIFE = 3  # gossip periods a peer's digest counts for (real time): then it is out of reach
# Real time: a tick sends an unchanged digest alone only this many gossip periods after the last
# (under DIGEST_LIFE, so that peers keep counting this robot), unless a peer's digest since then
# holds a version this robot lacks (docs/wire.md, "Delta gossip").
DIGEST_REFRESH = 2
STACK_GOSSIP = ("delta", "ask", "full")
MAX_REFUSED = 4096  # slot versions remembered as refused (oldest forgotten first)
# How far ahead of the receiver's clock a slot's version may be (docs/wire.md, "Versions and
# epochs"): an epoch is its owner's start in ms, so a stamp (a step) can be at most what the owner
# could have stepped since then at MAX_STEP_RATE, with CLOCK_SKEW_S for unsynchronised clocks and
# STAMP_SLACK steps for a fleet that starts at a step other than 0.
MAX_STEP_RATE = 100.0  # steps per second: 50× a 2 Hz robot, above any lock-step simulation here
CLOCK_SKEW_S = 300.0
STAMP_SLACK = 10_000
GOSSIP_PERIOD_S = 0.5  # the one default gossip period (agent configs, launches)
LOCKSTEP_RESEND_MAX = 8  # periods: the longest a lock-step agent waits to re-send a stack
# ... in a fleet of up to LOCKSTEP_RESEND_MAX / 2 + 1 robots: beyond, 2 (N − 1) periods, so that
# whatever N an agent receives about one re-sent stack every two periods (N² / (2 (N − 1)) / N).
WINDOW_STEPS = 64  # the one default of how far ahead frames, orders, rounds and links are kept
# At most this many steps in a row defer their fusion while the agent is behind its frames: the
# peers' slots are fused at least every (CATCH_UP_STEPS + 1)-th step (every 2 s at 0.5 s steps).
CATCH_UP_STEPS = 3
FRAME, FRAME_UNFUSED = "frame", "frame_unfused"  # journal kinds of a step with and without fusion


@dataclass(frozen=True, slots=True)
class CoreSettings:
    """``gossip_period`` (s) of the stack timer; ``retry_period`` (s) between requests for missing
    frames; ``window``: frames, orders, rounds and simulated links are kept only up to this many
    steps ahead of the node; ``max_control_bytes``: larger control messages are refused unread;
    ``invalid_log_period`` (s) between two log lines about invalid input from one source;
    ``simulation``: this agent runs in a simulation and obeys the simulator's links
    (``sim/links``), which no real robot ever does; ``catch_up``: in real time, how many steps
    in a row may defer their fusion while the next frame is already waiting (0: never; module
    docstring)."""

    mode: str = "realtime"
    gossip_period: float = GOSSIP_PERIOD_S
    retry_period: float = 0.25
    window: int = WINDOW_STEPS
    max_control_bytes: int = 64 * 1024
    invalid_log_period: float = 5.0
    publish_local: bool = True
    simulation: bool = False
    # "delta": a stack carries the held slots some peer lacks, by the digests (``have``) peers
    # send; "ask" (the default): delta, and this robot asks one relay to push it the versions of
    # each owner it does not hear, each with the relay's next gossip tick; "full": every held
    # slot, every time (docs/wire.md, "Delta gossip" and "Asks").
    stack_gossip: str = "ask"
    catch_up: int = CATCH_UP_STEPS
    # A simulated real time agent subscribes to the stacks of the peers in range only, from the
    # links the simulator sends a step ahead (``sim/listen``; docs/agents.md): the stacks of the
    # robots out of range are then not even sent to it.
    listen_in_range: bool = True

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode {self.mode!r} (known: {', '.join(MODES)})")
        if self.stack_gossip not in STACK_GOSSIP:
            known = ", ".join(STACK_GOSSIP)
            raise ValueError(f"stack gossip {self.stack_gossip!r} (known: {known})")
        if not (self.gossip_period > 0 and self.retry_period > 0):
            raise ValueError("gossip and retry periods must be positive")
        if self.window < 1 or self.max_control_bytes < 64:
            raise ValueError("window must be ≥ 1 and max_control_bytes ≥ 64")
        if self.catch_up < 0:
            raise ValueError("catch_up must be ≥ 0")


# -- actions ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Publish:
    key: str
    payload: bytes


@dataclass(frozen=True, slots=True)
class Append:
    """A journal record; on disk once the :class:`Commit` that follows it returned."""

    kind: str
    body: bytes


@dataclass(frozen=True, slots=True)
class Commit:
    """Commit the appended records (fsync) before any action after it is carried out."""


@dataclass(frozen=True, slots=True)
class Quarantine:
    """Set an input aside (``index``: its position in the journal, for a replayed record)."""

    kind: str
    body: bytes
    reason: str
    index: int | None = None


@dataclass(frozen=True, slots=True)
class CutJournal:
    """Cut the journal before its record ``index`` (the records from there on are set aside)."""

    index: int


@dataclass(frozen=True, slots=True)
class Halt:
    """The agent is told to stop."""

    reason: str


@dataclass(frozen=True, slots=True)
class Listen:
    """Subscribe to the stacks of ``peers`` only (None: of every robot). A simulated agent in
    real time hears only the robots its simulated radio reaches at the coming step; their
    stacks are the only ones worth receiving (the shell's ``StackSubscriptions``)."""

    peers: frozenset[str] | None


@dataclass(frozen=True, slots=True)
class Hear:
    """Wake the agent for stacks published on ``keys`` only (None: for every stack); the others
    wait in the inbox, unread, until something else wakes it (the core still judges each one,
    so nothing changes but when it is read). A simulated agent in real time does not read the
    stacks of robots its simulated radio does not reach: they need not wake the loop and the
    worker one by one (two thirds of the stacks of a 20-robot world)."""

    keys: frozenset[str] | None


Action = Publish | Append | Commit | Quarantine | CutJournal | Halt | Listen | Hear
Version = tuple[str, tuple[int, int]]  # a slot version: owner, (epoch, stamp)


@dataclass(slots=True)
class CoreCounters:
    """What the core adds to the node's counters."""

    ignored_out_of_range: int = 0
    invalid_frames: int = 0
    invalid_control: int = 0
    invalid_links: int = 0
    frames_processed: int = 0
    fusions_deferred: int = 0
    listen_changes: int = 0
    frames_duplicate: int = 0
    frames_ahead: int = 0
    orders_ahead: int = 0
    rounds_dropped: int = 0
    steps_failed: int = 0
    frames_quarantined: int = 0
    frames_degraded: int = 0
    steps_stuck: int = 0
    slots_refused: int = 0
    slots_implausible: int = 0
    restores: int = 0
    estimates_sent: int = 0
    estimates_skipped: int = 0
    need_requests: int = 0
    round_requests: int = 0
    rounds_resent: int = 0
    status_requests: int = 0
    replayed_frames: int = 0
    replayed_stacks: int = 0
    records_quarantined: int = 0
    relays_asked: int = 0  # (owner, relay) asks made: an owner this robot does not hear
    asks_answered: int = 0  # slots sent (with the next tick) only because a peer asked for them
    last_invalid: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class _Outgoing:
    """What the timer may send without touching the node: published whole by the worker."""

    stack: bytes | None = None
    previous: bytes | None = None
    need_from: int | None = None
    # Delta gossip in real time: the digest alone, sent on a tick when ``stack`` holds nothing
    # new (``fresh`` False: already published).
    digest: bytes | None = None
    fresh: bool = True
    k: int = 0  # the node's step when these were made (lock-step: the round of ``stack``)
    # Lock-step: the round whose stacks the next step needs, and the senders of the order whose
    # stack of it has not come (asked for by the timer, NeedRound).
    need_round: tuple[int, tuple[str, ...]] | None = None
    # Real time: from when a digest of this robot would let a peer push a version it lacks
    # (a gossip period after a peer's digest first showed that version; inf: nothing lacked).
    pull_at: float = math.inf
    # Real time: when the worker last published a stack that carried ``digest`` (a stack's
    # ``have`` is its digest): a tick need not send the same digest again until it is due.
    digest_sent_at: float = -math.inf


class AgentCore:
    """One robot's agent logic. ``make_node()`` builds a fresh node (at step 0) exactly as the
    first one was built; ``committed()`` returns the records committed so far (the journal), from
    which a failed step is rolled back."""

    def __init__(
        self,
        make_node: Callable[[], RobotNode],
        keys: Keys,
        settings: CoreSettings | None = None,
        committed: Callable[[], Sequence[Record]] | None = None,
        wall_clock: Callable[[], float] | None = None,
    ) -> None:
        self.make_node = make_node
        # Seconds since the Unix epoch, for the version bound (:meth:`_plausible`); None: no bound.
        self.wall_clock = wall_clock
        self.node = make_node()
        self.robot = self.node.robot
        self.keys = keys
        self.settings = settings or CoreSettings()
        self.committed = committed
        self.extra_counters: Callable[[], dict[str, int]] | None = None
        self.counters = CoreCounters()
        self.stop_reason = ""
        self._frames: dict[int, tuple[SensorFrame, bytes]] = {}
        self._orders: dict[int, StepOrder] = {}
        self._rounds: dict[tuple[str, int], tuple[StackMessage, bytes]] = {}
        self._links: dict[int, dict[str, tuple[str, ...]]] = {}
        # The links the simulator sends a step ahead (``sim/listen``): for subscriptions only.
        self._ahead: dict[int, dict[str, tuple[str, ...]]] = {}
        self._refused: collections.OrderedDict[Version, None] = collections.OrderedDict()
        self._bad_frames: collections.OrderedDict[int, None] = collections.OrderedDict()
        self._uncommitted: list[Append] = []
        # The records committed while handling the current batch of messages: their actions are
        # carried out only after the batch, so ``committed()`` does not hold them yet.
        self._batch_records: list[Record] = []
        self._merged_since_commit: list[Version] = []
        self._deferred_in_row = 0  # steps since the last one that fused (catching up)
        self._listening: frozenset[str] | None = None  # the peers of the last Listen
        self._hearing: frozenset[str] | None = None  # the keys of the last Hear
        self._last_estimate: bytes | None = None
        self._last_need = -math.inf
        self._step_us = (0, 0)
        self._out = _Outgoing()
        self._now = 0.0
        # Delta gossip: every peer's latest digest, when it came and the owners it asked this
        # robot for; when each held version came and when each was last sent (owner → (version,
        # time)).
        self._digests: dict[str, tuple[dict[str, tuple[int, int]], float, frozenset[str]]] = {}
        self._got: dict[str, float] = {}
        self._sent: dict[str, tuple[tuple[int, int], float]] = {}
        self._out_include: set[str] = set()  # the owners of the slots in ``_out.stack``
        self._out_urgent = False  # whether ``_out.stack`` goes at once (not only asked slots)
        self._tick_last: bytes | None = None  # the timer thread's own: the last stack it sent
        # The timer thread's own: the digest last sent (by a tick, alone or with slots, or with a
        # stack of the worker: ``_Outgoing.digest_sent_at``), and when.
        self._digest_sent: tuple[bytes | None, float] = (None, -math.inf)
        # Versions peers' digests hold that this robot lacks: owner → (version, first seen).
        self._wanted: dict[str, tuple[tuple[int, int], float]] = {}
        # Standing asks (``stack_gossip = "ask"``): owner → (the relay asked to push its new
        # versions, when); since when a peer's digest has shown a version of an owner newer
        # than the one held, without a break; whether the current batch of messages changed
        # the asks, and when a digest last went at once for that (at most once a period).
        self._asks: dict[str, tuple[str, float]] = {}
        self._behind: dict[str, float] = {}
        self._asked_now = False
        self._asked_sent_at = -math.inf
        self.digests_skipped = 0  # ticks that sent nothing: an unchanged digest (timer thread)
        self.tick_bytes = 0  # bytes of stacks and digests the timer sent (timer thread only)
        # Lock-step re-sends (timer thread only): the round last re-sent, the periods to wait
        # before its next re-send, and the periods waited so far.
        self._resend_round = -1
        self._resend_wait = 1
        self._resend_idle = 0
        # Re-sent acknowledgements: (round, when last re-sent, the wait before the next one).
        self._ack_resend: tuple[int, float, float] = (-1, -math.inf, 0.0)
        # Lock-step requests for round stacks: (the need, when first seen, when last asked)
        # (timer thread only), and when each of this agent's rounds was last sent on request.
        self._round_need: tuple[tuple[int, tuple[str, ...]] | None, float, float] = (
            None,
            -math.inf,
            -math.inf,
        )
        self._round_resent: dict[int, float] = {}

    # -- lifecycle ---------------------------------------------------------------------------

    def replay(self, records: Sequence[Record]) -> list[Action]:
        """Rebuild the belief from committed records (before :meth:`start`); never aborts.

        A stack record that does not decode or merge is quarantined with its index and skipped
        (its owner gossips again). A frame record that fails is quarantined and ends the replay:
        every later record depends on it, so the journal is cut there (:class:`CutJournal`, the
        cut records are set aside by the journal) and the agent asks for its frames again.
        """
        actions: list[Action] = []
        for index, record in enumerate(records):
            try:
                self._apply(record)
            except Exception as exc:
                self.counters.records_quarantined += 1
                reason = f"replay of record {index} ({record.kind}): {type(exc).__name__}: {exc}"
                log.error("%s: %s", self.robot, reason)
                actions.append(Quarantine(record.kind, record.body, reason, index))
                self._restore(records[:index])
                if record.kind not in (FRAME, FRAME_UNFUSED):
                    continue
                actions.append(CutJournal(index))
                break
        if records:
            log.info(
                "%s: replayed %d frames and %d stacks (now at step %d)",
                self.robot,
                self.counters.replayed_frames,
                self.counters.replayed_stacks,
                self.node.k,
            )
        self._refresh()
        return actions

    def _apply(self, record: Record) -> None:
        if record.kind == "stack":
            message = self.node.decode_stack(record.body)
            if message is None:
                raise ValueError(self.node.counters.last_error)
            self.node.merge(message)
            self.counters.replayed_stacks += 1
        elif record.kind in (FRAME, FRAME_UNFUSED):
            frame = decode_frame(record.body)
            if frame.robot != self.robot or frame.k != self.node.k + 1:
                raise ValueError(f"frame of {frame.robot} at step {frame.k} after {self.node.k}")
            self.node.on_frame(frame, fuse=record.kind == FRAME)
            self.counters.replayed_frames += 1

    def _restore(self, records: Sequence[Record]) -> None:
        """A fresh node, replayed from ``records``, which were replayed before: a stack record
        that failed then (quarantined) is skipped again."""
        self.node = self.make_node()
        replayed = (self.counters.replayed_frames, self.counters.replayed_stacks)
        for record in records:
            try:
                self._apply(record)
            except Exception:
                if record.kind in (FRAME, FRAME_UNFUSED):
                    raise
                log.debug("%s: skipped a quarantined stack record", self.robot)
        self.counters.replayed_frames, self.counters.replayed_stacks = replayed

    def start(self, now: float) -> list[Action]:
        """After start or restart: tell the fleet where this agent is."""
        self._now = now
        actions = self._publish_stack()
        if self.node.k > 0:
            actions += self._publish_estimate()
        return [*self._listen(initial=True), *actions, *self._ask_for_frames(now, force=True)]

    # -- events ------------------------------------------------------------------------------

    def on_message(self, key: str, payload: bytes, now: float) -> list[Action]:
        """One message that arrived on ``key``; then every step that became possible."""
        return self.on_messages([(key, payload)], now)

    def on_messages(self, messages: Sequence[tuple[str, bytes]], now: float) -> list[Action]:
        """Messages (key, payload) that arrived together, in order, each followed by every step
        it made possible; what the timer sends is refreshed once, after all of them."""
        keys = self.keys
        self._now = now
        self._batch_records = []
        actions: list[Action] = []
        # In real time, every message of the batch first: a step then sees the frames that are
        # already waiting behind it (and catches up) and fuses every stack that came with them.
        at_once = self.settings.mode == "realtime"
        for key, payload in messages:
            if key.startswith(keys.ctl("")):
                actions += self._on_control(key, payload)
            elif key == keys.frames(self.robot):
                actions += self._on_frame(payload)
            elif key.startswith(f"{keys.prefix}/stack/"):
                actions += self._on_stack(key, payload)
            elif key == keys.sim_links():
                self._on_links(payload, self._links)
            elif key == keys.sim_listen():
                self._on_links(payload, self._ahead)
            if not at_once:
                actions += self._step_all()
        if at_once:
            actions += self._step_all()
        actions += self._listen() + self._hear()
        self._refresh()
        out = self._out
        if out.fresh and out.digest is not None and out.stack is not None and self._out_urgent:
            # Delta gossip in real time: what a peer turned out to lack goes now, not at the
            # next tick (a tick then carries the digest alone) — but a slot only a peer's ask
            # sends waits for the tick (docs/wire.md, "Asks"); a changed ask goes now.
            self._out = dataclasses.replace(out, fresh=False, digest_sent_at=now)
            self.node.mark_sent(len(out.stack))
            actions.append(Publish(self.keys.stack(self.robot), out.stack))
        elif (
            self._asked_now
            and out.digest is not None
            and now - self._asked_sent_at >= self.settings.gossip_period
        ):  # else the changed digest goes at the next tick
            self._asked_sent_at = now
            self._out = dataclasses.replace(out, digest_sent_at=now)
            self.node.mark_sent(len(out.digest))
            actions.append(Publish(self.keys.stack(self.robot), out.digest))
        self._asked_now = False
        return actions

    def on_timer(self, now: float, announce: bool = False) -> list[Action]:
        """The gossip tick: re-send the stack (and, in lock-step, the previous round's, which a
        slower peer may still need) and ask for missing frames. Safe during a running step.
        ``announce``: send the digest even when it is not due (new peers were just subscribed
        to, and may have missed it)."""
        out = self._out
        self._now = now
        actions: list[Action] = []
        if self.settings.mode == "lockstep" and self._lockstep_backoff(out):
            pass  # unchanged since the last re-send, and not due yet
        elif self.settings.mode == "lockstep":
            if out.previous is not None:
                actions.append(Publish(self.keys.stack(self.robot), out.previous))
            if out.stack is not None:
                self.tick_bytes += len(out.stack) + len(out.previous or b"")
                actions.append(Publish(self.keys.stack(self.robot), out.stack))
        elif out.stack is not None:
            data: bytes | None = out.stack
            if out.digest is not None and (not out.fresh or out.stack is self._tick_last):
                data = out.digest  # nothing new since it was sent: the digest alone
                if not announce and not self._digest_due(out, now):
                    data = None
                    self.digests_skipped += 1
            self._tick_last = out.stack
            if data is not None:
                if out.digest is not None:
                    self._digest_sent = (out.digest, now)
                self.tick_bytes += len(data)
                actions.append(Publish(self.keys.stack(self.robot), data))
        if out.need_from is not None:
            actions += self._need(out.need_from, now)
        if out.need_round is not None or self._round_need[0] is not None:
            actions += self._ask_for_round(out.need_round, now)
        return actions

    def _digest_due(self, out: _Outgoing, now: float) -> bool:
        """Whether a tick with nothing new to send sends the digest alone. A digest went last
        with a stack or on a tick; it goes again when it changed since (holdings, step or
        position: peers learn what they may pull from this robot), when that was
        ``DIGEST_REFRESH`` gossip periods ago (peers keep counting this robot), or to pull: when
        a peer could now push a version this robot lacks (:meth:`_pull_at`) and no digest went
        since."""
        last, at = self._digest_sent
        if out.digest_sent_at > at:  # the worker sent this digest with a stack since
            last, at = out.digest, out.digest_sent_at
            self._digest_sent = (last, at)
        return (
            out.digest != last
            or now - at >= DIGEST_REFRESH * self.settings.gossip_period
            or at < out.pull_at <= now
        )

    def _ask_for_round(self, need: tuple[int, tuple[str, ...]] | None, now: float) -> list[Action]:
        """Lock-step: ask the senders whose stack of the coming step's round has not come for
        it, once it has been missing a gossip period and then at most once a period (a lost
        stack is otherwise re-sent only on its sender's backed-off ticks, up to 2 (N − 1)
        periods later). Timer thread only."""
        period = self.settings.gossip_period
        seen, since, asked = self._round_need
        if need != seen:
            self._round_need = (need, now, -math.inf)
            return []
        if need is None or now - since < period or now - asked < period:
            return []
        self._round_need = (need, since, now)
        self.counters.round_requests += 1
        payload = encode_control(NeedRound(self.robot, need[0], need[1]))
        return [Publish(self.keys.ctl("need", self.robot), payload)]

    def _lockstep_backoff(self, out: _Outgoing) -> bool:
        """Whether this tick skips the lock-step re-send: a round's stacks go out when the round
        ends, and the ticks only repair a loss, so a round's stacks are re-sent after 1, 2, 4
        ... up to :meth:`_lockstep_resend_max` periods (exponential back-off) instead of every
        period — with N agents every period would be N² stacks, which swamped 50 agents on 2
        cores. A new round starts over at one period; a round stack whose bytes change within
        the round (what peers lack shrinks as their digests come) keeps its back-off: starting
        over at every change re-sent stacks several times a period in a 50-agent fleet. Timer
        thread only."""
        if out.k != self._resend_round:
            self._resend_round, self._resend_wait, self._resend_idle = out.k, 1, 0
            return False
        self._resend_idle += 1
        if self._resend_idle < self._resend_wait:
            return True
        self._resend_wait = min(2 * self._resend_wait, self._lockstep_resend_max())
        self._resend_idle = 0
        return False

    def _lockstep_resend_max(self) -> int:
        """The longest back-off of the lock-step re-sends, in gossip periods: LOCKSTEP_RESEND_MAX,
        or 2 (N − 1) in a roster of N robots if longer. Every agent re-sends to N − 1 peers, so
        with a fixed cap the re-sends a peer receives grow with N (50 agents on 2 cores: about 6
        a second each, 23 MB per agent in three rounds, a round of minutes and inbox overflows);
        scaled, they stay at about one every two periods. Loopback or a LAN rarely loses a
        stack: the ticks only repair losses."""
        roster = self.node.roster
        peers = 0 if roster is None else len(roster) - 1
        return max(LOCKSTEP_RESEND_MAX, 2 * peers)

    def _ack_due(self, order: StepOrder) -> bool:
        """Whether a repeated order of the current round is answered with the estimate again.
        An order that names the robots it waits for is answered by those only, at most once a
        gossip period (the conductor backs its re-orders off). One that names nobody (an
        operator's, an older conductor's) goes to the whole fleet: answered at once the first
        time, then after 1, 2, 4 ... gossip periods, up to :meth:`_lockstep_resend_max` (every
        agent would answer it, and an estimate can be megabytes)."""
        if order.waiting is not None:
            return self.robot in order.waiting and self._answer_due(order.k)
        period = self.settings.gossip_period
        last_k, last_t, wait = self._ack_resend
        if order.k != last_k:
            self._ack_resend = (order.k, self._now, period)
            return True
        if self._now - last_t < wait:
            return False
        self._ack_resend = (
            order.k,
            self._now,
            min(2 * wait, self._lockstep_resend_max() * period),
        )
        return True

    def _answer_due(self, k: int) -> bool:
        """A request meant for this robot (an order naming it, a frame of its current step sent
        again): answered with the estimate at most once a gossip period."""
        period = self.settings.gossip_period
        last_k, last_t, _ = self._ack_resend
        if k == last_k and self._now - last_t < period:
            return False
        self._ack_resend = (k, self._now, period)
        return True

    def next_timer(self, now: float) -> float:
        return now + self.settings.gossip_period

    # -- input -------------------------------------------------------------------------------

    def _on_control(self, key: str, payload: bytes) -> list[Action]:
        try:
            order = decode_control(payload, max_bytes=self.settings.max_control_bytes)
        except RemoteProtocolError as exc:
            self.counters.invalid_control += 1
            self._log_invalid("ctl", exc)
            return []
        if isinstance(order, StepOrder):
            k = self.node.k
            if k < order.k <= k + self.settings.window:
                self._orders[order.k] = order
            elif order.k > k:
                self.counters.orders_ahead += 1
            elif order.k == k and k > 0 and self._ack_due(order):
                return self._publish_estimate(self._last_estimate)  # the conductor missed our ack
        elif isinstance(order, Status):
            self.counters.status_requests += 1
            return self._publish_estimate()
        elif isinstance(order, Stop):
            self.stop_reason = self.stop_reason or order.reason or "stopped by the conductor"
            return [Halt(self.stop_reason)]
        elif isinstance(order, NeedRound):
            return self._answer_round(order, self.keys.robot_of(key))
        elif isinstance(order, NeedFrames):
            pass  # for whoever publishes frames
        return []

    def _answer_round(self, need: NeedRound, asker: str | None) -> list[Action]:
        """A lock-step peer lacks this agent's stack of round ``need.k``: send it again if this
        agent has made it (its current round's or the previous one's), at most once a gossip
        period per round whoever asks. A request on another robot's key is ignored (each robot
        asks on its own ``ctl/need`` key; a secure fleet enforces it)."""
        if (
            self.settings.mode != "lockstep"
            or asker != need.robot
            or need.robot == self.robot
            or self.robot not in need.senders
        ):
            return []
        out = self._out
        data = {out.k: out.stack, out.k - 1: out.previous}.get(need.k)
        last = self._round_resent.get(need.k, -math.inf)
        if data is None or self._now - last < self.settings.gossip_period:
            return []
        self._round_resent = {k: t for k, t in self._round_resent.items() if k >= out.k - 1}
        self._round_resent[need.k] = self._now
        self.counters.rounds_resent += 1
        return [Publish(self.keys.stack(self.robot), data)]

    def _on_links(self, payload: bytes, into: dict[int, dict[str, tuple[str, ...]]]) -> None:
        """The simulator's verdict of who hears whom at step k (simulations only), kept
        ``into`` the links obeyed (``sim/links``) or those sent a step ahead (``sim/listen``)."""
        if not self.settings.simulation:
            return
        try:
            order = decode_control(payload, max_bytes=self.settings.max_control_bytes)
            if not isinstance(order, StepOrder):
                raise ValueError(f"expected links, got {type(order).__name__}")
        except (RemoteProtocolError, ValueError) as exc:
            self.counters.invalid_links += 1
            self._log_invalid("sim", exc)
            return
        k = self.node.k
        if k <= order.k <= k + self.settings.window:
            into[order.k] = order.links

    def _on_frame(self, data: bytes) -> list[Action]:
        try:
            frame = decode_frame(data)
            if frame.robot != self.robot:
                raise ValueError(f"frame of robot {frame.robot}")
        except (RemoteProtocolError, ValueError) as exc:
            self.counters.invalid_frames += 1
            self._log_invalid("frames", exc)
            return []
        k = self.node.k
        if frame.k <= k:
            self.counters.frames_duplicate += 1
            if frame.k == k and k > 0 and self._answer_due(k):
                return self._publish_estimate(self._last_estimate)
            return []
        if frame.k > k + self.settings.window:
            self.counters.frames_ahead += 1
            return []
        if zlib.crc32(data) in self._bad_frames:
            self.counters.frames_duplicate += 1  # these very bytes failed a step before
            return []
        self._frames.setdefault(frame.k, (frame, data))
        return []

    def _on_stack(self, key: str, payload: bytes) -> list[Action]:
        sender_key = self.keys.robot_of(key)
        if sender_key == self.robot:
            return []  # our own publication, echoed by the session
        if (
            self.settings.simulation
            and self.settings.mode == "realtime"
            and sender_key is not None
            and not self._heard(sender_key)
        ):
            # A simulated radio: a robot out of range is not heard at all, so its stack is not
            # read either (decoding them was most of what a 20-agent simulation spent on stacks).
            self.node.counters.stacks_received += 1
            self.node.counters.bytes_received += len(payload)
            if self._links:  # before the simulator's first verdict nobody is out of range
                self.counters.ignored_out_of_range += 1
            return []
        message = self.node.decode_stack(payload)
        if message is None:
            self._log_invalid(sender_key or key, ValueError(self.node.counters.last_error))
            return []
        if message.sender == self.robot:
            return []
        if sender_key is not None and message.sender != sender_key:
            # Each robot publishes only on its own key (access control enforces it on a secure
            # fleet): a stack whose sender is another robot is forged or misrouted.
            exc = SenderMismatch(f"sent by {message.sender!r} on the key of {sender_key}", "sender")
            self.node.reject(exc)
            self._log_invalid(sender_key, exc)
            return []
        message = self._plausible(self._without_refused(message))
        heard = self.settings.mode == "lockstep" or not self.settings.simulation
        # What the sender holds: what it lacks is sent to it (a simulated agent takes the
        # digests of the robots it hears only, as a radio would).
        noted = message.have if heard or self._heard(message.sender) else None
        if noted is not None:
            asked = (message.ask or {}).items()
            self._note_digest(
                message.sender, noted, frozenset(o for o, r in asked if r == self.robot)
            )
        if self.settings.mode == "lockstep":
            k = self.node.k
            if not k <= message.step <= k + self.settings.window:
                return []
            if len(self._rounds) >= self._max_rounds():
                self.counters.rounds_dropped += 1
                return []
            self._rounds.setdefault((message.sender, message.step), (message, payload))
            return []
        if self.settings.simulation and not self._heard(message.sender):
            if self._links:  # before the simulator's first verdict nobody is out of range
                self.counters.ignored_out_of_range += 1
            return []
        actions = self._merge(message, payload)
        if noted is not None:
            # Versions the sender holds that this robot still lacks after taking what came
            # with them: the ticks pull them (send the digest) when the sender could push.
            self._check_wanted(message.sender, noted)
        return actions

    def _listen(self, initial: bool = False) -> list[Action]:
        """A :class:`Listen` when whom to hear changed (``initial``: always): with
        ``listen_in_range`` in a simulated real time run, the robots heard at the coming step or
        at any later step whose links are here, those sent a step ahead included (so that a
        subscription is in place before its links are due: one declared as they change misses
        what the peer publishes meanwhile); nobody before the first links. Else every robot."""
        s = self.settings
        if not (s.listen_in_range and s.simulation and s.mode == "realtime"):
            return [Listen(None)] if initial else []
        due = [k for k in self._links if k <= self.node.k + 1]
        first = max(due) if due else self.node.k + 1
        robots: set[str] = set()
        for later, links in [*self._links.items(), *self._ahead.items()]:
            if later >= first:
                robots.update(links.get(self.robot, ()))
        if self.node.roster is not None:  # a robot not in the roster is never subscribed to
            robots &= self.node.roster
        peers = frozenset(robots - {self.robot})
        if not initial and peers == self._listening:
            return []
        self._listening = peers
        self.counters.listen_changes += 1
        return [Listen(peers)]

    def _hear(self) -> list[Action]:
        """A :class:`Hear` when the stacks worth waking for changed: in a simulated real time
        run, those of the robots heard under the links due at the coming step or under any later
        links already here; before the first links, every stack."""
        s = self.settings
        if not (s.simulation and s.mode == "realtime") or not self._links:
            return []
        due = [k for k in self._links if k <= self.node.k + 1]
        first = max(due) if due else min(self._links)
        robots: set[str] = set()
        for k, links in self._links.items():
            if k >= first:
                robots.update(links.get(self.robot, ()))
        keys = frozenset(self.keys.stack(r) for r in robots - {self.robot})
        if keys == self._hearing:
            return []
        self._hearing = keys
        return [Hear(keys)]

    def _heard(self, sender: str) -> bool:
        """In a simulation: whether the latest links published for the coming step let
        ``sender`` through to this robot (no links yet: nobody is heard)."""
        due = [k for k in self._links if k <= self.node.k + 1]
        if not due:
            return False
        return sender in self._links[max(due)].get(self.robot, ())

    def _max_rounds(self) -> int:
        roster = self.node.roster
        peers = len(roster) if roster is not None else self.node.limits.max_slots
        return max(1, peers) * (self.settings.window + 1)

    def _without_refused(self, message: StackMessage) -> StackMessage:
        if not self._refused:
            return message
        kept = [s for s in message.stack if (s.owner, s.version) not in self._refused]
        if len(kept) == len(message.stack):
            return message
        self.counters.slots_refused += len(message.stack) - len(kept)
        return dataclasses.replace(message, stack=Stack(tuple(kept)))  # the digest stays

    def _note_digest(
        self, sender: str, have: dict[str, tuple[int, int]], asked: frozenset[str]
    ) -> None:
        """Keep ``sender``'s digest and the owners it asked this robot for (until its next
        digest): only a roster robot's, and at most ``max_slots`` peers' (the longest unheard
        forgotten first), so that made-up senders cannot grow it."""
        roster = self.node.roster
        if roster is not None and sender not in roster:
            return
        self._digests.pop(sender, None)
        self._digests[sender] = (have, self._now, asked)
        while len(self._digests) > self.node.limits.max_slots:
            del self._digests[next(iter(self._digests))]

    def _check_wanted(self, sender: str, have: dict[str, tuple[int, int]]) -> None:
        """Note the versions of a peer's digest this robot lacks, each with when it was first
        seen (a newer version starts over: the peer got it just now); at most ``max_slots``,
        and with a roster only roster robots' digests and slots (no other is ever taken).

        With ``stack_gossip = "ask"``, this robot asks a relay to push the versions of an
        owner it does not hear (they will not come from the owner): :meth:`_ask`."""
        roster = self.node.roster
        if roster is not None and sender not in roster:
            return
        held = self.node.stack
        asks = self.settings.stack_gossip == "ask"
        for owner, version in have.items():
            if roster is not None and owner not in roster:
                continue
            if version > (held.version_of(owner) or (-1, -1)):
                known = self._wanted.get(owner)
                if known is None or known[0] < version:
                    self._wanted.pop(owner, None)
                    self._wanted[owner] = (version, self._now)
                if asks and owner != self.robot and not self._hears(owner):
                    self._ask(owner, sender)
        while len(self._wanted) > self.node.limits.max_slots:
            del self._wanted[next(iter(self._wanted))]

    def _hears(self, robot: str) -> bool:
        """Whether ``robot``'s own digest came within ``DIGEST_LIFE`` gossip periods."""
        noted = self._digests.get(robot)
        horizon = self._now - DIGEST_LIFE * self.settings.gossip_period
        return noted is not None and noted[1] >= horizon

    def _ask(self, owner: str, relay: str) -> None:
        """Behind on ``owner``, whom this robot does not hear, by ``relay``'s digest: ask
        ``relay`` to push ``owner``'s versions — unless a relay asked before is still heard and
        either was asked less than a gossip period ago or has not left this robot behind for a
        period (then the peers that could push after their chance would have). One relay per
        owner, so that a robot's neighbours do not all push the same slot (docs/wire.md,
        "Asks"); at most ``max_slots`` owners."""
        now, period = self._now, self.settings.gossip_period
        behind = self._behind.setdefault(owner, now)
        known = self._asks.get(owner)
        if known is not None:
            current, since = known
            if current == relay:
                return
            if self._hears(current) and (now - behind <= period or now - since <= period):
                return
        self._asks.pop(owner, None)
        self._asks[owner] = (relay, now)
        self._asked_now = True
        self.counters.relays_asked += 1
        while len(self._asks) > self.node.limits.max_slots:
            del self._asks[next(iter(self._asks))]

    def _current_asks(self) -> dict[str, str]:
        """The asks in force (owner → relay): those whose owner is still not heard and whose
        relay still is. An owner stops being behind once this robot holds the newest version a
        digest showed it, or that version is forgotten (``_wanted``, at most ``max_slots``)."""
        held = self.node.stack
        for owner in list(self._behind):
            newest = self._wanted.get(owner)
            if newest is None or newest[0] <= (held.version_of(owner) or (-1, -1)):
                del self._behind[owner]
        for owner in [
            o for o, (r, _) in self._asks.items() if self._hears(o) or not self._hears(r)
        ]:
            del self._asks[owner]
        return {o: r for o, (r, _) in self._asks.items()}

    def _pull_at(self) -> float:
        """When the ticks pull (send the digest even if unchanged): a gossip period after a
        peer's digest first showed a version this robot still lacks. A peer pushes a slot only
        to a digest that came a period after the slot came to it (docs/wire.md): an earlier
        pull would change nothing."""
        held = self.node.stack
        for owner in [
            o for o, (v, _) in self._wanted.items() if v <= (held.version_of(o) or (-1, -1))
        ]:
            del self._wanted[owner]
        first = min((seen for _, seen in self._wanted.values()), default=math.inf)
        return first + self.settings.gossip_period

    def _plausible(self, message: StackMessage) -> StackMessage:
        """Without the slots whose version is ahead of what their owner can have made by now:
        an epoch after the receiver's clock, or a stamp beyond ``MAX_STEP_RATE`` steps per
        second since the epoch began (both with ``CLOCK_SKEW_S``). Such a version would block
        every genuine one of its owner until the owner moved past it."""
        if self.wall_clock is None:
            return message
        now_ms = 1000.0 * (self.wall_clock() + CLOCK_SKEW_S)
        kept = [
            s
            for s in message.stack
            if s.epoch <= now_ms
            and s.stamp <= MAX_STEP_RATE * (now_ms - s.epoch) / 1000 + STAMP_SLACK
        ]
        if len(kept) == len(message.stack):
            return message
        self.counters.slots_implausible += len(message.stack) - len(kept)
        self._log_invalid(message.sender, ValueError("a slot version ahead of its owner's clock"))
        return dataclasses.replace(message, stack=Stack(tuple(kept)))  # the digest stays

    def _merge(self, message: StackMessage, payload: bytes) -> list[Action]:
        before = self.node.stack.versions()
        if self.node.merge(message):
            after = self.node.stack.versions()
            changed = [(o, s) for o, s in after.items() if before.get(o) != s]
            self._merged_since_commit += changed
            for owner, _ in changed:
                self._got[owner] = self._now
            self._uncommitted.append(Append("stack", payload))
        return []

    # -- stepping ----------------------------------------------------------------------------

    def _step_all(self) -> list[Action]:
        actions: list[Action] = []
        while True:
            step = self._try_step()
            if step is None:
                break
            actions += step
        return actions

    def _try_step(self) -> list[Action] | None:
        k = self.node.k + 1
        if k not in self._frames:
            return None
        if self.settings.mode == "lockstep":
            order = self._orders.get(k)
            if order is None:
                return None
            senders = order.links.get(self.robot, ())
            if any((s, k - 1) not in self._rounds for s in senders):
                return None
            for s in sorted(senders):
                message, data = self._rounds[(s, k - 1)]
                self._merge(self._without_refused(message), data)
        frame, data = self._frames.pop(k)
        # The frame is here: the timer must not go on asking for it while the step runs (every
        # request made the conductor send it again, and every copy was answered with an estimate).
        self._out = dataclasses.replace(self._out, need_from=None, need_round=None)
        behind = self.settings.mode == "realtime" and k + 1 in self._frames
        catching_up = behind and self.settings.catch_up > 0
        fuse = not behind or self._deferred_in_row >= self.settings.catch_up
        actions = self._step(frame, data, fuse, report=not catching_up)
        self._forget_before(self.node.k)
        return actions

    def _step(
        self, frame: SensorFrame, data: bytes, fuse: bool = True, report: bool = True
    ) -> list[Action]:
        """Step with ``frame`` and commit; on failure roll back and go on (module docstring).
        ``fuse=False``: a step that defers its fusion; ``report=False``: a step whose estimate is
        not published, the next step following at once (both: catching up)."""
        try:
            self._run(frame, fuse)
        except Exception as exc:
            return self._recover(frame, data, exc, fuse)
        return self._committed_step(data, fuse, report)

    def _run(self, frame: SensorFrame, fuse: bool) -> None:
        # on_frame alone does the same; split to time the fusion + D and the L step separately.
        node = self.node
        t0 = time.perf_counter()
        with np.errstate(over="raise", invalid="raise", divide="ignore"):
            if fuse:
                node.integrate_pending()
            t1 = time.perf_counter()
            node.track.advance(frame)
            t2 = time.perf_counter()
            node.on_frame(frame, fuse)
        t3 = time.perf_counter()
        self._step_us = (round(1e6 * (t2 - t1)), round(1e6 * ((t1 - t0) + (t3 - t2))))

    def _committed_step(self, frame: bytes, fused: bool, report: bool = True) -> list[Action]:
        """Commit a step taken with the frame bytes ``frame`` and publish. A step that deferred
        its fusion commits its frame alone: the stacks merged so far go into the journal, and
        stay suspects, with the step that fuses them. ``report=False``: no estimate (it would be
        superseded by the step that follows at once; one is made if asked for)."""
        self.counters.frames_processed += 1
        if not fused:
            self._deferred_in_row += 1
            self.counters.fusions_deferred += 1
            self._batch_records.append(Record(FRAME_UNFUSED, frame))
            return [Append(FRAME_UNFUSED, frame), Commit(), *self._report(report)]
        records = [*self._uncommitted, Append(FRAME, frame)]
        self._batch_records += [Record(a.kind, a.body) for a in records]
        actions: list[Action] = [*records, Commit()]
        self._uncommitted = []
        self._merged_since_commit = []
        self._deferred_in_row = 0
        return actions + self._publish_stack(previous=self._out.stack) + self._report(report)

    def _recover(self, frame: SensorFrame, data: bytes, exc: Exception, fuse: bool) -> list[Action]:
        self.counters.steps_failed += 1
        self._bad_frames[zlib.crc32(data)] = None
        while len(self._bad_frames) > MAX_REFUSED:
            self._bad_frames.popitem(last=False)
        reason = f"step {frame.k}: {type(exc).__name__}: {exc}"
        log.error("%s: %s; rolling back", self.robot, reason, exc_info=exc)
        suspects = list(self._merged_since_commit)
        for version in suspects:
            self._refuse(version)
        if self.committed is None:
            # Nothing to roll back to: stop stepping rather than go on from a broken belief.
            self.stop_reason = f"step failed with no journal to roll back to ({reason})"
            return [Quarantine(FRAME, data, reason), Halt(self.stop_reason)]
        self._rollback()
        if suspects:
            try:
                self._run(frame, fuse)
                log.warning(
                    "%s: step %d succeeded without the slots %s, which are refused",
                    self.robot,
                    frame.k,
                    suspects,
                )
                return self._committed_step(data, fuse)
            except Exception as again:
                reason = f"step {frame.k}: {type(again).__name__}: {again}"
                self._rollback()
        self.counters.frames_quarantined += 1
        actions: list[Action] = [Quarantine(FRAME, data, reason)]
        odometry_only = SensorFrame(frame.robot, frame.k, frame.odometry, (), np.full(3, np.nan))
        try:
            self._run(odometry_only, fuse)
        except Exception as last:
            # The odometry itself is unusable: stay at the last good step, alive, until a
            # different frame k arrives (these bytes are never tried again).
            self._rollback()
            self.counters.steps_stuck += 1
            log.error(
                "%s: step %d fails even on its odometry alone (%s): waiting for another frame %d",
                self.robot,
                frame.k,
                last,
                frame.k,
            )
            return actions
        self.counters.frames_degraded += 1
        log.warning("%s: frame %d quarantined, stepped on its odometry only", self.robot, frame.k)
        return actions + self._committed_step(encode_frame(odometry_only), fuse)

    def _rollback(self) -> None:
        assert self.committed is not None
        self.counters.restores += 1
        self._uncommitted = []
        self._merged_since_commit = []
        # What the journal holds, and the steps of this batch committed before this one.
        self._restore([*self.committed(), *self._batch_records])

    def _refuse(self, version: Version) -> None:
        self._refused[version] = None
        self.counters.slots_refused += 1
        while len(self._refused) > MAX_REFUSED:
            self._refused.popitem(last=False)

    def _forget_before(self, k: int) -> None:
        self._orders = {j: o for j, o in self._orders.items() if j > k}
        self._rounds = {key: v for key, v in self._rounds.items() if key[1] >= k}
        self._frames = {j: f for j, f in self._frames.items() if j > k}
        latest = max((j for j in self._links if j <= k + 1), default=None)
        self._links = {j: v for j, v in self._links.items() if j > k or j == latest}
        self._ahead = {j: v for j, v in self._ahead.items() if j > k}

    def _frames_missing(self) -> int | None:
        nxt = self.node.k + 1
        if self.settings.mode == "lockstep":
            missing = nxt in self._orders and nxt not in self._frames
        else:
            missing = bool(self._frames) and nxt not in self._frames
        return nxt if missing else None

    def _round_missing(self) -> tuple[int, tuple[str, ...]] | None:
        """Lock-step: the round whose stacks the next step merges, and the senders its order
        names whose stack of that round has not come (None: nothing to ask for)."""
        nxt = self.node.k + 1
        order = self._orders.get(nxt)
        if self.settings.mode != "lockstep" or order is None:
            return None
        senders = order.links.get(self.robot, ())
        missing = tuple(sorted(s for s in senders if (s, nxt - 1) not in self._rounds))
        return (nxt - 1, missing) if missing else None

    def _refresh(self) -> None:
        """Publish, whole, what the timer may read."""
        # Always, even empty: a lock-step peer ordered to hear us at round 1 needs our round 0.
        data, digest, fresh = self._stack_payload()
        need = self._frames_missing()
        old = self._out
        self._out = _Outgoing(
            data,
            old.previous,
            need,
            digest,
            fresh,
            self.node.k,
            self._round_missing(),
            self._pull_at(),
            old.digest_sent_at if digest == old.digest else -math.inf,
        )

    def _stack_payload(self) -> tuple[bytes, bytes | None, bool]:
        """The stack to gossip now, its digest alone (delta gossip in real time) and whether the
        stack holds a slot not sent before (docs/wire.md, "Delta gossip").

        Lock-step: every held slot that some roster peer lacks by its latest digest (a peer not
        heard from yet lacks everything), so that each round merges exactly what a full stack
        would bring. Real time: a slot goes to a peer whose digest lacks it only once that peer
        had its chance — a digest that came a gossip period after the slot came here (from its
        owner, whom the peer may hear itself) and after this agent last sent it; the own slot's
        new version goes at once. A peer that joined (an empty digest) so gets a whole stack. A
        peer that asks this robot for an owner (it does not hear that owner) has no chance to
        wait for: the slot goes with the next tick (docs/wire.md, "Asks")."""
        node = self.node
        if self.settings.stack_gossip == "full":
            return node.encoded_stack(), None, True
        stack = node.current_stack()
        period = self.settings.gossip_period
        strict = self.settings.mode == "lockstep"
        digests = dict(self._digests)
        if not strict:  # a peer not heard for DIGEST_LIFE periods is out of reach
            horizon = self._now - DIGEST_LIFE * period
            digests = {p: d for p, d in digests.items() if d[1] >= horizon}
        if strict and node.roster is not None:
            for peer in node.roster - {self.robot} - set(digests):
                digests[peer] = ({}, -math.inf, frozenset())
        include: set[str] = set()
        urgent = False
        if not strict and self._out.fresh and self._tick_last is not self._out.stack:
            include |= self._out_include & set(stack.by_owner())  # computed, not sent yet
        for slot in stack:
            version = slot.version
            sent_version, sent_at = self._sent.get(slot.owner, ((-1, -1), -math.inf))
            for peer, (have, heard_at, asked) in digests.items():
                if peer == slot.owner or have.get(slot.owner, (-1, -1)) >= version:
                    continue
                if strict:
                    include.add(slot.owner)
                    break
                resend = sent_version != version or heard_at > sent_at + period
                chance = (
                    slot.owner == self.robot or heard_at > self._got.get(slot.owner, 0.0) + period
                )
                on_ask = not chance and slot.owner in asked  # the peer does not hear the owner
                if resend and (chance or on_ask):
                    include.add(slot.owner)
                    self.counters.asks_answered += on_ask
                    urgent |= not on_ask
                    break
        for owner in include:
            self._sent[owner] = (stack.by_owner()[owner].version, self._now)
        self._out_include = include
        self._out_urgent = urgent
        asks = None if strict else self._current_asks()
        data = node.encoded_delta(include, asks)
        digest = None if strict else node.encoded_delta((), asks)
        return data, digest, bool(include)

    # -- output ------------------------------------------------------------------------------

    def _ask_for_frames(self, now: float, force: bool = False) -> list[Action]:
        return self._need(self.node.k + 1, now, force)

    def _need(self, k: int, now: float, force: bool = False) -> list[Action]:
        if not force and now - self._last_need < self.settings.retry_period:
            return []
        self._last_need = now
        self.counters.need_requests += 1
        payload = encode_control(NeedFrames(self.robot, k))
        return [Publish(self.keys.ctl("need", self.robot), payload)]

    def _publish_stack(self, previous: bytes | None = None) -> list[Action]:
        data, digest, _ = self._stack_payload()
        self._out = _Outgoing(
            data,
            previous,
            self._out.need_from,
            digest,
            False,
            self.node.k,
            None,
            self._pull_at(),
            self._now,
        )
        self.node.mark_sent(len(data))
        return [Publish(self.keys.stack(self.robot), data)]

    def _report(self, report: bool) -> list[Action]:
        if report:
            return self._publish_estimate()
        self._last_estimate = None  # made when next asked for
        self.counters.estimates_skipped += 1
        return []

    def _publish_estimate(self, data: bytes | None = None) -> list[Action]:
        """Publish ``data``, or the estimate of the current step (made and kept for answering
        again)."""
        if data is None:
            beliefs = {"distributed": self.node.distributed.snapshot(self.robot)}
            if self.settings.publish_local:
                beliefs["local"] = self.node.local.snapshot(self.robot)
            data = encode_estimate(
                EstimateMessage(self.robot, self.node.k, beliefs, self.counter_values())
            )
            self._last_estimate = data
        self.counters.estimates_sent += 1
        return [Publish(self.keys.estimate(self.robot), data)]

    def counter_values(self) -> dict[str, int]:
        """Every counter of the node and the core, by name."""
        c, a = self.node.counters, self.counters
        return {
            "step": self.node.k,
            "stacks_sent": c.stacks_sent,
            "stacks_received": c.stacks_received,
            "stacks_merged": c.stacks_merged,
            "stacks_unchanged": c.stacks_unchanged,
            "stacks_invalid": c.invalid,
            "stacks_badly_signed": c.errors_by_type.get("BadSignature", 0),
            "stacks_misaddressed": c.errors_by_type.get("SenderMismatch", 0),
            "slots_rejected": c.rejected_slots,
            "slots_foreign": c.foreign_slots,
            "own_slot_invalid": c.own_slot_invalid,
            "slots_refused": a.slots_refused,
            "slots_implausible": a.slots_implausible,
            "own_superseded": c.own_superseded,
            "slots_decoded": c.slots_decoded,
            "slots_skipped": c.slots_skipped,
            "slots_reused": c.slots_reused,
            "empty_joins": c.empty_joins,
            "rebuilds": c.rebuilds,
            "completed_joins": c.completed_joins,
            "ignored_out_of_range": a.ignored_out_of_range,
            "listen_changes": a.listen_changes,
            "bytes_sent": c.bytes_sent,
            "bytes_sent_ticks": self.tick_bytes,
            "digests_skipped": self.digests_skipped,
            "relays_asked": a.relays_asked,
            "asks_answered": a.asks_answered,
            "bytes_received": c.bytes_received,
            "frames_processed": a.frames_processed,
            "fusions_deferred": a.fusions_deferred,
            "frames_invalid": a.invalid_frames,
            "frames_duplicate": a.frames_duplicate,
            "frames_ahead": a.frames_ahead,
            "frames_quarantined": a.frames_quarantined,
            "frames_degraded": a.frames_degraded,
            "steps_failed": a.steps_failed,
            "steps_stuck": a.steps_stuck,
            "restores": a.restores,
            "control_invalid": a.invalid_control,
            "orders_ahead": a.orders_ahead,
            "rounds_dropped": a.rounds_dropped,
            "links_invalid": a.invalid_links,
            "estimates_sent": a.estimates_sent,
            "estimates_skipped": a.estimates_skipped,
            "need_requests": a.need_requests,
            "round_requests": a.round_requests,
            "rounds_resent": a.rounds_resent,
            "status_requests": a.status_requests,
            "replayed_frames": a.replayed_frames,
            "replayed_stacks": a.replayed_stacks,
            "records_quarantined": a.records_quarantined,
            "step_us_local": self._step_us[0],
            "step_us_distributed": self._step_us[1],
            "hypotheses_local": len(self.node.local.hypotheses),
            "hypotheses_distributed": len(self.node.distributed.hypotheses),
            **(self.extra_counters() if self.extra_counters is not None else {}),
        }

    def _log_invalid(self, source: str, exc: Exception) -> None:
        """At most one line per source and ``invalid_log_period`` (at the time of the event)."""
        now = self._now
        last = self.counters.last_invalid.get(source, -math.inf)
        if now - last >= self.settings.invalid_log_period:
            self.counters.last_invalid[source] = now
            log.warning("%s: invalid input from %s: %s", self.robot, source, exc)
