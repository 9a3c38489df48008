"""Adversarial chaos (``semfleet chaos --attack``): hostile Zenoh sessions against a running fleet,
and the evidence of what each attack achieved.

An attack run is a lock-step launch, so that its estimates can be compared bit for bit with the
clean run (the in-process runner, which a clean lock-step launch equals). The attackers act
between the rounds, ahead of the fleet: after step k they publish what a fleet member would only
publish during the rounds k+1…k+``AHEAD`` (a lock-step agent keeps the *first* stack of each
round and the first frame of each step), so an attack that is let in always wins its race.

The attacks, against the *victim* (the robot the others hear most in the run, :func:`roles`):

- ``impersonate`` — stacks on the victim's key, sent as the victim, whose victim slot is forged
  (a newer version carrying the object :data:`FORGED_OBJECTS` ["impersonate"]);
- ``stamp`` — a forged victim slot far ahead of its real version (the largest stamp the owner's
  clock allows under its current epoch), relayed on the *accomplice*'s key (the next most heard
  robot);
- ``epoch`` — the victim's genuine newest slot, its signature kept, under the next epoch
  (finding 8 of issue 43): on a secure fleet its signature no longer verifies, and the agents
  count it as badly signed; on an insecure one the victim has to move to a newer epoch;
- ``stop`` (``member-stop``) — ``ctl/stop`` two steps before the end (a member: on its own
  ``ctl/need`` key too);
- ``frames`` — sensor frames for the victim's next steps: no motion, and an object that is not
  there;
- ``garbage`` — malformed stacks (:func:`deploy.launch.chaos.garbage_stack`) on the victim's and
  the accomplice's keys;
- ``poison`` (``member-poison``) — the accomplice's own slot, ahead of its real versions, over
  the objects the victim holds: each moved :data:`POISON_SHIFT` m in x with information
  :data:`POISON_INFORMATION`·I (the wire's cap), within every wire limit. A member signs it with
  its own key: finding 2 of issue 43, which wrecked every receiver's D before the belief gate
  (``estimator.gate``);
- ``bloat`` — the accomplice's own slot at its next stamp with :data:`BLOAT_OBJECTS` objects
  and a dense ξ, 9.4 MB within every wire limit, once a step; a member signs it (finding 4 of
  issue 43: two such slots kept hundreds of MB in every victim). Agents refuse it unread, by
  its size (``stacks_invalid``), where they once decoded it before refusing it;
- ``flood`` (``status-flood``) — :data:`FLOOD_PER_STEP` status requests on ``ctl/status`` (and
  :data:`FLOOD_LARGE` control messages of 1 MiB) and requests on as many distinct
  ``ctl/need/<id>`` keys after every step; a member also sends status requests and
  round requests naming every robot on its own ``ctl/need`` key (finding 3 of issue 43: 2,000
  status requests a second made every agent publish as many estimates).

A session that holds the accomplice's certificate and signing key (a member's credentials used
against another member) also tries everything through what its own certificate allows: forged
victim slots on its own stack key, signed with its own key. Evidence of success is read off the
estimates: a forged object in anyone's belief, a victim that had to move to a new epoch
(``own_superseded``), agents that stopped before the run's end, estimates that differ from the
clean run's.

Over 300 lines for a reason: each attack is a few lines of one ``Attacker`` that observes the
fleet as it goes, and its evidence is read off the estimates by the functions below it; the
attacks and what counts as their success belong side by side.
"""

from __future__ import annotations

import asyncio
import random
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from agents.control import NeedFrames, NeedRound, Status, Stop, encode_control
from agents.node import CLOCK_SKEW_S, MAX_STEP_RATE, STAMP_SLACK
from agents.transport.base import Inbox, Keys
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport
from deploy.launch.chaos import forged_summary, garbage_stack
from estimator.hybrid import BeliefConfig
from estimator.models import MAX_STEP, Detection, SensorFrame
from estimator.summary import LocalSummary, ObjectClasses, Realisation
from estimator.xi import Xi
from protocol.codec import StackMessage, decode, encode, sign_slot
from protocol.errors import RemoteProtocolError
from protocol.frames import encode_frame
from protocol.stack import Slot, Stack

ATTACKS = (
    "impersonate",
    "stamp",
    "epoch",
    "stop",
    "frames",
    "garbage",
    "poison",
    "bloat",
    "flood",
)
# Issue 43's names for the member's attacks: each attack already runs as an uncertified session
# and, on a secure fleet, as a member (the accomplice's certificate and signing key).
ALIASES = {"member-stop": "stop", "member-poison": "poison", "status-flood": "flood"}
# Object ids no world has: one in a belief can only have come from that attack.
FORGED_OBJECTS = {"impersonate": 900_001, "stamp": 900_002, "frames": 900_003}
FORGED = frozenset(FORGED_OBJECTS.values())
AHEAD = 3  # rounds and steps forged ahead of the fleet
GARBAGE_PER_STEP = 20
POISON_SHIFT = 9000.0  # metres: inside the wire's ±world_extent of 10 km
POISON_INFORMATION = 1e9  # Limits.max_information
FLOOD_PER_STEP = 300
FLOOD_LARGE, FLOOD_LARGE_BYTES = 4, 1 << 20  # control messages of 1 MiB, each step
BLOAT_OBJECTS = 512  # Limits.max_objects: a dense ξ of 9.4 MB on the wire
POISONED = 1000.0  # an object estimate this far (m) from the origin can only be the poison


def parse_attacks(text: str) -> tuple[str, ...]:
    """``impersonate,stamp`` → the attacks, in :data:`ATTACKS` order (:data:`ALIASES` name
    some of them too); ``all`` → every attack. Raises ValueError naming an unknown one."""
    if text == "all":
        return ATTACKS
    names = [ALIASES.get(a, a) for a in text.split(",") if a]
    unknown = [a for a in names if a not in ATTACKS]
    if unknown or not names:
        known = ", ".join((*ATTACKS, *ALIASES))
        raise ValueError(f"unknown attacks {unknown} (known: {known}, or all)")
    return tuple(a for a in ATTACKS if a in names)


@dataclass(frozen=True, slots=True)
class Identity:
    """Who an attacker is: ``label`` for the report, the Zenoh ``settings`` of its session, and
    the robot whose credentials it holds (``robot``, ``signing_key``), if any."""

    label: str
    settings: ZenohSettings
    robot: str | None = None
    signing_key: Ed25519PrivateKey | None = None


@dataclass(slots=True)
class Attacker:
    """One hostile session running ``attacks`` against ``victim`` of ``robots``."""

    identity: Identity
    attacks: tuple[str, ...]
    keys: Keys
    robots: Sequence[str]
    victim: str
    accomplice: str  # whose stack key the relayed forgeries travel on
    num_classes: int
    steps: int
    seed: int = 0
    # The fleet's class representation: a forged slot is of the kind the victims fuse.
    classes: str = BeliefConfig().classes
    sent: Counter[str] = field(default_factory=Counter)
    error: str = ""  # why the session could not open, if it could not
    transport: ZenohTransport | None = None
    tokens: Inbox = field(default_factory=lambda: Inbox(10_000))
    stacks: Inbox = field(default_factory=lambda: Inbox(1_000))
    seen_alive: set[str] = field(default_factory=set)
    versions: dict[str, tuple[int, int]] = field(default_factory=dict)
    # The objects of the victim's newest slot overheard: ids and linearisation poses.
    victim_objects: tuple[tuple[int, ...], np.ndarray] | None = None
    victim_slot: Slot | None = None  # the newest genuine one overheard, as signed

    async def open(self) -> None:
        transport = ZenohTransport(self.identity.settings)
        transport.watch_alive(self.keys.alive("*"), self.tokens)
        transport.subscribe(self.keys.stack("*"), self.stacks)
        try:
            await transport.open()
        except Exception as exc:  # a refused session is a result, not a failure of the run
            self.error = f"{type(exc).__name__}: {exc}"
            return
        self.transport = transport

    async def close(self) -> None:
        if self.transport is not None:
            await self.transport.close()

    def _observe(self) -> None:
        """Tokens seen, and the newest version of every robot's slot the session overheard."""
        for message in self.tokens.drain():
            robot = message.key.rsplit("/", 1)[-1]
            if robot in self.robots:
                self.seen_alive.add(robot)
        for message in self.stacks.drain():
            try:
                stack = decode(message.payload).stack
            except RemoteProtocolError:
                continue
            for slot in stack:
                if set(slot.summary.object_ids) & FORGED:
                    continue  # its own forgery, delivered back to its own subscriber
                if slot.version > self.versions.get(slot.owner, (-1, -1)):
                    self.versions[slot.owner] = slot.version
                    if slot.owner == self.victim:
                        self.victim_slot = slot
                        summary = slot.summary
                        po = summary.per_object
                        xi = po.xi if po is not None else summary.distinct_xi()[0][0]
                        self.victim_objects = (summary.object_ids, np.array(xi.lin))

    def on_step(self, k: int) -> None:
        """After the fleet's step ``k``: the forgeries for rounds and steps k+1…k+AHEAD."""
        if self.transport is None:
            return
        self._observe()
        for attack in self.attacks:
            for key, payload in getattr(self, f"_{attack}")(k):
                self.transport.publish(key, payload)
                self.sent[attack] += 1

    # -- the attacks -------------------------------------------------------------------------

    def _impersonate(self, k: int) -> list[tuple[str, bytes]]:
        epoch, stamp = self.versions.get(self.victim, (0, k))
        out = []
        for j in range(k + 1, k + 1 + AHEAD):
            slot = self._forged("impersonate", epoch, min(max(stamp, j) + 1, MAX_STEP))
            out.append((self.keys.stack(self.victim), self._stack(self.victim, slot, j)))
            if self.identity.robot is not None:
                out.append(
                    (self.keys.stack(self.accomplice), self._stack(self.accomplice, slot, j))
                )
        return out

    def _stamp(self, k: int) -> list[tuple[str, bytes]]:
        epoch, _ = self.versions.get(self.victim, (0, k))
        now_ms = 1000 * time.time()  # the receivers' bound, minus a second of margin
        ceiling = MAX_STEP_RATE * (now_ms + 1000 * (CLOCK_SKEW_S - 1) - epoch) / 1000
        slot = self._forged("stamp", epoch, int(min(ceiling + STAMP_SLACK, MAX_STEP)))
        return [
            (self.keys.stack(self.accomplice), self._stack(self.accomplice, slot, j))
            for j in range(k + 1, k + 1 + AHEAD)
        ]

    def _epoch(self, k: int) -> list[tuple[str, bytes]]:
        if self.victim_slot is None:
            return []
        slot = self.victim_slot
        moved = Slot(slot.owner, slot.stamp, slot.summary, slot.epoch + 1, slot.signature)
        return [
            (self.keys.stack(self.accomplice), self._stack(self.accomplice, moved, j))
            for j in range(k + 1, k + 1 + AHEAD)
        ]

    def _stop(self, k: int) -> list[tuple[str, bytes]]:
        if k != self.steps - 2:  # two steps early: every agent hears it before the last one
            return []
        keys = [self.keys.ctl("stop")]  # and a member on the one control key it may put on
        keys += [self.keys.ctl("need", self.identity.robot)] if self.identity.robot else []
        return [(key, encode_control(Stop("attack"))) for key in keys]

    def _frames(self, k: int) -> list[tuple[str, bytes]]:
        scores = np.zeros(self.num_classes)
        scores[0] = 1.0
        ghost = Detection(FORGED_OBJECTS["frames"], np.array([1.0, 0.0, 0.0]), scores)
        return [
            (
                self.keys.frames(self.victim),
                encode_frame(
                    SensorFrame(self.victim, j, np.zeros(3), (ghost,), np.full(3, np.nan))
                ),
            )
            for j in range(k + 1, k + 1 + AHEAD)
        ]

    def _garbage(self, k: int) -> list[tuple[str, bytes]]:
        rng = random.Random(self.seed * 1_000_003 + k)
        targets = (self.keys.stack(self.victim), self.keys.stack(self.accomplice))
        return [(targets[i % 2], garbage_stack(rng)) for i in range(GARBAGE_PER_STEP)]

    def _poison(self, k: int) -> list[tuple[str, bytes]]:
        if self.victim_objects is None:
            return []
        owner = self.identity.robot or self.accomplice  # a member: its own slot, its own key
        ids, lin = self.victim_objects
        n = len(ids)
        shifted = lin + np.array([POISON_SHIFT, 0.0, 0.0])
        xi = Xi(shifted, POISON_INFORMATION * np.eye(3 * n), np.zeros(3 * n))
        if self.classes == "per_object":
            summary = LocalSummary(ids, (), ObjectClasses(np.zeros((n, self.num_classes)), xi))
        else:
            summary = LocalSummary(ids, (Realisation((0,) * n, 0.0, xi),))
        epoch, stamp = self.versions.get(owner, (0, k))
        out = []
        for j in range(k + 1, k + 1 + AHEAD):
            slot = Slot(owner, min(max(stamp, j) + 1, MAX_STEP), summary, epoch)
            if self.identity.signing_key is not None:
                slot = sign_slot(slot, self.identity.signing_key)
            out.append((self.keys.stack(owner), self._stack(owner, slot, j)))
        return out

    def _bloat(self, k: int) -> list[tuple[str, bytes]]:
        owner = self.identity.robot or self.accomplice
        n = BLOAT_OBJECTS
        lin = np.tile([1.0, 1.0, 0.0], (n, 1))
        xi = Xi(lin, 1e6 * np.eye(3 * n), np.zeros(3 * n))
        summary = LocalSummary(
            tuple(range(800_000, 800_000 + n)),
            (),
            ObjectClasses(np.zeros((n, self.num_classes)), xi),
        )
        epoch, stamp = self.versions.get(owner, (0, k))
        slot = Slot(owner, min(max(stamp, k) + 1, MAX_STEP), summary, epoch)
        if self.identity.signing_key is not None:
            slot = sign_slot(slot, self.identity.signing_key)
        return [(self.keys.stack(owner), self._stack(owner, slot, k + 1))]

    def _flood(self, k: int) -> list[tuple[str, bytes]]:
        status = encode_control(Status())
        out = [(self.keys.ctl("status"), status)] * FLOOD_PER_STEP
        out += [(self.keys.ctl("status"), bytes(FLOOD_LARGE_BYTES))] * FLOOD_LARGE  # finding 6
        out += [
            (self.keys.ctl("need", f"x{i}"), encode_control(NeedFrames(f"x{i}", k)))
            for i in range(FLOOD_PER_STEP)
        ]
        if self.identity.robot is not None:  # a member: on the one control key it may put on
            own = self.keys.ctl("need", self.identity.robot)
            rounds = encode_control(NeedRound(self.identity.robot, k, tuple(self.robots)))
            out += [(own, status), (own, rounds)] * (FLOOD_PER_STEP // 2)
        return out

    def _forged(self, attack: str, epoch: int, stamp: int) -> Slot:
        """A victim slot the victim never made: one object of class 0 that is not there."""
        summary = forged_summary(FORGED_OBJECTS[attack], self.num_classes, self.classes)
        slot = Slot(self.victim, stamp, summary, epoch)
        if self.identity.signing_key is not None:  # signed — by the wrong key
            slot = sign_slot(slot, self.identity.signing_key)
        return slot

    def _stack(self, sender: str, slot: Slot, step: int) -> bytes:
        return encode(StackMessage(sender, None, Stack((slot,)), step))


def roles(links: Sequence[Mapping[str, Sequence[str]]], robots: Sequence[str]) -> tuple[str, str]:
    """(victim, accomplice) from the run's lock-step links (one receiver → senders map per
    step): the robot most heard by the others, and the most heard of the rest — the two whose
    stacks an attack on gossip can reach anyone through (ties: roster order)."""
    heard = Counter(s for step in links for senders in step.values() for s in senders)
    ranked = sorted(robots, key=lambda r: (-heard[r], robots.index(r)))
    return ranked[0], ranked[1]


async def open_all(attackers: Sequence[Attacker], settle_s: float = 1.0) -> None:
    """Open every attacker's session; give them ``settle_s`` to see the fleet's tokens."""
    for a in attackers:
        await a.open()
    await asyncio.sleep(settle_s)
    for a in attackers:
        a._observe()


# -- evidence --------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Achieved:
    """What one attack achieved in one run: ``effects`` (empty: nothing), and what the agents
    counted of it."""

    attack: str
    effects: tuple[str, ...]
    counted: str


def forged_objects_seen(
    estimates: Mapping[tuple[str, int], object],
) -> dict[str, set[tuple[str, str]]]:
    """attack → {(robot, belief)} whose estimate at any step held that attack's forged object."""
    seen: dict[str, set[tuple[str, str]]] = {a: set() for a in FORGED_OBJECTS}
    for (robot, _k), est in estimates.items():
        for belief, snap in est.beliefs.items():  # type: ignore[attr-defined]
            for attack, obj in FORGED_OBJECTS.items():
                if obj in snap.object_ids:
                    seen[attack].add((robot, belief))
    return seen


def poisoned_beliefs(estimates: Mapping[tuple[str, int], object]) -> set[tuple[str, str]]:
    """{(robot, belief)} whose estimate at any step held an object more than :data:`POISONED`
    metres from the origin: only the ``poison`` attack puts one there."""
    out = set()
    for (robot, _k), est in estimates.items():
        for belief, snap in est.beliefs.items():  # type: ignore[attr-defined]
            pose = np.asarray(snap.object_pose)
            if pose.size and float(np.abs(pose[..., :2]).max()) > POISONED:
                out.add((robot, belief))
    return out


def evidence(
    attacks: Sequence[str],
    estimates: Mapping[tuple[str, int], object],
    counters: Mapping[str, Mapping[str, int]],
    last_step: Mapping[str, int],
    steps: int,
    stopped_early: Sequence[str],
    victim: str,
) -> list[Achieved]:
    """Per attack: its effects on the fleet (see the module docstring) and the agents' counts."""
    seen = forged_objects_seen(estimates)
    total = Counter[str]()
    for c in counters.values():
        total.update({k: int(v) for k, v in c.items() if isinstance(v, int)})
    out = []
    for attack in attacks:
        effects: list[str] = []
        if seen.get(attack):
            who = ", ".join(f"{r} {b[0].upper()}" for r, b in sorted(seen[attack]))
            effects.append(f"forged object in {who}")
        if attack in ("stamp", "epoch") and counters.get(victim, {}).get("own_superseded", 0):
            effects.append(f"{victim} had to move to a new epoch")
        if attack == "poison" and (hit := poisoned_beliefs(estimates)):
            who = ", ".join(f"{r} {b[0].upper()}" for r, b in sorted(hit))
            effects.append(f"objects {POISON_SHIFT / 1000:g} km away in {who}")
        if attack == "flood":
            answered = {r: int(c.get("estimates_sent", 0)) for r, c in counters.items()}
            # Answered: more than two estimates a step plus one for every tenth flood request.
            bound = 2 * steps + FLOOD_PER_STEP * steps // 10
            loud = sorted(r for r, n in answered.items() if n > bound)
            if loud:
                most = max(answered[r] for r in loud)
                effects.append(f"{', '.join(loud)} answered it: up to {most} estimates")
        if attack == "stop" and stopped_early:
            effects.append(f"stopped {', '.join(stopped_early)} before step {steps}")
        counted = {
            "impersonate": ("stacks_badly_signed", "stacks_misaddressed", "slots_implausible"),
            "stamp": ("stacks_badly_signed", "slots_implausible"),
            "epoch": ("stacks_badly_signed",),
            "stop": ("control_invalid",),
            "frames": ("frames_invalid",),
            "garbage": ("stacks_invalid",),
            "poison": ("slots_rejected",),
            "bloat": ("stacks_invalid", "slots_rejected"),
            "flood": ("status_requests", "control_invalid", "inbox_dropped"),
        }[attack]
        text = ", ".join(f"{name} {total[name]}" for name in counted if total[name])
        out.append(Achieved(attack, tuple(effects), text or "—"))
    return out


def write_attacker_config(path: Path, doc: Mapping[str, object]) -> Path:
    """A JSON5 (plain JSON) Zenoh config for an attacker session."""
    import json

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    return path
