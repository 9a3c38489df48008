"""RobotNode: the sans-I/O core of one robot (design doc §6, ARCHITECTURE data flow).

It owns the robot's LOCAL belief L, its DISTRIBUTED belief D and its stack. Bytes come in through
``on_stack``, frames through ``on_frame``, and ``outgoing`` gives the bytes to send. It never
touches a socket, a clock or a thread; the shells (in-process runner, asyncio agent) drive it.

Over 300 lines for a reason: L, D and the stack of one robot change together on every frame
and every stack (the own slot is rebuilt from L, D integrates what the stack holds); one class
keeps that order in one place.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Callable, Collection, Container, Iterable, Mapping
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from numpy.typing import ArrayLike

from agents.without_ids import WithoutIds
from estimator.association import Association, Associator, SensorField
from estimator.distributed import DistributedBelief, FusionStats, SlotError
from estimator.fleet_association import FleetAssociation, FleetAssociationConfig
from estimator.gate import (
    GateSettings,
    Held,
    Implausible,
    check_summary,
    evidence_per_detection,
    held_objects,
)
from estimator.hybrid import SPARSE_XI_ABOVE, BeliefConfig, BeliefModel, HybridBelief
from estimator.models import GLOBAL_IDS, Detection, SensorFrame
from estimator.slots import linearisation_point, summarise
from estimator.summary import LocalSummary
from protocol.codec import (
    MAX_EPOCH,
    Limits,
    StackMessage,
    decode,
    encode,
    sign_slot,
    with_wire,
)
from protocol.errors import LocalProtocolError, RemoteProtocolError, SenderMismatch
from protocol.signing import SigningKeys
from protocol.stack import Slot, Stack
from protocol.stack_size import largest_stack_bytes

if TYPE_CHECKING:
    import gtsam

log = logging.getLogger(__name__)


def _no_clock() -> float:
    return 0.0


Version = tuple[str, tuple[int, int]]  # a slot version: owner, (epoch, stamp)

# How far ahead of the receiver's clock a slot's version may be (docs/wire.md, "Versions and
# epochs"): an epoch is its owner's start in ms, so a stamp (a step) can be at most what the owner
# could have stepped since then at MAX_STEP_RATE, with CLOCK_SKEW_S for unsynchronised clocks and
# STAMP_SLACK steps for a fleet that starts at a step other than 0.
MAX_STEP_RATE = 100.0  # steps per second: 50× a 2 Hz robot, above any lock-step simulation here
CLOCK_SKEW_S = 300.0
STAMP_SLACK = 10_000
# At most one log line per this many steps for the own slot taken at L's point (the fit check,
# ``estimator.slots``): on real data it refuses at most steps of a run, and one line per robot
# and step was 11,500 lines in a four-run study of UTIAS Dataset 7. The counter keeps them all.
FIT_LOG_STEPS = 100


def _log_fit_refused(node: RobotNode) -> None:
    """The own slot was taken at L's point: one line per FIT_LOG_STEPS steps at most."""
    if node.k - node._fit_logged_k < FIT_LOG_STEPS:
        return
    node._fit_logged_k = node.k
    log.warning(
        "%s: own slot at step %d taken at L's point: D's estimate does not fit L's own data "
        "(excess χ² %.3g per dimension; %d so far; at most one line per %d steps)",
        node.robot,
        node.k,
        node.local.slot_fit,
        node.local.slot_fit_refused,
        FIT_LOG_STEPS,
    )


def _local_ids(node: RobotNode) -> bool:
    """Frames without global ids: with per-object classes D matches every peer's objects onto
    its own (``estimator.fleet_association``); a table of joint classes cannot, and the node
    neither fuses peers' slots nor sends its own."""
    d = node.distributed
    if d.per_object:
        log_prior = np.log(np.asarray(d.model.class_prior, dtype=float))
        d.association = FleetAssociation(log_prior, node.fleet_config)
        return True
    log.warning(
        "%s: frames without global ids and joint class tables: its objects have robot-local "
        "ids, so it neither fuses peers' slots nor sends its own (fleet association needs "
        "per-object classes)",
        node.robot,
    )
    return True


@dataclass(frozen=True, slots=True)
class Received:
    """What :meth:`RobotNode.receive` made of one stack. ``message``: what was admitted of it
    (None: refused whole, or the node's own echo); ``merged``: the versions it made the node
    hold; ``refused`` and ``implausible``: its slots dropped as refused versions or as ahead of
    their owner's clock; ``error``: why it was refused whole, or what was dropped of it (for
    the shell's log)."""

    message: StackMessage | None
    merged: tuple[Version, ...] = ()
    taken: bool = False
    refused: int = 0
    implausible: int = 0
    error: Exception | None = None
    gated: int = 0


def _always(sender: str) -> bool:
    return True


def _without(message: StackMessage, drop: Callable[[Slot], bool]) -> tuple[StackMessage, int]:
    """``message`` without the slots ``drop`` picks (its digest stays), and how many."""
    kept = [s for s in message.stack if not drop(s)]
    if len(kept) == len(message.stack):
        return message, 0
    return replace(message, stack=Stack(tuple(kept))), len(message.stack) - len(kept)


def _ahead_of(wall_s: float | None) -> Callable[[Slot], bool]:
    """Whether a slot's version is ahead of what its owner can have made by ``wall_s``: an
    epoch after the receiver's clock, or a stamp beyond ``MAX_STEP_RATE`` steps per second since
    the epoch began (both with ``CLOCK_SKEW_S``). Such a version would block every genuine one
    of its owner until the owner moved past it. None: no bound."""
    if wall_s is None:
        return lambda slot: False
    now_ms = 1000.0 * (wall_s + CLOCK_SKEW_S)
    return lambda s: (
        not (
            s.epoch <= now_ms and s.stamp <= MAX_STEP_RATE * (now_ms - s.epoch) / 1000 + STAMP_SLACK
        )
    )


@dataclass(slots=True)
class NodeCounters:
    """What a node has seen. ``invalid`` counts messages rejected by the protocol layer,
    ``rejected_slots`` slots that decoded but contradict the belief's model or what it believes
    (the belief gate, ``estimator.gate``), ``foreign_slots``
    slots refused because their owner is outside the roster (or the stack is full),
    ``own_slot_invalid`` times the own slot could not be sent (outside the limits),
    ``evicted_slots`` held slots dropped for a fresher one when the stack was full (the
    neighbourhood bound, :meth:`RobotNode._admitted`),
    ``empty_joins`` slots whose join with D was empty and ``rebuilds`` the times D was rebuilt
    from L and the held slots because of one, ``completed_joins`` the hypotheses of D joined with
    a slot's nearest realisations because the slot carried none of theirs
    (``FusionStats.completed``); ``own_superseded`` the times a received stack held
    a version of the own slot newer than the node's (a lost journal's earlier life, or a forgery
    on an unsigned fleet): the node then moves to a higher epoch. ``slots_decoded`` counts the
    slots whose bodies were parsed, ``slots_skipped`` those left unparsed: versions the node
    already held or had passed, ``slots_reused`` those not parsed again because the node had
    parsed the very same bytes before and not merged them yet (a lock-step agent buffers the
    stacks of later rounds; docs/wire.md, "Decoding only what is new"); ``unassociated_slots``
    peers' slots not held because this robot's objects have robot-local ids (its frames came
    without global ids; what such a node adds is counted in ``RobotNode.without_ids``)."""

    stacks_received: int = 0
    stacks_merged: int = 0
    stacks_unchanged: int = 0
    invalid: int = 0
    rejected_slots: int = 0
    foreign_slots: int = 0
    own_slot_invalid: int = 0
    evicted_slots: int = 0
    empty_joins: int = 0
    rebuilds: int = 0
    completed_joins: int = 0
    own_superseded: int = 0
    slots_decoded: int = 0
    slots_skipped: int = 0
    slots_reused: int = 0
    unassociated_slots: int = 0
    bytes_received: int = 0
    stacks_sent: int = 0
    bytes_sent: int = 0
    last_error: str = ""
    errors_by_type: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class Signing:
    """A fleet that signs its slots (docs/wire.md, "Signed slots"): this robot's Ed25519 key,
    and every roster robot's public key (its own included)."""

    key: Ed25519PrivateKey
    keys: SigningKeys


class BeliefError(RuntimeError):
    """A belief that is no longer a distribution after a step (non-finite weights or poses): the
    step failed, and its shell must roll the node back."""


@dataclass(frozen=True, slots=True)
class StepReport:
    """One ``on_frame``: the fusion done on D before the local steps, and the time (s, by the
    step clock the caller gave; 0 without one) of its three phases: the fusion of the held
    slots into D, L's step, and D's step with its rebuild and checks."""

    k: int
    fusion: FusionStats
    fusion_s: float = 0.0
    local_s: float = 0.0
    distributed_s: float = 0.0


class LocalTrack:
    """A robot's LOCAL belief L and its generator: stepped once per frame, summarised at most once
    per step. L depends on the robot's own data only, so nodes of one robot that differ only in
    how they fuse (a study's consistent and double-counting fleets) may share one track.

    ``associator``: data association for frames without global ids (``estimator.association``):
    such a frame is associated with L's objects first, and L (and the node's D) step on the
    frame of robot-local ids it gives. Frames of global ids never reach it. ``guided``: the
    association is gated on the guide ``advance`` is given (the node's D), not on L; a track
    that several nodes share is not guided (each would guide it differently)."""

    def __init__(
        self,
        belief: HybridBelief,
        rng: np.random.Generator,
        associator: Associator | None = None,
        guided: bool = False,
    ) -> None:
        if len(belief.robots) != 1:
            raise ValueError("a local belief holds exactly one robot")
        self.belief = belief
        self.robot = belief.robots[0]
        self._rng = rng
        self.associator = associator
        self.guided = guided
        self.association: Association | None = None  # the last associated frame's
        self.association_s = 0.0  # its time, by the clock ``advance`` was given
        self._stepped: SensorFrame | None = None
        self._summary: LocalSummary | None = None
        self._summary_k = -1

    @property
    def k(self) -> int:
        return self.belief.step_of[self.robot]

    def advance(
        self,
        frame: SensorFrame,
        clock: Callable[[], float] | None = None,
        guide: HybridBelief | None = None,
    ) -> SensorFrame:
        """Step L with ``frame`` (associated first when its ids are not global, on ``guide``
        when the track is ``guided``) and return the frame L stepped on; a frame it already has
        is not stepped again (another sharer stepped it). ``clock`` times the association
        (``association_s``)."""
        if frame.k == self.k and self._stepped is not None and self._stepped.k == frame.k:
            return self._stepped
        if frame.k == self.k:
            return frame
        self.association_s = 0.0
        if frame.ids != GLOBAL_IDS:
            if self.associator is None:
                raise ValueError(
                    f"frame {frame.k} of {self.robot} has {frame.ids} ids: associating them "
                    "needs the robot's sensor field (an Associator)"
                )
            tick = clock if clock is not None else _no_clock
            t0 = tick()
            # a guide at another step (never with a node's D) would predict the wrong pose
            guided = self.guided and guide is not None and guide.step_of.get(self.robot) == self.k
            by = guide if guided else None
            self.association = self.associator.associate(self.belief, frame, by)
            self.association_s = tick() - t0
            frame = self.association.frame
        self.belief.step([frame], self._rng, self.replay_of(frame))
        self._stepped = frame
        return frame

    def replay_of(self, frame: SensorFrame) -> tuple[tuple[str, int, Detection], ...]:
        """The earlier detections of the objects ``frame`` confirmed (``Association.replay``),
        when it is the frame this track last associated; none for any other frame."""
        a = self.association
        return a.replay if a is not None and a.frame is frame else ()

    def summary(self, at: gtsam.Values | None = None) -> LocalSummary | None:
        """The own slot's content at the current step (None before any object is seen),
        linearised at ``at`` (a node's fused estimate; not shared with other sharers, so never
        kept) or at L's own point (kept for the step)."""
        if at is not None:
            return summarise(self.belief, at)
        if self._summary_k != self.k:
            self._summary = summarise(self.belief)
            self._summary_k = self.k
        return self._summary


class BeliefGate:
    """A node's belief gate (``estimator.gate``): which slots of a received stack contradict
    what D believes, decided once per slot version and content until D next changes."""

    def __init__(
        self, settings: GateSettings, model: BeliefModel, semantic_poses: bool, max_slots: int
    ) -> None:
        self.settings = settings
        # λmax(R⁻¹) of the detection factors, the information bound's unit; 0 when the semantic
        # factors also inform the Gaussians (no bound then), and for point objects: a bearing's
        # Jacobian in the point grows as 1/range, unbounded without a minimum range.
        pose_objects = model.objects.dim == 3
        self.geometric_info = (
            1.0 / min(model.geometric_noise.variances)
            if pose_objects and not semantic_poses
            else 0.0
        )
        # B, the class evidence one detection can give (the class-evidence bound's unit; 0 with
        # semantic_poses too): scores plausible at the gate's false-alarm rate (10⁻⁹ when off).
        plausible = settings.false_alarm or GateSettings().false_alarm
        self.per_detection = (
            0.0 if semantic_poses else evidence_per_detection(model.classifier, plausible)
        )
        self._max = 4 * max_slots
        self._held: Held | None = None  # D's objects, until D next changes
        # (owner, epoch, stamp, content) → verdict; the content is told by the slot's signature
        # or the hash of its bytes, never by holding the slot itself (a refused slot of tens of
        # MB must not stay in memory because it was refused).
        self._verdicts: dict[tuple[str, int, int, object], Implausible | None] = {}

    def changed(self) -> None:
        self._held = None
        self._verdicts.clear()

    def refused(
        self, message: StackMessage, robot: str, held: Stack, belief: DistributedBelief
    ) -> dict[str, Implausible]:
        """Owner → why, for every slot of ``message`` newer than the version ``held`` that the
        gate refuses (``robot``'s own slot is never checked here)."""
        bad: dict[str, Implausible] = {}
        for s in message.stack:
            if s.owner == robot or s.version <= (held.version_of(s.owner) or (-1, -1)):
                continue
            content = s.signature or (hash(s.wire.data) if s.wire is not None else None)
            key = (s.owner, s.epoch, s.stamp, content)
            if content is not None and key in self._verdicts:
                verdict = self._verdicts[key]
            else:
                verdict = self._verdict(s, belief)
                if len(self._verdicts) >= self._max:
                    self._verdicts.clear()
                if content is not None:
                    self._verdicts[key] = verdict
            if verdict is not None:
                bad[s.owner] = verdict
        return bad

    def _verdict(self, slot: Slot, belief: DistributedBelief) -> Implausible | None:
        try:
            belief.check(slot)
        except SlotError:
            return None  # not this gate's to judge: the model fit refuses it at the merge
        # Robot-local ids: a slot's ids are not D's, and which D object each is comes from the
        # matching (``estimator.fleet_association``), itself gated: no test by id here.
        by_id = belief.association is None
        if self._held is None and self.settings.false_alarm and len(belief.object_ids) and by_id:
            self._held = held_objects(belief)
        try:
            check_summary(
                slot.owner,
                slot.summary,
                slot.stamp,
                self._held if by_id else None,
                self.geometric_info,
                self.settings,
                self.per_detection,
            )
        except Implausible as exc:
            # Without its traceback: its frames hold the slot's matrices (tens of MB at most).
            return exc.with_traceback(None)
        except (ArithmeticError, ValueError, RuntimeError) as exc:  # numbers it cannot judge
            return Implausible(f"slot of {slot.owner}: cannot be checked ({exc})")
        return None


def node_limits(num_classes: int, config: BeliefConfig) -> Limits:
    """The default wire limits of a node whose beliefs follow ``config``: the defaults, with room
    for as many class realisations per slot as its own local belief may hold (``config.cap()``;
    4,096 for ``BeliefConfig.exact()``), so that no node refuses its own slot, nor a peer's of
    the same configuration, for holding what the belief was configured to hold."""
    default = Limits(num_classes=num_classes)
    return replace(default, max_realisations=max(default.max_realisations, config.cap()))


class RobotNode:
    """One robot. ``rng_local`` and ``rng_distributed`` must be two generators built from the same
    seed: then, with nothing received, D repeats L exactly. ``local`` may hand in a shared
    :class:`LocalTrack` instead (``rng_local`` is then unused)."""

    def __init__(
        self,
        robot: str,
        start: ArrayLike,
        model: BeliefModel,
        rng_local: np.random.Generator,
        rng_distributed: np.random.Generator,
        config: BeliefConfig | None = None,
        fusion: str = "consistent",
        downdate: str = "remove",
        limits: Limits | None = None,
        local: LocalTrack | None = None,
        roster: frozenset[str] | None = None,
        signing: Signing | None = None,
        epoch: int = 0,
        gate: GateSettings | None = None,
        sensor: SensorField | None = None,
        keep_slots: int | None = None,
    ) -> None:
        self.robot = robot
        # The own slot's epoch (docs/wire.md, "Versions and epochs"): the shell gives the one of
        # its journal; it only grows, when a stack shows a newer version of the own slot.
        self.epoch = epoch
        if signing is not None and signing.keys.get(robot) != signing.key.public_key():
            raise ValueError(f"{robot}'s signing key is not the one its roster holds for it")
        self.signing = signing
        if local is None:
            associator = None if sensor is None else Associator(model, sensor)
            local = LocalTrack(
                HybridBelief(model, {robot: start}, config), rng_local, associator, guided=True
            )
        if local.robot != robot:
            raise ValueError(f"node {robot} got the local track of {local.robot}")
        self.track = local
        self.distributed = DistributedBelief(model, robot, start, config, fusion, downdate)
        held = (config or BeliefConfig()).cap()  # the most realisations the own slot may hold
        self.limits = limits or node_limits(model.num_classes, config or BeliefConfig())
        if self.limits.max_realisations < held:
            raise ValueError(
                f"limits: max_realisations {self.limits.max_realisations} cannot hold this "
                f"belief's own slot (up to {held} class realisations): raise it, or lower "
                "max_hypotheses"
            )
        if roster is not None and robot not in roster:
            raise ValueError(f"robot {robot} is not in its own roster {sorted(roster)}")
        self.roster = roster
        # Refuse unread any stack larger than the largest this fleet's configuration can send
        # (protocol.stack_size): one slot per roster robot, each as large as the form allows.
        cfg = config or BeliefConfig()
        robots = len(roster) if roster is not None else self.limits.max_slots
        largest = largest_stack_bytes(self.limits, robots, cfg.classes, cfg.xi, SPARSE_XI_ABOVE)
        if largest < self.limits.max_message_bytes:
            self.limits = replace(self.limits, max_message_bytes=largest)
        self.stack = Stack()
        # The slots this robot keeps, its own included (docs/distributed.md, "How many robots a
        # D holds"): at most a stack's (the wire's ``max_slots``), fewer on a robot that bounds
        # its neighbourhood while it still takes stacks of up to ``max_slots``.
        self.keep_slots = self.limits.max_slots if keep_slots is None else keep_slots
        if not 2 <= self.keep_slots <= self.limits.max_slots:
            raise ValueError(f"keep_slots {keep_slots}: must be in 2..{self.limits.max_slots}")
        # Real time with holding times: the ages (ms) of held slots, which the agent core gives
        # (``agents.ages``), and by how much a new owner's slot must be younger than the oldest
        # held to take its place (:func:`_evict_for`); None: stamps decide.
        self.slot_ages: Callable[[Iterable[str]], dict[str, int]] | None = None
        self.age_margin_ms = 0
        self._incoming_age: dict[str, int] | None = None  # the ages the stack being merged said
        semantic_poses = cfg.semantic_poses
        self.gate = BeliefGate(gate or GateSettings(), model, semantic_poses, self.limits.max_slots)
        self.counters = NodeCounters()
        self.position: tuple[float, float] | None = None
        self.k = 0
        self._rng_distributed = rng_distributed
        self._encoded: bytes | None = None
        # encoded_delta's bytes per chosen owners, for one (stack, step, position)
        self._deltas_at: tuple[Stack, int, tuple[float, float] | None] | None = None
        self._deltas: dict[tuple[tuple[str, ...], tuple[tuple[str, str], ...], bool], bytes] = {}
        # Slots parsed and not yet held, by version (see ``decode_stack``).
        self._parsed: OrderedDict[tuple[str, int, int], Slot] = OrderedDict()
        self._own_slot_stale = False
        self._fit_logged_k = -FIT_LOG_STEPS  # the step of the last "taken at L's point" line
        self._rebuild_due = False
        self.without_ids = WithoutIds()  # frames without global ids: around D's step
        # how D matches peers' objects when its frames have no global ids (``_local_ids``)
        self.fleet_config = FleetAssociationConfig()
        self._last_refusal: Exception | None = None  # why the last stack was refused whole
        # Frames without global ids: robot-local object ids, which no peer shares: D matches
        # peers' objects onto its own (``_local_ids``; issue 45, item 3).
        self.local_ids = False

    @property
    def local(self) -> HybridBelief:
        """L, the robot's belief from its own data only."""
        return self.track.belief

    # -- input -------------------------------------------------------------------------------

    def on_stack(self, data: bytes) -> bool:
        """Decode and merge a received stack; True if it brought a newer slot. Invalid input is
        counted and dropped: nothing already accepted is lost."""
        return self.receive(data).taken

    def receive(
        self,
        payload: bytes,
        sender: str | None = None,
        refused: Container[Version] = (),
        wall_s: float | None = None,
        merge_if: Callable[[str], bool] | None = _always,
    ) -> Received:
        """Every decision on a received stack, in one order: decode (bounded, signatures, only
        the versions that can change anything parsed), the sender (a stack published on the key
        of ``sender`` must be that robot's: else forged or misrouted), the ``refused`` versions
        (they failed a step here before), plausibility (no version ahead of what its owner can
        have made by ``wall_s``, seconds since the Unix epoch; None: no bound), then — when
        ``merge_if(sender)`` — the model fit of each new slot and the merge (``taken``: the stack
        changed the node, its versions or its own epoch, and a journal must keep it).
        ``merge_if=None`` admits without merging (a lock-step round stack, merged at its step by
        :meth:`merge_round`). Every refusal is counted; nothing already held is lost."""
        if sender == self.robot:
            return Received(None)  # our own publication, echoed by the session
        message = self.decode_stack(payload)
        if message is None:
            return Received(None, error=self._last_refusal)
        if message.sender == self.robot:
            return Received(None)
        if sender is not None and message.sender != sender:
            # Each robot publishes only on its own key (access control enforces it on a secure
            # fleet): a stack whose sender is another robot is forged or misrouted.
            exc = SenderMismatch(f"sent by {message.sender!r} on the key of {sender}", "sender")
            self.reject(exc)
            return Received(None, error=exc)
        message, dropped = _without(message, lambda s: (s.owner, s.version) in refused)
        message, implausible = _without(message, _ahead_of(wall_s))
        error: Exception | None = (
            ValueError("a slot version ahead of its owner's clock") if implausible else None
        )
        taken: bool = False
        merged: tuple[Version, ...] = ()
        if merge_if is None:
            # A lock-step round stack: the belief gate judges it at its step (:meth:`merge_round`),
            # against D as it is then, as the in-process runner does — judged on arrival, it met
            # whatever step this robot was at, and a refused sender stalled the round for good.
            return Received(message, refused=dropped, implausible=implausible, error=error)
        admitted, bad = gated(self, message)
        if admitted is None:
            # A sender whose own slot contradicts what this robot believes is not heard: its
            # stack is refused whole.
            return Received(None, refused=dropped, gated=len(bad), error=bad[message.sender])
        if bad:
            error = next(iter(bad.values()))
        if merge_if(message.sender):
            taken, merged = self._merged(admitted)
        return Received(admitted, merged, taken, dropped, implausible, error, len(bad))

    def _changed(self) -> None:
        """D changed: the gate's view of it and its verdicts are made again when next needed."""
        self.gate.changed()

    def merge_round(self, message: StackMessage, refused: Container[Version] = ()) -> Received:
        """Merge a round stack admitted by :meth:`receive` and held for its step (lock-step),
        without the versions refused since, and through the belief gate as :meth:`receive`
        passes a stack in real time (a sender whose own slot it refuses: nothing merged)."""
        message, dropped = _without(message, lambda s: (s.owner, s.version) in refused)
        admitted, bad = gated(self, message)
        if admitted is None:
            return Received(None, refused=dropped, gated=len(bad), error=bad[message.sender])
        taken, merged = self._merged(admitted)
        error = next(iter(bad.values())) if bad else None
        return Received(admitted, merged, taken, dropped, error=error, gated=len(bad))

    def count_unread(self, payload: bytes) -> None:
        """A stack the shell dropped unread (a simulated radio out of range): counted as
        received."""
        self.counters.stacks_received += 1
        self.counters.bytes_received += len(payload)

    def _merged(self, message: StackMessage) -> tuple[bool, tuple[Version, ...]]:
        before = self.stack.versions()
        if not self.merge(message):
            return False, ()
        after = self.stack.versions()
        return True, tuple((o, v) for o, v in after.items() if before.get(o) != v)

    def decode_stack(self, data: bytes) -> StackMessage | None:
        """Decode a received stack (counted); None, counted by error type, if it is invalid."""
        self.counters.stacks_received += 1
        self.counters.bytes_received += len(data)
        keys = None if self.signing is None else self.signing.keys
        try:
            message = decode(data, self.limits, keys, self._wants, self._parsed_before)
        except RemoteProtocolError as exc:
            self._count_error(exc)
            return None
        self.counters.slots_decoded += len(message.stack) - len(message.reused)
        self.counters.slots_skipped += len(message.skipped)
        self.counters.slots_reused += len(message.reused)
        self._keep_parsed(s for s in message.stack if s.owner not in message.reused)
        return message

    def _forget_parsed(self, message: StackMessage, owners: Container[str]) -> None:
        """Refused slots are not kept for reuse: whatever their size, nothing refused stays."""
        for s in message.stack:
            if s.owner in owners:
                self._parsed.pop((s.owner, s.epoch, s.stamp), None)

    def _parsed_before(self, owner: str, epoch: int, stamp: int) -> Slot | None:
        return self._parsed.get((owner, epoch, stamp))

    def _keep_parsed(self, slots: Iterable[Slot]) -> None:
        """Remember the slots just parsed until they are held or passed, so that another copy of
        the same bytes is not parsed again (a lock-step agent's buffered rounds hold them
        anyway). Bounded whatever arrives: roster owners only, at most ``2 × max_slots`` slots
        and one message's worth of bytes (``max_message_bytes``), the oldest forgotten first."""
        for s in slots:
            if s.wire is not None and (self.roster is None or s.owner in self.roster):
                self._parsed[(s.owner, s.epoch, s.stamp)] = s
        held = self.stack.versions()
        for key in [k for k in self._parsed if (k[1], k[2]) <= held.get(k[0], (-1, -1))]:
            del self._parsed[key]
        size = sum(len(s.wire.data) for s in self._parsed.values() if s.wire is not None)
        while self._parsed and (
            len(self._parsed) > 2 * self.limits.max_slots or size > self.limits.max_message_bytes
        ):
            _, gone = self._parsed.popitem(last=False)
            size -= len(gone.wire.data) if gone.wire is not None else 0

    def _wants(self, owner: str, epoch: int, stamp: int) -> bool:
        """Whether a received slot version can change anything here: newer than the version held
        (or, for the own slot, than the node's own (epoch, step)); the others are not parsed."""
        if owner == self.robot:
            return (epoch, stamp) > (self.epoch, self.k)
        return _wanted(self, owner, epoch, stamp)

    def merge(self, message: StackMessage) -> bool:
        """Merge a decoded stack (newest version per owner, never the own slot); True if it
        brought a newer slot."""
        epoch, evicted = self.epoch, self.counters.evicted_slots
        self._incoming_age = message.age
        merged = _merge_admitted(self, message.stack)
        if merged.versions() == self.stack.versions():
            if self.epoch != epoch:
                return True  # the stack moved the own epoch: a replay must see it again
            self.counters.stacks_unchanged += 1
            return False
        self.stack = merged
        self._encoded = None
        self.counters.stacks_merged += 1
        _drop_evicted(self, evicted)
        return True

    def _admitted(self, stack: Stack) -> list[Slot]:
        """The slots of a received stack this node may hold: owners in the roster, no more in all
        than a stack carries (the own stack always encodes; full: :func:`_evict_for`)."""
        held = self.stack.versions()
        room = self.keep_slots - len(held | {self.robot: (0, 0)})
        stamps = {s.owner: s.stamp for s in self.stack if s.owner != self.robot}
        out = []
        for s in stack:
            if s.owner == self.robot:
                self._check_own(s)
                continue
            if self.local_ids and self.distributed.association is None:
                self.counters.unassociated_slots += 1
                continue
            if self.roster is not None and s.owner not in self.roster:
                self.counters.foreign_slots += 1
                continue
            if s.owner not in held and room <= 0 and not _evict_for(self, s, held, stamps):
                self.counters.foreign_slots += 1
                continue
            if s.version <= held.get(s.owner, (-1, -1)):
                continue  # not newer: the merge keeps the version held
            if not self._fits(s):
                continue  # never held, so never relayed either
            if s.owner not in held:
                room -= 1
            stamps.pop(s.owner, None)  # taken: no longer one to evict for this stack's others
            out.append(s)
        return out

    def _check_own(self, slot: Slot) -> None:
        """A received version of the own slot newer than any this node made (its current
        version is (epoch, k)) was made by an earlier life of this robot that lost its journal,
        or forged on a fleet that does not sign: the node's slots move to an epoch above it, so
        that its peers take them again."""
        if slot.version <= (self.epoch, self.k) or slot.epoch >= MAX_EPOCH:
            return  # (no epoch above the largest; the agent core refuses such slots first)
        self.counters.own_superseded += 1
        self.epoch = slot.epoch + 1
        self._own_slot_stale = True
        self._encoded = None
        log.warning(
            "%s: peers hold a version (%d, %d) of its slot it never made: epoch now %d",
            self.robot,
            slot.epoch,
            slot.stamp,
            self.epoch,
        )

    def on_frame(
        self, frame: SensorFrame, fuse: bool = True, clock: Callable[[], float] | None = None
    ) -> StepReport:
        """One robot step: integrate changed slots into D, local step on L and on D, rebuild the
        own slot from L (never from D). If a slot could not be joined with D, D is rebuilt from L
        and every held slot once both have taken the step.

        ``fuse=False`` steps D without integrating the held slots (nor a due rebuild): the fusion
        is deferred to a later step, which integrates every slot still newer than D's version —
        as if those slots had come one step later (a shell that is behind its frames catches up
        this way; see ``agents.core``).

        ``clock`` (seconds, e.g. ``time.perf_counter``) times the phases for the report: the
        node itself reads no clock."""
        if frame.robot != self.robot:
            raise ValueError(f"node {self.robot} got a frame of {frame.robot}")
        tick = clock if clock is not None else _no_clock
        if frame.ids != GLOBAL_IDS and not self.local_ids:
            self.local_ids = _local_ids(self)
        t0 = tick()
        fusion = (
            self.integrate_pending()
            if fuse
            else FusionStats((), (), 0, len(self.distributed.hypotheses))
        )
        t1 = tick()
        stepped = self.track.advance(frame, clock, self.distributed)
        t2 = tick()
        d_frames, d_replay = self.without_ids.for_d(self.track, self.distributed, frame, stepped)
        self.distributed.step(d_frames, self._rng_distributed, d_replay)
        if fuse and self.without_ids.rematch_due(self.track, stepped):
            held = self._checked(self.stack.newer_than({}, own=self.robot))
            self._rebuild_due |= self.without_ids.rematch(self.distributed, held)
        if self._rebuild_due and fuse:
            rebuilt = self.rebuild()
            fusion = replace(
                fusion, empty_joins=fusion.empty_joins + rebuilt.empty_joins, rebuilds=1
            )
        self.k = frame.k
        self._changed()
        self.position = self._checked_position()
        # The own slot is rebuilt from L lazily, when a stack is next needed.
        self._own_slot_stale = True
        self._encoded = None
        return StepReport(frame.k, fusion, t1 - t0, t2 - t1, tick() - t2)

    def _checked_position(self) -> tuple[float, float]:
        """D's estimated position, once L and D are checked to be distributions still."""
        for name, belief in (("L", self.local), ("D", self.distributed)):
            log_w = np.array([h.log_weight for h in belief.hypotheses])
            if not (len(log_w) and np.isfinite(log_w).all()):
                raise BeliefError(f"{self.robot}: {name} has non-finite hypothesis weights")
            if belief.per_object and not np.isfinite(belief.class_log_posterior()).all():
                raise BeliefError(f"{self.robot}: {name} has non-finite class evidence")
            position = belief.position(self.robot)
            if not all(np.isfinite(position)):
                raise BeliefError(f"{self.robot}: {name} has a non-finite robot pose")
        return position

    def integrate_pending(self) -> FusionStats:
        """Integrate into D every slot of the stack newer than the version D used (also done by
        ``on_frame``; shells call it first to time the fusion on its own).

        A slot whose join with D is empty (D pruned a class combination the slot needs) is counted
        and makes the next ``on_frame`` rebuild D, so that no peer's information is lost.
        """
        incoming = self._checked(self.stack.newer_than(self.distributed.versions, own=self.robot))
        # D is stepped right after (on_frame), which updates iSAM2 again: no settling here.
        stats = self.distributed.integrate(incoming, settle=False)
        self._changed()
        d = self.distributed
        if (stats.empty_joins and d.fusion == "consistent") or d.orphans():  # rebuilt later
            self._rebuild_due = True
        self.counters.empty_joins += stats.empty_joins
        self.counters.completed_joins += stats.completed
        return stats

    def rebuild(self) -> FusionStats:
        """Make D anew from L and the newest held version of every other robot's slot (L and D
        must be at the same step)."""
        held = self._checked(self.stack.newer_than({}, own=self.robot))
        stats = self.distributed.rebuild(self.local, held)
        self.without_ids.rebuilt()
        self._changed()
        self._rebuild_due = False
        self.counters.empty_joins += stats.empty_joins
        self.counters.rebuilds += stats.rebuilds
        self.counters.completed_joins += stats.completed
        if stats.skipped:
            log.warning(
                "%s: slots of %s join with no hypothesis of D even after a rebuild",
                self.robot,
                ", ".join(stats.skipped),
            )
        return stats

    def _checked(self, slots: Iterable[Slot]) -> list[Slot]:
        """The slots that fit D's model; the others are counted and logged."""
        return [slot for slot in slots if self._fits(slot)]

    def _fits(self, slot: Slot) -> bool:
        try:
            self.distributed.check(slot)
        except SlotError as exc:
            self.counters.rejected_slots += 1
            self.counters.last_error = str(exc)
            self._parsed.pop((slot.owner, slot.epoch, slot.stamp), None)
            log.warning("%s: rejected slot: %s", self.robot, exc)
            return False
        return True

    def _count_error(self, exc: RemoteProtocolError) -> None:
        self._last_refusal = exc.with_traceback(None)  # its frames would hold the payload
        name = type(exc).__name__
        self.counters.invalid += 1
        self.counters.errors_by_type[name] = self.counters.errors_by_type.get(name, 0) + 1
        self.counters.last_error = str(exc)

    # -- output ------------------------------------------------------------------------------

    def current_stack(self) -> Stack:
        """The stack with the own slot rebuilt from L (never from D) at the latest step."""
        if self._own_slot_stale:
            refused = self.local.slot_fit_refused
            summary = self.track.summary(linearisation_point(self.distributed))
            if self.local.slot_fit_refused > refused:
                _log_fit_refused(self)
            if summary is not None and not (self.local_ids and not self.distributed.association):
                stated = summary.robot_local() if self.local_ids else summary
                own = Slot(self.robot, self.k, stated, self.epoch)
                self.stack = self.stack.with_slot(self._encoded_once(own))
            self._own_slot_stale = False
        return self.stack

    def _encoded_once(self, slot: Slot) -> Slot:
        """The own slot, signed when the fleet signs its slots, with its bytes made once for
        every stack that carries it until the next step (left as it is if the limits refuse it:
        ``encoded_stack`` then leaves it out and counts it)."""
        try:
            if self.signing is None:
                return with_wire(slot, self.limits)
            return sign_slot(slot, self.signing.key, self.limits)
        except LocalProtocolError:
            return slot

    def reject(self, exc: RemoteProtocolError) -> None:
        """Count a received stack refused by the shell (e.g. a sender that is not its key's)."""
        self._count_error(exc)

    def outgoing(self) -> bytes | None:
        """The encoded stack to gossip, or None while the node has nothing to share."""
        if len(self.current_stack()) == 0:
            return None
        return self.encoded_stack()

    def encoded_stack(self) -> bytes:
        """The encoded stack, even when empty (a lock-step agent still announces its round),
        under the node's own limits: what its peers would refuse is never sent. Only the own slot
        and position can break them (every held slot passed the same limits on the way in): then
        they are left out, counted in ``own_slot_invalid``, and the rest still goes out."""
        stack = self.current_stack()
        if self._encoded is None:
            self._encoded = _encoded_message(self, stack, None)
        return self._encoded

    def encoded_delta(
        self, owners: Collection[str], ask: Mapping[str, str] | None = None, aged: bool = False
    ) -> bytes:
        """A delta stack (docs/wire.md, "Delta gossip"): the held slots of ``owners`` only — what
        some peer lacks — the digest of every version held (``have``) and ``ask`` (owner → the
        relay asked to push its versions; None or empty: none); ``aged``: with an ``age`` of 0
        for each slot, for the sender to stamp (``protocol.codec.stamp_ages``; none if no slot).
        The own slot is left out, and counted, when the limits refuse it, as in
        :meth:`encoded_stack` (and the stack then says no ages)."""
        stack = self.current_stack()
        chosen = tuple(s for s in stack if s.owner in owners)
        # The same delta is asked for again and again (after every batch of messages, for the
        # digest and for what peers lack) while the stack, step and position stay: its bytes are
        # kept until one of them changes (a deterministic encoding of the same message).
        at = (stack, self.k, self.position)
        if self._deltas_at != at or len(self._deltas) >= 8:
            self._deltas_at, self._deltas = at, {}
        asks = dict(ask) if ask else None
        aged = aged and bool(chosen)
        key = (tuple(s.owner for s in chosen), tuple(sorted(asks.items())) if asks else (), aged)
        known = self._deltas.get(key)
        if known is not None:
            return known
        data = _encoded_message(self, Stack(chosen), (stack.versions(), asks), aged)
        self._deltas[key] = data
        return data

    def mark_sent(self, size: int) -> None:
        """Tell the node a stack of ``size`` bytes went out (for its counters)."""
        self.counters.stacks_sent += 1
        self.counters.bytes_sent += size


def _encoded_message(
    node: RobotNode,
    stack: Stack,
    delta: tuple[dict[str, tuple[int, int]], dict[str, str] | None] | None,
    aged: bool = False,
) -> bytes:
    """``stack`` (with ``delta``'s digest and asks; ``aged``: ages 0 to be stamped) under the
    node's limits, with D's position; if they refuse that, with L's position, so that the own
    slot, built from L, never depends on D; failing that, without the own slot, position and
    ages (counted in ``own_slot_invalid``)."""
    have, asks = delta if delta is not None else (None, None)
    age = {s.owner: 0 for s in stack} if aged else None
    try:
        position = node.position
        message = StackMessage(node.robot, position, stack, node.k, have=have, ask=asks, age=age)
        return encode(message, node.limits)
    except LocalProtocolError as exc:
        error = exc
    if node.position is not None:
        local = node.local.position(node.robot)
        try:
            message = StackMessage(node.robot, local, stack, node.k, have=have, ask=asks, age=age)
            return encode(message, node.limits)
        except LocalProtocolError as exc:
            error = exc
    node.counters.own_slot_invalid += 1
    node.counters.last_error = str(error)
    log.error("%s: own slot or position not sendable: %s", node.robot, error)
    others = Stack(tuple(s for s in stack if s.owner != node.robot))
    return encode(StackMessage(node.robot, None, others, node.k, have=have, ask=asks), node.limits)


def _evict_for(
    node: RobotNode, slot: Slot, held: dict[str, tuple[int, int]], stamps: dict[str, int]
) -> bool:
    """The neighbourhood bound (docs/distributed.md, "How many robots a D holds"), when
    ``node``'s stack is full: drop the stalest slot of ``stamps`` (owner → stamp of the held
    slots not taken from the stack being admitted) from the stack, ``held`` and ``stamps`` if
    ``slot`` is fresher and fits D's model; whether one was dropped (``evicted_slots``); D lets
    go in batches (:func:`_drop_evicted`).

    Fresher by holding times when the agent core gives the ages of the held slots and the stack
    said the new slot's (real time, ask gossip: ``agents.ages``): the held slot whose information
    is oldest goes for one at least ``age_margin_ms`` younger — so a robot lets go of those it no
    longer hears of, whatever step they are at (robots that started later have lower stamps).
    Otherwise by stamp, the owner's step when it made the slot: relayed one hop per step (the
    in-process fleet, lock-step), a slot's age is its owner's distance in hops, so a robot keeps
    the ``keep_slots − 1`` nearest robots it hears of; stamps are compared across owners, which
    holds for the robots of one fleet stepping together."""
    if not stamps:
        return False
    said = node._incoming_age.get(slot.owner) if node._incoming_age is not None else None
    ages = node.slot_ages(stamps) if node.slot_ages is not None and said is not None else {}
    if said is not None and len(ages) == len(stamps):
        stalest = max(stamps, key=lambda o: (ages[o], o))
        fresher = ages[stalest] - said > node.age_margin_ms
    else:
        stalest = min(stamps, key=lambda o: (stamps[o], o))
        fresher = slot.stamp > stamps[stalest]
    if not fresher or not node._fits(slot):
        return False
    node.stack = Stack(tuple(s for s in node.stack if s.owner != stalest))
    del stamps[stalest], held[stalest]
    node._encoded = None
    node.counters.evicted_slots += 1
    return True


def _wanted(node: RobotNode, owner: str, epoch: int, stamp: int) -> bool:
    """Whether a slot version of another robot can change ``node``: newer than the version held;
    of an owner not held, if the stack has room or ``stamp`` is fresher than the stalest held
    slot's (:func:`_evict_for`). Those that cannot are left unparsed."""
    held = node.stack.version_of(owner)
    if held is not None:
        return (epoch, stamp) > held
    if node.slot_ages is not None:
        return True  # by holding times, which come after the slots: admission decides
    others = [s.stamp for s in node.stack if s.owner != node.robot]
    return len(others) + 1 < node.keep_slots or stamp > min(others, default=stamp)


def _merge_admitted(node: RobotNode, stack: Stack) -> Stack:
    """``node``'s stack merged with what it admits of ``stack`` (admitting may evict)."""
    admitted = node._admitted(stack)
    return node.stack.merge(admitted, own=node.robot)


def _drop_evicted(node: RobotNode, evicted_before: int) -> None:
    """D keeps the last version it fused of an owner evicted from the stack (still one slot per
    robot, so nothing is counted twice: a later version of the owner replaces it) until it
    keeps as many such owners as the stack holds peers; then one rebuild, at the next step,
    drops them all. A rebuild per eviction made D's step 4.2× slower at N = 100 than at N = 25
    (2,720 rebuilds in 4,000 robot steps; docs/distributed.md). ``evicted_before``: the
    node's ``evicted_slots`` before the stack just merged (none evicted since: nothing to do)."""
    if node.counters.evicted_slots == evicted_before:
        return
    held = node.stack.versions()
    dropped = sum(owner not in held for owner in node.distributed.versions)
    if dropped >= node.keep_slots - 1:
        node._rebuild_due = True


def gated(
    node: RobotNode, message: StackMessage
) -> tuple[StackMessage | None, dict[str, Implausible]]:
    """``message`` without the slots the belief gate refuses (None: the sender's own is
    among them, and the stack is refused whole), and those refusals, counted."""
    bad = node.gate.refused(message, node.robot, node.stack, node.distributed)
    if not bad:
        return message, bad
    node._forget_parsed(message, bad)
    node.counters.rejected_slots += len(bad)
    node.counters.last_error = str(next(iter(bad.values())))
    if message.sender in bad:
        return None, bad
    return _without(message, lambda s: s.owner in bad)[0], bad


def admits_round(node: RobotNode, message: StackMessage) -> bool:
    """Whether the belief gate hears ``message``'s sender now: its own slot, if new, is
    plausible against D (counted nowhere: :meth:`RobotNode.merge_round` counts)."""
    return message.sender not in node.gate.refused(
        message, node.robot, node.stack, node.distributed
    )


def refuse_round(node: RobotNode, message: StackMessage) -> Received:
    """A copy of a round stack its step does not merge (another copy of the sender's was
    merged, or none was heard): what the belief gate refuses of it, counted."""
    _, bad = gated(node, message)
    error = bad.get(message.sender) or next(iter(bad.values()), None)
    return Received(None, gated=len(bad), error=error)
