"""DeltaGossip: what one robot sends of its stack, to whom and when (docs/wire.md, "Delta gossip"
and "Asks"), without any I/O.

A peer's stack carries its digest (``have``: the version it holds of every owner) and its asks
(owner → the relay it asks to push that owner's versions). From them this policy keeps, per peer,
what it holds and when that was heard; per held owner, when its version came here and when it was
last sent; the versions peers showed that this robot lacks; and the relays this robot asks. It
answers: which held slots go with the next stack (:meth:`DeltaGossip.select`), which asks the
next stack carries (:meth:`current_asks`), when a tick must pull (:meth:`pull_at`) and whether a
tick with nothing new sends the digest alone (:meth:`tick`).

It sees digests, versions, senders and times, nothing else: no node, codec or journal. The
agent core (``agents.core``) feeds it what arrived and encodes what it chose. Everything it
keeps is bounded by ``max_slots`` peers or owners, and with a roster it keeps roster robots only.

Lock-step (``strict``): a slot goes to every round while some roster peer lacks it by its
latest digest (a peer not heard yet lacks everything), so that each round merges exactly what a
full stack would bring; no asks, no digest alone. Real time: a slot goes to a peer whose digest
lacks it only once that peer had its chance — a digest that came a gossip period after the slot
came here (from its owner, whom the peer may hear itself) and after this robot last sent it; the
own slot's new version goes at once. A slot a peer asked this robot for goes on arrival (``relay
= "event"``, the default): at once, unless a stack went less than ``PUSH_WINDOW_S`` ago — then
when that window ends (:attr:`Outgoing.flush_at`), with whatever else came meanwhile — so that a
version crosses each hop in the time of a transit and a merge, not of a gossip period; with
``relay = "tick"`` (before issue 47) it waits for the next tick. The ticks stay, as the
anti-entropy repair: they re-send what a digest shows a peer still lacks.

Threading: :meth:`tick`, :meth:`digest_due` and :meth:`flush` run on the shell's loop and touch
only ``tick_last``, ``digest_sent``, ``digests_skipped``, ``flushes`` and ``pushed_at`` (the one
field both sides write: a lost race sends one stack more); everything else runs on the worker.

Over 300 lines for a reason: the selection, the asks, the pulls and the ticks read and bound the
same per-peer and per-owner tables; split, each table's bound would be kept in two places.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace

from agents.ages import Aging, stamped_ages
from protocol.codec import stamp_ages

Version = tuple[int, int]  # (epoch, stamp) of one owner's slot
Sent = tuple[bytes, frozenset[str]]  # bytes to publish, and the peers they go to (none: all)
NONE: Version = (-1, -1)  # older than any version

DIGEST_LIFE = 3  # gossip periods a peer's digest counts for (real time): then it is out of reach
# Real time: a tick sends an unchanged digest alone only this many gossip periods after the last
# (under DIGEST_LIFE, so that peers keep counting this robot), unless a peer's digest since then
# holds a version this robot lacks (docs/wire.md, "Delta gossip").
DIGEST_REFRESH = 2
# Event-driven relay: at most one stack per this window (s) goes for asked slots alone, so that
# versions arriving in a burst (a fleet's robots step together) leave in one stack, not one each.
# 5 ms: well under the 10 ms a hop may take (issue 47). A longer one buys few messages: on the
# 20-robot capacity world (seed 11, 20 steps) windows of 5, 20 and 50 ms pushed 56, 54 and 43
# stacks per agent — asked versions come spread over the step, not in bursts.
PUSH_WINDOW_S = 0.005
RELAYS = ("event", "tick")


@dataclass(frozen=True, slots=True)
class Outgoing:
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
    # Event-driven relay: when the shell flushes ``stack`` (asked slots held back by the push
    # window, :meth:`DeltaGossip.flush`; inf: nothing held back).
    flush_at: float = math.inf
    # Holding times (``agents.ages``): per slot of ``stack``, the age it came with and since
    # when it is held, for the ages it says when it goes (None: ``stack`` says none).
    aging: Aging | None = None
    # Event-driven relay: the peers whose asks alone put slots in ``stack`` (a push goes to them
    # alone, ``Keys.stack_to``); empty: it goes to every robot in range.
    push_to: frozenset[str] = frozenset()

    def sent_at(self, now: float) -> bytes | None:
        """``stack`` as it goes at ``now``: with its slots' ages of that moment."""
        if self.stack is None or self.aging is None:
            return self.stack
        return stamp_ages(self.stack, stamped_ages(self.aging, now)) or self.stack


@dataclass(frozen=True, slots=True)
class Digest:
    """A peer's latest digest: the versions it holds, when it came, the owners it asked this
    robot to push."""

    have: Mapping[str, Version]
    heard_at: float
    asked: frozenset[str]


class DeltaGossip:
    """The gossip policy of ``robot`` (module docstring). ``period``: the gossip period (s);
    ``strict``: lock-step; ``asks``: ask relays for the owners not heard (``stack_gossip =
    "ask"``); ``roster``: the robots of the fleet (None: any); ``max_slots``: the bound of every
    table kept; ``relay``: when asked slots go (``RELAYS``, module docstring)."""

    def __init__(
        self,
        robot: str,
        period: float,
        strict: bool,
        asks: bool,
        roster: frozenset[str] | None,
        max_slots: int,
        relay: str = "event",
    ) -> None:
        if relay not in RELAYS:
            raise ValueError(f"relay {relay!r} (known: {', '.join(RELAYS)})")
        self.robot = robot
        self.event = relay == "event"
        self.period = period
        self.strict = strict
        self.asking = asks
        self.roster = roster
        self.max_slots = max_slots
        self.digests: dict[str, Digest] = {}
        self.got: dict[str, float] = {}  # owner → when its held version came
        self.sent: dict[str, tuple[Version, float]] = {}  # owner → (version, when) last sent
        self.included: set[str] = set()  # the owners of the slots of the last selection
        self.urgent = False  # whether the last selection goes at once (not only asked slots)
        self.asked_only = False  # whether it holds slots only a peer's ask sends
        self.askers: frozenset[str] = frozenset()  # the peers whose asks those are
        # Event-driven relay: when a stack last went at once or by a flush (written by the
        # worker and by the shell's flush: a lost race costs one stack more, never one less),
        # and the stacks pushed for asked slots at once (the worker's) and by flushes (the
        # shell's: each counter has one writer).
        self.pushed_at = -math.inf
        self.pushes = 0
        self.flushes = 0
        # Versions peers' digests hold that this robot lacks: owner → (version, first seen).
        self.wanted: dict[str, tuple[Version, float]] = {}
        # Standing asks: owner → (the relay asked to push its new versions, when); since when a
        # peer's digest has shown a version of an owner newer than the one held, without a
        # break; whether the current batch changed the asks, and when a digest last went at
        # once for that (at most once a period).
        self.asks: dict[str, tuple[str, float]] = {}
        self.behind: dict[str, float] = {}
        self.asked_now = False
        self.asked_sent_at = -math.inf
        self.relays_asked = 0  # (owner, relay) asks made
        self.asks_answered = 0  # slots sent (with the next tick) only because a peer asked
        # The timer thread's own: the stack the last tick saw, the digest last sent (by a tick
        # or with a stack of the worker: ``Outgoing.digest_sent_at``) and when, the ticks that
        # sent nothing (an unchanged digest).
        self.tick_last: bytes | None = None
        self.digest_sent: tuple[bytes | None, float] = (None, -math.inf)
        self.digests_skipped = 0

    # -- what peers hold ---------------------------------------------------------------------

    def note_digest(
        self, sender: str, have: Mapping[str, Version], asked: frozenset[str], now: float
    ) -> None:
        """Keep ``sender``'s digest and the owners it asked this robot for (until its next
        digest): only a roster robot's, and at most ``max_slots`` peers' (the longest unheard
        forgotten first), so that made-up senders cannot grow it."""
        if self.roster is not None and sender not in self.roster:
            return
        self.digests.pop(sender, None)
        self.digests[sender] = Digest(have, now, asked)
        while len(self.digests) > self.max_slots:
            del self.digests[next(iter(self.digests))]

    def check_wanted(
        self, sender: str, have: Mapping[str, Version], held: Mapping[str, Version], now: float
    ) -> None:
        """Note the versions of a peer's digest this robot lacks (``held``: what it holds), each
        with when it was first seen (a newer version starts over: the peer got it just now); at
        most ``max_slots``, and with a roster only roster robots' digests and slots. With asks,
        ask a relay to push the versions of an owner this robot does not hear (:meth:`_ask`)."""
        if self.roster is not None and sender not in self.roster:
            return
        for owner, version in have.items():
            if self.roster is not None and owner not in self.roster:
                continue
            if version > held.get(owner, NONE):
                known = self.wanted.get(owner)
                if known is None or known[0] < version:
                    self.wanted.pop(owner, None)
                    self.wanted[owner] = (version, now)
                if self.asking and owner != self.robot and not self.hears(owner, now):
                    self._ask(owner, sender, now)
        while len(self.wanted) > self.max_slots:
            del self.wanted[next(iter(self.wanted))]

    def came(self, owners: list[str], now: float) -> None:
        """New versions of ``owners`` were merged at ``now``."""
        for owner in owners:
            self.got[owner] = now

    def hears(self, robot: str, now: float) -> bool:
        """Whether ``robot``'s own digest came within ``DIGEST_LIFE`` gossip periods."""
        noted = self.digests.get(robot)
        return noted is not None and noted.heard_at >= now - DIGEST_LIFE * self.period

    def _ask(self, owner: str, relay: str, now: float) -> None:
        """Behind on ``owner``, whom this robot does not hear, by ``relay``'s digest: ask
        ``relay`` to push ``owner``'s versions — unless a relay asked before is still heard and
        either was asked less than a gossip period ago or has not left this robot behind for a
        period (then the peers that could push after their chance would have). One relay per
        owner, so that a robot's neighbours do not all push the same slot (docs/wire.md,
        "Asks"); at most ``max_slots`` owners."""
        behind = self.behind.setdefault(owner, now)
        known = self.asks.get(owner)
        if known is not None:
            current, since = known
            if current == relay:
                return
            if self.hears(current, now) and (
                now - behind <= self.period or now - since <= self.period
            ):
                return
        self.asks.pop(owner, None)
        self.asks[owner] = (relay, now)
        self.asked_now = True
        self.relays_asked += 1
        while len(self.asks) > self.max_slots:
            del self.asks[next(iter(self.asks))]

    def current_asks(self, held: Mapping[str, Version], now: float) -> dict[str, str]:
        """The asks in force (owner → relay): those whose owner is still not heard and whose
        relay still is. An owner stops being behind once this robot holds the newest version a
        digest showed it, or that version is forgotten (``wanted``, at most ``max_slots``)."""
        for owner in list(self.behind):
            newest = self.wanted.get(owner)
            if newest is None or newest[0] <= held.get(owner, NONE):
                del self.behind[owner]
        for owner in [
            o for o, (r, _) in self.asks.items() if self.hears(o, now) or not self.hears(r, now)
        ]:
            del self.asks[owner]
        return {o: r for o, (r, _) in self.asks.items()}

    def pull_at(self, held: Mapping[str, Version]) -> float:
        """When the ticks pull (send the digest even if unchanged): a gossip period after a
        peer's digest first showed a version this robot still lacks. A peer pushes a slot only
        to a digest that came a period after the slot came to it (docs/wire.md): an earlier
        pull would change nothing."""
        for owner in [o for o, (v, _) in self.wanted.items() if v <= held.get(o, NONE)]:
            del self.wanted[owner]
        first = min((seen for _, seen in self.wanted.values()), default=math.inf)
        return first + self.period

    # -- what to send ------------------------------------------------------------------------

    def select(self, held: Mapping[str, Version], now: float, unsent: bool) -> set[str]:
        """The owners whose held slots (``held``, in the stack's order) go with the next stack
        (module docstring); ``unsent``: the last selection was made but not sent yet (its slots
        stay chosen). Sets :attr:`urgent` (whether the stack goes at once, not with the tick)
        and remembers what is sent when."""
        digests = dict(self.digests)
        if not self.strict:  # a peer not heard for DIGEST_LIFE periods is out of reach
            horizon = now - DIGEST_LIFE * self.period
            digests = {p: d for p, d in digests.items() if d.heard_at >= horizon}
        if self.strict and self.roster is not None:
            for peer in self.roster - {self.robot} - set(digests):
                digests[peer] = Digest({}, -math.inf, frozenset())
        include: set[str] = set()
        urgent = False
        asked_only = not self.strict and unsent and self.asked_only  # still held back
        askers = set(self.askers) if asked_only else set()
        if not self.strict and unsent:
            include |= self.included & set(held)  # computed, not sent yet
        for owner, version in held.items():
            sent_version, sent_at = self.sent.get(owner, (NONE, -math.inf))
            asked_by: list[str] = []
            for peer, d in digests.items():
                if peer == owner or d.have.get(owner, NONE) >= version:
                    continue
                if self.strict:
                    include.add(owner)
                    break
                if not (sent_version != version or d.heard_at > sent_at + self.period):
                    continue  # sent, and the peer's digest is no later than a period after it
                if owner == self.robot or d.heard_at > self.got.get(owner, 0.0) + self.period:
                    include.add(owner)  # the peer had its chance: every robot in range now
                    urgent = True
                    asked_by = []
                    break
                if owner in d.asked:  # the peer does not hear the owner, and asked this robot
                    asked_by.append(peer)
            if asked_by:
                include.add(owner)
                self.asks_answered += 1
                asked_only = True
                askers.update(asked_by)
        for owner in include:
            self.sent[owner] = (held[owner], now)
        self.included = include
        self.urgent = urgent
        self.asked_only = asked_only and not urgent
        self.askers = frozenset(askers) if self.asked_only else frozenset()
        return include

    def send_now(self, out: Outgoing, now: float) -> tuple[Sent | None, Outgoing]:
        """Real time, after a batch of messages: what to send at once (the bytes, and the peers
        they go to alone; none: every robot in range) and what the timer reads then. What a peer
        turned out to lack goes now, to every robot in range, not at the next tick (a tick then
        carries the digest alone); so does a slot only peers' asks send, with event-driven
        relay, to those peers alone (``out.push_to``), unless a stack went less than
        ``PUSH_WINDOW_S`` ago: then it goes when the window ends (``flush_at``). With ``relay =
        "tick"`` it waits for the tick (docs/wire.md, "Asks"). A changed ask goes now, at most
        once a period (else with the next tick)."""
        asked, self.asked_now = self.asked_now, False
        ready = out.fresh and out.digest is not None and out.stack is not None
        if ready and (self.urgent or (self.event and self.asked_only)):
            if self.urgent or now - self.pushed_at >= PUSH_WINDOW_S:
                self.pushed_at = now
                self.pushes += not self.urgent
                to = frozenset() if self.urgent else out.push_to
                # A push to its askers alone did not show the digest to the others.
                shown = out.digest_sent_at if to else now
                data = out.sent_at(now) or b""  # never empty: ``ready`` holds a stack
                return (data, to), replace(out, fresh=False, digest_sent_at=shown)
            out = replace(out, flush_at=self.pushed_at + PUSH_WINDOW_S)
        if asked and out.digest is not None and now - self.asked_sent_at >= self.period:
            self.asked_sent_at = now
            return (out.digest, frozenset()), replace(out, digest_sent_at=now)
        return None, out

    def flush(self, out: Outgoing, now: float) -> Sent | None:
        """Real time, the shell's flush at ``out.flush_at``: the stack whose asked slots the push
        window held back, to the peers that asked for them (``out.push_to``), unless it went
        since (with a tick, or at once: then nothing)."""
        if out.stack is None or not out.fresh or out.stack is self.tick_last:
            return None
        self.tick_last = out.stack
        self.pushed_at = now
        self.flushes += 1
        if out.digest is not None and not out.push_to:
            self.digest_sent = (out.digest, now)
        data = out.sent_at(now)
        return None if data is None else (data, out.push_to)

    def tick(self, out: Outgoing, now: float, announce: bool) -> bytes | None:
        """Real time, the timer thread: the bytes a gossip tick sends — the stack if it holds
        something not sent yet, else the digest alone when due (:meth:`digest_due`; always with
        ``announce``), else nothing."""
        if out.stack is None:
            return None
        data: bytes | None = out.stack
        if out.digest is not None and (not out.fresh or out.stack is self.tick_last):
            data = out.digest  # nothing new since it was sent: the digest alone
            if not announce and not self.digest_due(out, now):
                data = None
                self.digests_skipped += 1
        self.tick_last = out.stack
        if data is not None and out.digest is not None:
            self.digest_sent = (out.digest, now)
        return out.sent_at(now) if data is out.stack else data

    def digest_due(self, out: Outgoing, now: float) -> bool:
        """Whether a tick with nothing new to send sends the digest alone. A digest went last
        with a stack or on a tick; it goes again when it changed since (holdings, step or
        position: peers learn what they may pull from this robot), when that was
        ``DIGEST_REFRESH`` gossip periods ago (peers keep counting this robot), or to pull: when
        a peer could now push a version this robot lacks (:meth:`pull_at`) and no digest went
        since."""
        last, at = self.digest_sent
        if out.digest_sent_at > at:  # the worker sent this digest with a stack since
            last, at = out.digest, out.digest_sent_at
            self.digest_sent = (last, at)
        return (
            out.digest != last
            or now - at >= DIGEST_REFRESH * self.period
            or at < out.pull_at <= now
        )
