"""AgentCore: one agent of the fleet without any I/O (the aioquic pattern).

The core takes events — a message that arrived on a key (frame, stack, control, simulated links),
a timer tick — each with the current time ``now``, and returns *actions*: publish these bytes on
that key, append a record to the journal, commit it, quarantine an input, log. It owns the
:class:`~agents.node.RobotNode` and every bounded buffer around it; it never touches a socket, a
clock, a thread or a file. ``agents/runtime.py`` is the asyncio shell that feeds it. Its ports,
given at construction: the journal reader (``committed``), the wall clock that bounds slot
versions (``wall_clock``), the clock that times a step's phases (``step_clock``) and the shell's
own counters for the estimates (``shell_counters``).

The core is a dispatcher over policies that own their state and are driven with ``now``:
:class:`~agents.gossip.DeltaGossip` (what of the stack goes to whom and when),
:class:`~agents.rounds.Rounds` (lock-step orders, round stacks and their repair; built only in
lock-step mode), :class:`~agents.rounds.Answers` (how often a repeated request is answered) and
:class:`~agents.sim_radio.SimRadio` (a simulation's links; built only in a simulation). Every
decision on a received stack is the node's (:meth:`~agents.node.RobotNode.receive`); the step is
the node's (:meth:`~agents.node.RobotNode.on_frame`). What stays here is what ties them: the
frames, the journal (commit, roll-back, replay) and the estimates.

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

Over 300 lines for a reason: the agent's event logic that is not a policy's (frames, the
journal's commit, roll-back and replay, estimates) is one state machine over one node: what is
committed and what is refused are invariants of it. The policies hold everything else.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from agents.ages import Ages, Aging
from agents.control import (
    Control,
    NeedFrames,
    NeedRound,
    Status,
    StepOrder,
    Stop,
    decode_control,
    encode_control,
    fits_key,
)
from agents.gossip import DIGEST_LIFE, RELAYS, DeltaGossip, Outgoing, Sent
from agents.journal import Record
from agents.node import Received, RobotNode, admits_round, refuse_round
from agents.recovery import FRAME, FRAME_UNFUSED, Ledger, Replayed, apply, restore
from agents.rounds import Answers, Rounds
from agents.sim_radio import SimRadio
from agents.transport.base import Keys
from estimator.gate import Implausible
from estimator.models import SensorFrame
from estimator.models.objects import ObjectKind
from protocol.codec import StackMessage
from protocol.errors import BadSignature, RemoteProtocolError, SenderMismatch
from protocol.estimate import EstimateMessage, encode_estimate
from protocol.frames import decode_frame, encode_frame

log = logging.getLogger(__name__)

MODES = ("lockstep", "realtime")
STACK_GOSSIP = ("delta", "ask", "full")
GOSSIP_PERIOD_S = 0.5  # the one default gossip period (agent configs, launches)
WINDOW_STEPS = 64  # the one default of how far ahead frames, orders, rounds and links are kept
# At most this many steps in a row defer their fusion while the agent is behind its frames: the
# peers' slots are fused at least every (CATCH_UP_STEPS + 1)-th step (every 2 s at 0.5 s steps).
CATCH_UP_STEPS = 3


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
    # When a slot a peer asked for goes: "event" (the default), on arrival, at most one stack a
    # push window; "tick", with the next gossip tick (before issue 47; agents.gossip).
    relay: str = "event"
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
        if self.relay not in RELAYS:
            raise ValueError(f"relay {self.relay!r} (known: {', '.join(RELAYS)})")
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


@dataclass(frozen=True, slots=True)
class Flush:
    """Call :meth:`AgentCore.on_flush` at ``at`` (the core's clock): event-driven relay held a
    stack back for the push window (``agents.gossip.PUSH_WINDOW_S``)."""

    at: float


Action = Publish | Append | Commit | Quarantine | CutJournal | Halt | Listen | Hear | Flush


@dataclass(slots=True)
class CoreCounters:
    """What the core adds to the node's and the policies' counters."""

    invalid_frames: int = 0
    invalid_control: int = 0
    frames_processed: int = 0
    fusions_deferred: int = 0
    frames_duplicate: int = 0
    frames_ahead: int = 0
    orders_ahead: int = 0  # real time: orders beyond the window (lock-step: the Rounds' count)
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
    status_requests: int = 0
    records_quarantined: int = 0
    last_invalid: dict[str, float] = field(default_factory=dict)


class AgentCore:
    """One robot's agent logic. ``make_node()`` builds a fresh node (at step 0) exactly as the
    first one was built; the ports (module docstring): ``committed()`` returns the records
    committed so far (the journal), from which a failed step is rolled back (None: a failed step
    halts the agent); ``wall_clock()`` seconds since the Unix epoch, for the version bound (None:
    no bound); ``step_clock()`` seconds, for the step's phase timings (None: not timed);
    ``shell_counters()`` the shell's counters, reported with the core's; ``clock()`` the clock of
    every ``now``, read when a step ends and when an estimate is made (holding times,
    ``agents.ages``; None: the event's ``now``)."""

    def __init__(
        self,
        make_node: Callable[[], RobotNode],
        keys: Keys,
        settings: CoreSettings | None = None,
        committed: Callable[[], Sequence[Record]] | None = None,
        wall_clock: Callable[[], float] | None = None,
        step_clock: Callable[[], float] | None = None,
        shell_counters: Callable[[], Mapping[str, int]] | None = None,
        clock: Callable[[], float] | None = None,
    ) -> None:
        self.make_node = functools.partial(_aged_node, self, make_node)
        self.committed = committed
        self.wall_clock = wall_clock
        self.step_clock = step_clock
        self.shell_counters, self.clock = shell_counters, clock
        s = self.settings = settings or CoreSettings()
        self.node = self.make_node()
        self.robot = self.node.robot
        self.keys = keys
        self._sim_keys = (keys.sim_links(self.robot), keys.sim_listen(self.robot))
        self.counters = CoreCounters()
        self._status_due = False  # a status request came in the current batch
        self.replayed = Replayed()
        self.stop_reason = ""
        self.gossip, self.answers, self.rounds, self.radio = _policies(self.node, s)
        # Room for the ages of every slot held and of as many again let go of, twice: a held
        # slot whose versions stopped coming must keep its age (the neighbourhood bound reads it).
        self.ages, self._arrived = Ages(self.robot, 4 * self.node.limits.max_slots), 0.0
        self._frames: dict[int, tuple[SensorFrame, bytes]] = {}
        self.ledger = Ledger()
        self._last_estimate: bytes | None = None
        self._last_need = -math.inf
        self._step_us = (0, 0)
        self._out = Outgoing()
        self._now = 0.0
        self.tick_bytes = 0  # bytes of stacks and digests the timer or a flush sent (loop only)

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
                apply(self.node, record, self.replayed)
            except Exception as exc:
                self.counters.records_quarantined += 1
                reason = f"replay of record {index} ({record.kind}): {type(exc).__name__}: {exc}"
                log.error("%s: %s", self.robot, reason)
                actions.append(Quarantine(record.kind, record.body, reason, index))
                self.node = restore(self.make_node, records[:index])
                if record.kind not in (FRAME, FRAME_UNFUSED):
                    continue
                actions.append(CutJournal(index))
                break
        if records:
            done = (self.robot, self.replayed.frames, self.replayed.stacks, self.node.k)
            log.info("%s: replayed %d frames and %d stacks (now at step %d)", *done)
        self._refresh()
        return actions

    def start(self, now: float) -> list[Action]:
        """After start or restart: tell the fleet where this agent is."""
        self._now = now
        actions = self._publish_stack()
        if self.node.k > 0:
            actions += self._publish_estimate()
        return [*self._listen(initial=True), *actions, *self._need(self.node.k + 1, now, True)]

    # -- events ------------------------------------------------------------------------------

    def on_message(self, key: str, payload: bytes, now: float) -> list[Action]:
        """One message that arrived on ``key``; then every step that became possible."""
        return self.on_messages([(key, payload)], now)

    def on_messages(
        self,
        messages: Sequence[tuple[str, bytes]],
        now: float,
        arrived: Sequence[float] | None = None,
    ) -> list[Action]:
        """Messages (key, payload) that arrived together, in order (each at ``arrived[i]``, by
        default ``now``), each followed by every step it made possible; what the timer sends is
        refreshed once, after all of them."""
        keys = self.keys
        self._now = now
        self.ledger.batch = []
        actions: list[Action] = []
        # In real time, every message of the batch first: a step then sees the frames that are
        # already waiting behind it (and catches up) and fuses every stack that came with them.
        at_once = self.settings.mode == "realtime"
        for i, (key, payload) in enumerate(messages):
            self._arrived = now if arrived is None else arrived[i]
            if key.startswith(keys.ctl("")):
                actions += _on_control(self, key, payload)
            elif key == keys.frames(self.robot):
                actions += self._on_frame(payload)
            elif key.startswith(f"{keys.prefix}/stack/"):
                self._on_stack(key, payload)
            elif key in self._sim_keys and self.radio is not None:
                ahead = key == self._sim_keys[1]
                error = self.radio.on_links(payload, ahead, self.node.k)
                if error is not None:
                    _log_invalid(self, "sim", error)
            if not at_once:
                actions += self._step_all()
        if at_once:
            actions += self._step_all()
        if self._status_due:
            self._status_due = False
            actions += self._publish_estimate()
        actions += self._listen() + self._hear()
        self._refresh()
        sent, self._out = self.gossip.send_now(self._out, now)  # real time: what goes at once
        if sent is not None:
            pushes = _pushes(self, sent)
            for p in pushes:
                self.node.mark_sent(len(p.payload))
            actions += pushes
        elif self._out.flush_at < math.inf:
            actions.append(Flush(self._out.flush_at))
        return actions

    def on_flush(self, now: float) -> list[Action]:
        """Event-driven relay, on the shell's loop at a :class:`Flush`: the stack held back."""
        sent = self.gossip.flush(self._out, now)
        pushes = [] if sent is None else _pushes(self, sent)
        self.tick_bytes += sum(len(p.payload) for p in pushes)
        return list(pushes)

    def on_timer(self, now: float, announce: bool = False) -> list[Action]:
        """The gossip tick: re-send the stack (and, in lock-step, the previous round's, which a
        slower peer may still need) and ask for missing frames. Safe during a running step.
        ``announce``: send the digest even when it is not due (new peers were just subscribed
        to, and may have missed it)."""
        out = self._out
        self._now = now
        sends, ask = self.rounds.tick(out, now) if self.rounds is not None else ([], None)
        if self.rounds is None and (data := self.gossip.tick(out, now, announce)) is not None:
            sends = [data]
        if out.stack is not None:
            self.tick_bytes += sum(len(b) for b in sends)
        actions: list[Action] = [Publish(self.keys.stack(self.robot), b) for b in sends]
        if out.need_from is not None:
            actions += self._need(out.need_from, now)
        if ask is not None:
            actions.append(Publish(self.keys.ctl("need", self.robot), encode_control(ask)))
        return actions

    # -- input -------------------------------------------------------------------------------

    def _on_frame(self, data: bytes) -> list[Action]:
        try:
            frame = decode_frame(data)
            _check_frame(frame, self.robot, self.node.local.model.objects)
        except (RemoteProtocolError, ValueError) as exc:
            self.counters.invalid_frames += 1
            _log_invalid(self, "frames", exc, "frames_invalid")
            return []
        k = self.node.k
        if frame.k <= k:
            self.counters.frames_duplicate += 1
            if frame.k == k and k > 0 and self.answers.due(k, self._now):
                return self._publish_estimate(self._last_estimate)
            return []
        if frame.k > k + self.settings.window:
            self.counters.frames_ahead += 1
            return []
        if self.ledger.is_bad(data):
            self.counters.frames_duplicate += 1  # these very bytes failed a step before
            return []
        self._frames.setdefault(frame.k, (frame, data))
        return []

    def _on_stack(self, key: str, payload: bytes) -> None:
        """A peer's stack: admitted by the node (:meth:`RobotNode.receive`), its digest noted,
        then merged (real time) or held for its round (lock-step). A simulated radio does not
        even read the stack of a robot out of range, nor take its digest."""
        sender = self.keys.stack_sender(key)
        radio = self.radio if self.settings.mode == "realtime" else None
        k = self.node.k
        if radio is not None and sender not in (None, self.robot) and not radio.heard(sender, k):
            self.node.count_unread(payload)
            return radio.out_of_range()
        heard: Callable[[str], bool] = (
            (lambda s: True) if radio is None else (lambda s: radio.heard(s, k))
        )
        wall = None if self.wall_clock is None else self.wall_clock()
        got = self.node.receive(
            payload, sender, self.ledger.refused, wall, None if self.rounds is not None else heard
        )
        self._count(got, sender or key)
        message = got.message
        if message is None:
            return
        if radio is not None and not heard(message.sender):
            radio.out_of_range()
            return
        asked = frozenset(o for o, r in (message.ask or {}).items() if r == self.robot)
        if message.have is not None:
            self.gossip.note_digest(message.sender, message.have, asked, self._now)
        if self.rounds is not None:
            self.rounds.hold(message, payload, k, self._hears)
            return
        self._took(got, payload)
        if message.have is not None:
            # Versions the sender holds that this robot still lacks after taking what came
            # with them: the ticks pull them (send the digest) when the sender could push.
            held = self.node.stack.versions()
            self.gossip.check_wanted(message.sender, message.have, held, self._now)

    def _hears(self, message: StackMessage) -> bool:
        return admits_round(self.node, message)

    def _count(self, got: Received, source: str) -> None:
        self.counters.slots_refused += got.refused
        self.counters.slots_implausible += got.implausible
        if got.error is not None:
            where = got.message.sender if got.message else source
            _log_invalid(self, where, got.error, _stack_counter(got.error))

    def _took(self, got: Received, payload: bytes) -> None:
        """A merge that changed the node: its stack is journaled with the next step, its new
        versions stay suspects until then."""
        if got.taken:
            self.ledger.took(got.merged, payload)
            self.gossip.came([owner for owner, _ in got.merged], self._now)
            _aged(self, got)

    def _listen(self, initial: bool = False) -> list[Action]:
        """A :class:`Listen` when whom to hear changed (``initial``: always)."""
        s = self.settings
        if self.radio is None or not (s.listen_in_range and s.mode == "realtime"):
            return [Listen(None)] if initial else []
        peers = self.radio.listen(self.node.k, self.node.roster, initial)
        return [] if peers is None else [Listen(peers)]

    def _hear(self) -> list[Action]:
        """A :class:`Hear` when the stacks worth waking for changed (:meth:`SimRadio.hear`)."""
        if self.radio is None or self.settings.mode != "realtime":
            return []
        keys = self.radio.hear(self.node.k, self.keys.stack)
        if keys is None:
            return []
        pushes = {self.keys.stack_to(self.keys.stack_sender(k) or "*", self.robot) for k in keys}
        return [Hear(keys | pushes)]

    # -- stepping ----------------------------------------------------------------------------

    def _step_all(self) -> list[Action]:
        actions: list[Action] = []
        while (step := self._try_step()) is not None:
            actions += step
        return actions

    def _try_step(self) -> list[Action] | None:
        k = self.node.k + 1
        if k not in self._frames:
            return None
        if self.rounds is not None and not _merge_round(self, self.rounds, k):
            return None
        frame, data = self._frames.pop(k)
        # The frame is here: the timer must not go on asking for it while the step runs (every
        # request made the conductor send it again, and every copy was answered with an estimate).
        self._out = dataclasses.replace(self._out, need_from=None, need_round=None)
        behind = self.settings.mode == "realtime" and k + 1 in self._frames
        catching_up = behind and self.settings.catch_up > 0
        fuse = not behind or self.ledger.deferred_in_row >= self.settings.catch_up
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
        with np.errstate(over="raise", invalid="raise", divide="ignore"):
            done = self.node.on_frame(frame, fuse, self.step_clock)
        self._step_us = (
            round(1e6 * done.local_s),
            round(1e6 * (done.fusion_s + done.distributed_s)),
        )

    def _committed_step(self, frame: bytes, fused: bool, report: bool = True) -> list[Action]:
        """Commit a step taken with the frame bytes ``frame`` and publish. A step that deferred
        its fusion commits its frame alone: the stacks merged so far go into the journal, and
        stay suspects, with the step that fuses them. ``report=False``: no estimate (it would be
        superseded by the step that follows at once; one is made if asked for)."""
        self.counters.frames_processed += 1
        self.counters.fusions_deferred += not fused
        records = self.ledger.commit(frame, fused)
        actions: list[Action] = [*(Append(r.kind, r.body) for r in records), Commit()]
        self.ages.took(self.robot, (self.node.epoch, self.node.k), 0, _time(self))
        if fused:
            actions += self._publish_stack(previous=self._out.stack)
        return actions + self._report(report)

    def _recover(self, frame: SensorFrame, data: bytes, exc: Exception, fuse: bool) -> list[Action]:
        self.counters.steps_failed += 1
        reason = f"step {frame.k}: {type(exc).__name__}: {exc}"
        log.error("%s: %s; rolling back", self.robot, reason, exc_info=exc)
        suspects = self.ledger.failed(data)
        self.counters.slots_refused += len(suspects)
        failed = (self.robot, frame.k, suspects)
        if self.committed is None:
            # Nothing to roll back to: stop stepping rather than go on from a broken belief.
            self.stop_reason = f"step failed with no journal to roll back to ({reason})"
            return [Quarantine(FRAME, data, reason), Halt(self.stop_reason)]
        self._rollback()
        if suspects:
            try:
                self._run(frame, fuse)
                log.warning("%s: step %d succeeded without the refused slots %s", *failed)
                return self._committed_step(data, fuse)
            except Exception as again:
                reason = f"step {frame.k}: {type(again).__name__}: {again}"
                self._rollback()
        self.counters.frames_quarantined += 1
        actions: list[Action] = [Quarantine(FRAME, data, reason)]
        odometry_only = dataclasses.replace(frame, detections=(), true_pose=np.full(3, np.nan))
        try:
            self._run(odometry_only, fuse)
        except Exception as last:
            # The odometry itself is unusable: stay at the last good step, alive, until a
            # different frame k arrives (these bytes are never tried again).
            self._rollback()
            self.counters.steps_stuck += 1
            log.error(
                "%s: step %d fails even on its odometry alone (%s): waiting", *failed[:2], last
            )
            return actions
        self.counters.frames_degraded += 1
        log.warning("%s: frame %d quarantined, stepped on its odometry only", self.robot, frame.k)
        return actions + self._committed_step(encode_frame(odometry_only), fuse)

    def _rollback(self) -> None:
        assert self.committed is not None
        self.counters.restores += 1
        self.node = restore(self.make_node, self.ledger.rollback(self.committed()))

    def _forget_before(self, k: int) -> None:
        self._frames = {j: f for j, f in self._frames.items() if j > k}
        if self.rounds is not None:
            self.rounds.forget_before(k)
        if self.radio is not None:
            self.radio.forget_before(k)

    def _frames_missing(self) -> int | None:
        k, frames = self.node.k + 1, self._frames
        missing = bool(frames) and k not in frames  # real time: a later frame came
        if self.rounds is not None:
            missing = self.rounds.frames_missing(k, frames)
        return k if missing else None

    # -- output ------------------------------------------------------------------------------

    def _refresh(self) -> None:
        """Publish, whole, what the timer may read."""
        # Always, even empty: a lock-step peer ordered to hear us at round 1 needs our round 0.
        data, digest, fresh, aging = _stack_payload(self)
        old, k = self._out, self.node.k
        rounds = None if self.rounds is None else self.rounds.round_missing(k + 1, self._hears)
        sent_at = old.digest_sent_at if digest == old.digest else -math.inf
        pull_at = self.gossip.pull_at(self.node.stack.versions())
        missing = self._frames_missing()
        to = self.gossip.askers
        self._out = Outgoing(
            data, old.previous, missing, digest, fresh, k, rounds, pull_at, sent_at, aging=aging,
            push_to=to,
        )  # fmt: skip

    def _need(self, k: int, now: float, force: bool = False) -> list[Action]:
        if not force and now - self._last_need < self.settings.retry_period:
            return []
        self._last_need = now
        self.counters.need_requests += 1
        payload = encode_control(NeedFrames(self.robot, k))
        return [Publish(self.keys.ctl("need", self.robot), payload)]

    def _publish_stack(self, previous: bytes | None = None) -> list[Action]:
        data, digest, _, aging = _stack_payload(self)
        pull_at, need, k = (
            self.gossip.pull_at(self.node.stack.versions()),
            self._out.need_from,
            self.node.k,
        )
        out = Outgoing(
            data, previous, need, digest, False, k, None, pull_at, self._now, aging=aging
        )
        self._out, data = out, out.sent_at(_time(self)) or data
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
            data = self._last_estimate = _estimate(self)
        self.counters.estimates_sent += 1
        return [Publish(self.keys.estimate(self.robot), data)]

    def counter_values(self) -> dict[str, int]:
        """Every counter of the node, the core and its policies, by name."""
        return _counter_values(self)


def _counter_values(core: AgentCore) -> dict[str, int]:
    c, a, g = core.node.counters, core.counters, core.gossip
    rounds, radio = core.rounds, core.radio
    return {
        "step": core.node.k,
        "stacks_sent": c.stacks_sent,
        "stacks_received": c.stacks_received,
        "stacks_merged": c.stacks_merged,
        "stacks_unchanged": c.stacks_unchanged,
        "stacks_invalid": c.invalid,
        "stacks_badly_signed": c.errors_by_type.get("BadSignature", 0),
        "stacks_misaddressed": c.errors_by_type.get("SenderMismatch", 0),
        "slots_rejected": c.rejected_slots,
        "slots_foreign": c.foreign_slots,
        "slots_evicted": c.evicted_slots,
        "own_slot_invalid": c.own_slot_invalid,
        "slots_refused": a.slots_refused,
        "slots_implausible": a.slots_implausible,
        "own_superseded": c.own_superseded,
        "slots_decoded": c.slots_decoded,
        "slots_skipped": c.slots_skipped,
        "slots_reused": c.slots_reused,
        "slots_unassociated": c.unassociated_slots,
        "rematches": core.node.without_ids.rematches,
        "peer_sightings": core.node.without_ids.peer_sightings,
        "empty_joins": c.empty_joins,
        "rebuilds": c.rebuilds,
        "completed_joins": c.completed_joins,
        "ignored_out_of_range": 0 if radio is None else radio.ignored_out_of_range,
        "listen_changes": 0 if radio is None else radio.listen_changes,
        "bytes_sent": c.bytes_sent,
        "bytes_sent_ticks": core.tick_bytes,
        "digests_skipped": g.digests_skipped,
        "relays_asked": g.relays_asked,
        "asks_answered": g.asks_answered,
        "relay_pushes": g.pushes + g.flushes,
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
        "orders_ahead": a.orders_ahead + (0 if rounds is None else rounds.orders_ahead),
        "rounds_dropped": 0 if rounds is None else rounds.rounds_dropped,
        "links_invalid": 0 if radio is None else radio.invalid_links,
        "estimates_sent": a.estimates_sent,
        "estimates_skipped": a.estimates_skipped,
        "need_requests": a.need_requests,
        "round_requests": 0 if rounds is None else rounds.round_requests,
        "rounds_resent": 0 if rounds is None else rounds.rounds_resent,
        "status_requests": a.status_requests,
        "replayed_frames": core.replayed.frames,
        "replayed_stacks": core.replayed.stacks,
        "records_quarantined": a.records_quarantined,
        "step_us_local": core._step_us[0],
        "step_us_distributed": core._step_us[1],
        **core.ages.report(core.node.distributed.stamps, _time(core)),
        "hypotheses_local": len(core.node.local.hypotheses),
        "hypotheses_distributed": len(core.node.distributed.hypotheses),
        **(core.shell_counters() if core.shell_counters is not None else {}),
    }


def _policies(
    node: RobotNode, s: CoreSettings
) -> tuple[DeltaGossip, Answers, Rounds | None, SimRadio | None]:
    """The core's policies for ``node`` under settings ``s`` (module docstring)."""
    roster, max_slots, robot, period = (
        node.roster,
        node.limits.max_slots,
        node.robot,
        s.gossip_period,
    )
    peers = 0 if roster is None else len(roster) - 1
    lockstep = s.mode == "lockstep"
    asks = s.stack_gossip == "ask"
    gossip = DeltaGossip(robot, period, lockstep, asks, roster, max_slots, s.relay)
    max_peers = len(roster) if roster is not None else max_slots
    rounds = Rounds(robot, period, s.window, peers, max_peers) if lockstep else None
    radio = SimRadio(robot, s.window, s.max_control_bytes) if s.simulation else None
    return gossip, Answers(robot, period, peers), rounds, radio


def _stack_payload(core: AgentCore) -> tuple[bytes, bytes | None, bool, Aging | None]:
    """The stack to gossip now, its digest alone (delta gossip in real time), whether the stack
    holds a slot not sent before and its slots' holding times (ask gossip in real time, when all
    are known: ``agents.ages``): every held slot (``stack_gossip = "full"``), else those
    :meth:`DeltaGossip.select` picks, with the asks in force (real time)."""
    node = core.node
    if core.settings.stack_gossip == "full":
        return node.encoded_stack(), None, True, None
    held = node.current_stack().versions()
    unsent = core._out.fresh and core.gossip.tick_last is not core._out.stack
    include = core.gossip.select(held, core._now, unsent)
    if core.rounds is not None:
        return node.encoded_delta(include), None, bool(include), None
    asks = core.gossip.current_asks(held, core._now)
    aging = None
    if core.settings.stack_gossip == "ask" and include:
        aging = core.ages.aging((o for o in held if o in include), held)  # the stack's order
    data = node.encoded_delta(include, asks, aged=aging is not None)
    return data, node.encoded_delta((), asks), bool(include), aging


def _pushes(core: AgentCore, sent: Sent) -> list[Publish]:
    """The publications of ``sent``: on the robot's stack key, or one on ``Keys.stack_to`` for
    each peer it goes to alone (event-driven relay's pushes of asked slots)."""
    data, to = sent
    if not to:
        return [Publish(core.keys.stack(core.robot), data)]
    return [Publish(core.keys.stack_to(core.robot, peer), data) for peer in sorted(to)]


def _aged_node(core: AgentCore, make_node: Callable[[], RobotNode]) -> RobotNode:
    """``make_node()``, whose full stack lets go of the oldest information by holding times in
    real time with ask gossip (``RobotNode.slot_ages``): an owner whose held version is older by
    more than the life of a digest (``DIGEST_LIFE`` gossip periods: then a peer is out of reach)
    than a new owner's makes room for it."""
    node = make_node()
    s = core.settings
    if s.mode == "realtime" and s.stack_gossip == "ask":
        node.slot_ages = lambda owners: core.ages.held_ages(
            owners, node.stack.versions(), core._arrived
        )
        node.age_margin_ms = round(1000 * DIGEST_LIFE * s.gossip_period)
    return node


def _aged(core: AgentCore, got: Received) -> None:
    """Holding times: the versions ``got`` made the node hold came at ``core._arrived``, as old
    as their stack said (``agents.ages``)."""
    said = got.message.age if got.message is not None else None
    for owner, version in got.merged:
        carried = None if said is None else said.get(owner)
        core.ages.took(owner, version, carried, core._arrived)


def _time(core: AgentCore) -> float:
    """Now, by the core's clock (the current event's ``now`` without one)."""
    return core.clock() if core.clock is not None else core._now


def _estimate(core: AgentCore) -> bytes:
    """The estimate of ``core``'s current step: D (and L, with ``publish_local``), counters and
    the version of each peer's slot D has integrated (what a launch times the age of
    information by)."""
    node, robot = core.node, core.robot
    beliefs = {"distributed": node.distributed.snapshot(robot)}
    if core.settings.publish_local:
        beliefs["local"] = node.local.snapshot(robot)
    fused = node.distributed.stamps
    return encode_estimate(EstimateMessage(robot, node.k, beliefs, core.counter_values(), fused))


def _merge_round(core: AgentCore, rounds: Rounds, k: int) -> bool:
    """Lock-step: merge the round stacks step ``k`` takes (:meth:`Rounds.ready`) after counting
    what the belief gate refuses of the copies it passes over; False: the round is not ready."""
    held = rounds.ready(k, core._hears)
    if held is None:
        return False
    for message in rounds.passed_over(k, held):
        core._count(refuse_round(core.node, message), message.sender)
    for message, data in held:
        got = core.node.merge_round(message, core.ledger.refused)
        core._count(got, message.sender)
        core._took(got, data)
    return True


def _on_control(core: AgentCore, key: str, payload: bytes) -> list[Action]:
    """A control message: step order, status request, stop, round request (lock-step)."""
    if (order := _decoded_control(core, key, payload)) is None:
        return []
    k = core.node.k
    if isinstance(order, StepOrder):
        if order.k == k and k > 0 and core.answers.order_due(order, core._now):
            return core._publish_estimate(core._last_estimate)  # the conductor missed our ack
        if core.rounds is not None:
            core.rounds.on_order(order, k)
        elif order.k > k + core.settings.window:
            core.counters.orders_ahead += 1
    elif isinstance(order, Status):
        # One estimate per batch, after its steps, however many asked (issue 43, finding 3).
        core.counters.status_requests += 1
        core._status_due = True
    elif isinstance(order, Stop):
        core.stop_reason = core.stop_reason or order.reason or "stopped by the conductor"
        return [Halt(core.stop_reason)]
    elif isinstance(order, NeedRound) and core.rounds is not None:
        out = core._out
        data = core.rounds.answer_round(
            order,
            core.keys.robot_of(key),
            {out.k: out.stack, out.k - 1: out.previous},
            core._now,
        )
        return [] if data is None else [Publish(core.keys.stack(core.robot), data)]
    return []  # NeedFrames: for whoever publishes frames


def _check_frame(frame: SensorFrame, robot: str, kind: ObjectKind) -> None:
    """ValueError unless ``frame`` is ``robot``'s and its detections are of the robot's object
    ``kind`` (a frame holds one kind: ``protocol.frames``)."""
    if frame.robot != robot:
        raise ValueError(f"frame of robot {frame.robot}")
    if frame.detections and len(frame.detections[0].z_geo) != kind.dim:
        raise ValueError(
            f"frame {frame.k}: detections of {len(frame.detections[0].z_geo)} numbers, "
            f"this robot's {kind.name} objects have {kind.dim}"
        )


def _log_invalid(core: AgentCore, source: str, exc: Exception, counter: str = "") -> None:
    """At most one line per source, kind of error and ``invalid_log_period`` (at the time of
    the event), naming the counter that counts it: the log and the counters tell the same story
    (one error kind never hides another behind the rate limit)."""
    now, last_invalid = core._now, core.counters.last_invalid
    kind = f"{source}/{type(exc).__name__}"
    if now - last_invalid.get(kind, -math.inf) >= core.settings.invalid_log_period:
        if len(last_invalid) >= _MAX_LOG_SOURCES:
            last_invalid.clear()  # bounded whatever the sources claim to be
        last_invalid[kind] = now
        counted = f", counted in {counter}" if counter else ""
        name = type(exc).__name__
        log.warning("%s: invalid input from %s (%s%s): %s", core.robot, source, name, counted, exc)


_MAX_LOG_SOURCES = 1024


def _stack_counter(exc: Exception) -> str:
    """The counter of a stack refused by ``exc`` (``counter_values``)."""
    if isinstance(exc, BadSignature):
        return "stacks_invalid and stacks_badly_signed"
    if isinstance(exc, SenderMismatch):
        return "stacks_invalid and stacks_misaddressed"
    if isinstance(exc, Implausible):
        return "slots_rejected"
    if isinstance(exc, RemoteProtocolError):
        return "stacks_invalid"
    return "slots_implausible"  # a version ahead of its owner's clock


def _decoded_control(core: AgentCore, key: str, payload: bytes) -> Control | None:
    """The control message ``payload`` if it decodes and fits its ``key``
    (:func:`agents.control.fits_key`); else None, counted in ``control_invalid`` and logged."""
    try:
        order = decode_control(payload, max_bytes=core.settings.max_control_bytes)
        if not fits_key(order, key.removeprefix(core.keys.ctl(""))):
            raise ValueError(f"{type(order).__name__} on {key}, not its key")
    except (RemoteProtocolError, ValueError) as exc:
        core.counters.invalid_control += 1
        _log_invalid(core, "ctl", exc, "control_invalid")
        return None
    return order
