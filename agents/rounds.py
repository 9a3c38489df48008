"""Lock-step rounds and the estimate answers, without any I/O.

:class:`Rounds` (built only in lock-step mode): the conductor's step orders and the peers' round
stacks an agent keeps until its step can run; when a round is complete (:meth:`Rounds.ready`);
what is missing (frames of an ordered step, round stacks of the senders an order names); the
timer's repair of losses — the round's own stacks re-sent with exponential back-off
(:meth:`Rounds.backoff`), a peer's missing round stack asked for (:meth:`Rounds.ask_for_round`)
and such an ask answered (:meth:`Rounds.answer_round`); which copy of a sender's round stack a
step merges when a member that is the attacker publishes forged ones on its key, and when to go
on without a sender whose every copy the belief gate refuses. Everything kept is bounded by the
``window`` steps ahead and by the roster.

:class:`Answers` (every mode): how often a repeated request — an order of the current round, a
frame of the current step sent again — is answered with the estimate again.

Each sees orders, stacks' senders and steps, and times; the belief gate only as a predicate
given by the shell; no node, codec or journal.

Over 300 lines for a reason: the rounds' bookkeeping, their repair by the timer and the choice
among forged and honest copies act on the same held stacks and requests, and split apart each
would need the others' state.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Container, Sequence

from agents.control import NeedRound, StepOrder
from agents.gossip import Outgoing
from protocol.codec import StackMessage

COPIES = 3  # distinct copies of one sender's round stack kept (:meth:`Rounds.hold`)
# A round gives up on a sender whose every copy its belief gate refuses once a copy came after
# this many requests for it, a gossip period or more apart (:meth:`Rounds.ready`): a request gives
# the sender's own stack a chance to come (a flooded inbox drops some), and an attacker's forged
# copy, published ahead of the round on the sender's key, no race to win. One request: the whole
# attack suite (a member's poison and a status flood among them) left the estimates equal to the
# clean run in 3 of 3 runs, and each refused round of an honest but drifted peer costs about two
# gossip periods (three requests made a lock-step launch of UTIAS Dataset 7 about 4× slower).
GIVE_UP_ASKS = 1
LOCKSTEP_RESEND_MAX = 8  # periods: the longest a lock-step agent waits to re-send a stack
# ... in a fleet of up to LOCKSTEP_RESEND_MAX / 2 + 1 robots: beyond, 2 (N − 1) periods, so that
# whatever N an agent receives about one re-sent stack every two periods (N² / (2 (N − 1)) / N).


def _anyone(message: StackMessage) -> bool:
    return True


def resend_max(peers: int) -> int:
    """The longest back-off of the lock-step re-sends, in gossip periods, with ``peers`` other
    robots: LOCKSTEP_RESEND_MAX, or 2 (N − 1) if longer. Every agent re-sends to N − 1 peers, so
    with a fixed cap the re-sends a peer receives grow with N (50 agents on 2 cores: about 6 a
    second each, 23 MB per agent in three rounds, a round of minutes and inbox overflows);
    scaled, they stay at about one every two periods. Loopback or a LAN rarely loses a stack:
    the ticks only repair losses."""
    return max(LOCKSTEP_RESEND_MAX, 2 * peers)


class Answers:
    """When a repeated request is answered with the estimate again (``period``: the gossip
    period; ``peers``: the other robots of the roster)."""

    def __init__(self, robot: str, period: float, peers: int) -> None:
        self.robot = robot
        self.period = period
        self.peers = peers
        # (round, when last answered, the wait before the next answer).
        self.last: tuple[int, float, float] = (-1, -math.inf, 0.0)

    def order_due(self, order: StepOrder, now: float) -> bool:
        """Whether a repeated order of the current round is answered with the estimate again.
        An order that names the robots it waits for is answered by those only, at most once a
        gossip period (the conductor backs its re-orders off). One that names nobody (an
        operator's, an older conductor's) goes to the whole fleet: answered at once the first
        time, then after 1, 2, 4 ... gossip periods, up to :func:`resend_max` (every agent
        would answer it, and an estimate can be megabytes)."""
        if order.waiting is not None:
            return self.robot in order.waiting and self.due(order.k, now)
        last_k, last_t, wait = self.last
        if order.k != last_k:
            self.last = (order.k, now, self.period)
            return True
        if now - last_t < wait:
            return False
        self.last = (order.k, now, min(2 * wait, resend_max(self.peers) * self.period))
        return True

    def due(self, k: int, now: float) -> bool:
        """A request meant for this robot (an order naming it, a frame of its current step sent
        again): answered with the estimate at most once a gossip period."""
        last_k, last_t, _ = self.last
        if k == last_k and now - last_t < self.period:
            return False
        self.last = (k, now, self.period)
        return True


class Rounds:
    """The lock-step rounds of ``robot`` (module docstring): ``window`` steps ahead at most,
    ``peers`` other robots (the roster's, else up to ``max_slots``)."""

    def __init__(self, robot: str, period: float, window: int, peers: int, max_peers: int) -> None:
        self.robot = robot
        self.period = period
        self.window = window
        self.peers = peers
        self.max_rounds = max(1, max_peers) * (window + 1)
        self.orders: dict[int, StepOrder] = {}
        # (sender, round) → the distinct copies that came, in order.
        self.held: dict[tuple[str, int], list[tuple[StackMessage, bytes]]] = {}
        # The round and senders last asked for (:meth:`tick`) and how often that round was
        # asked for; the (sender, round) whose copy came after the last of GIVE_UP_ASKS asks.
        self._asked: tuple[int, tuple[str, ...], int] | None = None
        self.answered: set[tuple[str, int]] = set()
        self.orders_ahead = 0
        self.rounds_dropped = 0
        self.round_requests = 0
        self.rounds_resent = 0
        # The timer thread's own: the round last re-sent, the periods to wait before its next
        # re-send and the periods waited so far; a request for round stacks (the need, when
        # first seen, when last asked).
        self._resend = (-1, 1, 0)
        self._need: tuple[tuple[int, tuple[str, ...]] | None, float, float] = (
            None,
            -math.inf,
            -math.inf,
        )
        self._resent: dict[int, float] = {}  # when each round was last sent on request

    # -- what arrives ------------------------------------------------------------------------

    def on_order(self, order: StepOrder, k: int) -> None:
        """Keep an order of a step ahead of ``k`` (within the window; beyond, counted)."""
        if k < order.k <= k + self.window:
            self.orders[order.k] = order
        elif order.k > k:
            self.orders_ahead += 1

    def hold(
        self,
        message: StackMessage,
        payload: bytes,
        k: int,
        hears: Callable[[StackMessage], bool] = _anyone,
    ) -> None:
        """Keep a peer's round stack until the step that merges it (its round within the
        window; at most ``max_rounds`` rounds held, and as many further copies). Up to
        ``COPIES`` distinct copies of one sender's round are kept: a member that is the attacker
        can publish forged ones on the sender's key before the honest one comes, and the step
        takes the first its belief gate ``hears`` (:meth:`ready`). When they are all there, a
        copy the gate hears now takes the place of the last one it does not."""
        if not k <= message.step <= k + self.window:
            return
        key = (message.sender, message.step)
        asked = self._asked
        if (
            asked is not None
            and asked[0] == message.step
            and message.sender in asked[1]
            and asked[2] >= GIVE_UP_ASKS
        ):
            self.answered.add(key)
        copies = self.held.get(key)
        if copies is None:
            if len(self.held) >= self.max_rounds:
                self.rounds_dropped += 1
                return
            self.held[key] = [(message, payload)]
            return
        if any(c[1] == payload for c in copies):
            return
        if len(copies) >= COPIES:
            deaf = [i for i, (m, _) in enumerate(copies) if not hears(m)]
            if deaf and hears(message):
                copies[deaf[-1]] = (message, payload)
            else:
                self.rounds_dropped += 1
            return
        # Further copies have a bound of their own, so that they never crowd out a first one.
        if sum(len(c) - 1 for c in self.held.values()) >= self.max_rounds:
            self.rounds_dropped += 1
            return
        copies.append((message, payload))

    def ready(
        self, k: int, hears: Callable[[StackMessage], bool] = _anyone
    ) -> list[tuple[StackMessage, bytes]] | None:
        """The round stacks step ``k`` merges, in sender order, once its order and a stack of
        round ``k − 1`` from every sender it names are here (None: not yet). Of a sender's
        copies, the first that ``hears`` (the belief gate, judged now: before step ``k``, as
        the in-process runner judges). If it hears none of them, the round asks the sender
        for its stack (:meth:`round_missing`) and takes the first copy once a copy came after
        the GIVE_UP_ASKS-th request, which the step's merge refuses and counts: one drifted
        peer, or a member that is the attacker, must not stall the round for good, and a forged
        copy published ahead of the round must not win the race against the sender's own."""
        order = self.orders.get(k)
        if order is None:
            return None
        picks = []
        for s in sorted(order.links.get(self.robot, ())):
            pick = self._pick(s, k - 1, hears)
            if pick is None or not (pick[2] or (s, k - 1) in self.answered):
                return None
            picks.append(pick)
        return [(m, data) for m, data, _ in picks]

    def passed_over(
        self, k: int, merged: Sequence[tuple[StackMessage, bytes]]
    ) -> list[StackMessage]:
        """The copies of round ``k − 1`` that step ``k`` does not merge (``merged``: what
        :meth:`ready` gave): forged ones the belief gate refused, for the shell to count."""
        taken = {data for _, data in merged}
        return [
            m
            for (_, r), copies in sorted(self.held.items())
            if r == k - 1
            for m, data in copies
            if data not in taken
        ]

    def _pick(
        self, sender: str, round_k: int, hears: Callable[[StackMessage], bool]
    ) -> tuple[StackMessage, bytes, bool] | None:
        """The copy of ``sender``'s round stack to merge, and whether ``hears`` it (None: no
        copy came)."""
        copies = self.held.get((sender, round_k))
        if not copies:
            return None
        for message, payload in copies:
            if hears(message):
                return message, payload, True
        return copies[0][0], copies[0][1], False

    def forget_before(self, k: int) -> None:
        self.orders = {j: o for j, o in self.orders.items() if j > k}
        self.held = {key: v for key, v in self.held.items() if key[1] >= k}
        self.answered = {key for key in self.answered if key[1] >= k}

    def frames_missing(self, k: int, frames: Container[int]) -> bool:
        """Whether step ``k`` is ordered and its frame has not come."""
        return k in self.orders and k not in frames

    def round_missing(
        self, k: int, hears: Callable[[StackMessage], bool] = _anyone
    ) -> tuple[int, tuple[str, ...]] | None:
        """The round whose stacks step ``k`` merges, and the senders its order names whose stack
        of that round has not come, or came and is not heard yet (:meth:`ready`; None: nothing
        to ask for)."""
        order = self.orders.get(k)
        if order is None:
            return None
        senders = order.links.get(self.robot, ())
        missing = tuple(
            sorted(
                s
                for s in senders
                if not (pick := self._pick(s, k - 1, hears))
                or not (pick[2] or (s, k - 1) in self.answered)
            )
        )
        return (k - 1, missing) if missing else None

    # -- the timer's repairs -----------------------------------------------------------------

    def tick(self, out: Outgoing, now: float) -> tuple[list[bytes], NeedRound | None]:
        """The timer: the round stacks to re-send (the current round's and the previous one's,
        which a slower peer may still need; none while backed off) and the request for the
        missing round stacks of the coming step, if one is due."""
        sends = [] if self.backoff(out.k) else [out.previous, out.stack]
        need = out.need_round
        ask = None
        if (need is not None or self.asking) and self.ask_for_round(need, now) and need is not None:
            ask = NeedRound(self.robot, need[0], need[1])
            asked = self._asked
            times = asked[2] + 1 if asked is not None and asked[0] == need[0] else 1
            self._asked = (need[0], need[1], times)
        return [b for b in sends if b is not None], ask

    def backoff(self, round_k: int) -> bool:
        """Whether this tick skips the re-send of round ``round_k``'s stacks: they go out when
        the round ends, and the ticks only repair a loss, so they are re-sent after 1, 2, 4 ...
        up to :func:`resend_max` periods instead of every period — with N agents every period
        would be N² stacks, which swamped 50 agents on 2 cores. A new round starts over at one
        period; a round stack whose bytes change within the round (what peers lack shrinks as
        their digests come) keeps its back-off: starting over at every change re-sent stacks
        several times a period in a 50-agent fleet."""
        last, wait, idle = self._resend
        if round_k != last:
            self._resend = (round_k, 1, 0)
            return False
        idle += 1
        if idle < wait:
            self._resend = (last, wait, idle)
            return True
        self._resend = (last, min(2 * wait, resend_max(self.peers)), 0)
        return False

    def ask_for_round(self, need: tuple[int, tuple[str, ...]] | None, now: float) -> bool:
        """Whether to ask the senders whose stack of the coming step's round has not come for
        it: once it has been missing a gossip period, then at most once a period (a lost stack
        is otherwise re-sent only on its sender's backed-off ticks, up to 2 (N − 1) periods
        later)."""
        seen, since, asked = self._need
        if need != seen:
            self._need = (need, now, -math.inf)
            return False
        if need is None or now - since < self.period or now - asked < self.period:
            return False
        self._need = (need, since, now)
        self.round_requests += 1
        return True

    @property
    def asking(self) -> bool:
        """Whether a request for round stacks is being followed (the timer must see it end)."""
        return self._need[0] is not None

    def answer_round(
        self,
        need: NeedRound,
        asker: str | None,
        rounds: dict[int, bytes | None],
        now: float,
    ) -> bytes | None:
        """A peer lacks this robot's stack of round ``need.k``: the bytes to send again, if this
        robot made that round (``rounds``: round → its stack, the current and the previous), at
        most once a gossip period per round whoever asks. A request on another robot's key is
        ignored (each robot asks on its own ``ctl/need`` key; a secure fleet enforces it)."""
        if asker != need.robot or need.robot == self.robot or self.robot not in need.senders:
            return None
        data = rounds.get(need.k)
        last = self._resent.get(need.k, -math.inf)
        if data is None or now - last < self.period:
            return None
        oldest = min(rounds)
        self._resent = {k: t for k, t in self._resent.items() if k >= oldest}
        self._resent[need.k] = now
        self.rounds_resent += 1
        return data
