"""The agent core's policies, each alone: digests, orders, links, versions and times in, decisions
out — no node, codec or journal (agents/gossip.py, agents/rounds.py, agents/sim_radio.py,
agents/recovery.py)."""

from __future__ import annotations

import math

import pytest

from agents.control import NeedRound, StepOrder, encode_control
from agents.gossip import DIGEST_LIFE, DIGEST_REFRESH, DeltaGossip, Outgoing
from agents.journal import Record
from agents.recovery import FRAME, FRAME_UNFUSED, Ledger
from agents.rounds import LOCKSTEP_RESEND_MAX, Answers, Rounds, resend_max
from agents.sim_radio import SimRadio
from protocol.codec import StackMessage
from protocol.stack import Stack

P = 0.5  # gossip period (s)
ROSTER = frozenset({"r1", "r2", "r3", "r4"})


def _gossip(strict: bool = False, asks: bool = True, max_slots: int = 32) -> DeltaGossip:
    return DeltaGossip("r1", P, strict, asks, ROSTER, max_slots)


# -- DeltaGossip -----------------------------------------------------------------------------


def test_lockstep_sends_what_some_peer_lacks_and_only_that() -> None:
    g = _gossip(strict=True)
    held = {"r1": (0, 5), "r2": (0, 4), "r3": (0, 2)}
    # Nobody heard yet: every roster peer lacks everything.
    assert g.select(held, 0.0, unsent=False) == {"r1", "r2", "r3"}
    for peer in ("r2", "r3", "r4"):
        g.note_digest(peer, {"r1": (0, 5), "r2": (0, 4), "r3": (0, 2)}, frozenset(), 1.0)
    assert g.select(held, 1.0, unsent=False) == set()
    # r4's digest lacks r3's version 2 (it holds 1): only that slot goes, whatever the times.
    g.note_digest("r4", {"r1": (0, 5), "r2": (0, 4), "r3": (0, 1)}, frozenset(), 1.0)
    assert g.select(held, 1.0, unsent=False) == {"r3"}
    # A peer's own slot is never sent back to it: r2 lacking r2's version changes nothing.
    g.note_digest("r4", {"r1": (0, 5), "r2": (0, 4), "r3": (0, 2)}, frozenset(), 2.0)
    g.note_digest("r2", {"r1": (0, 5), "r2": (0, 1), "r3": (0, 2)}, frozenset(), 2.0)
    assert g.select(held, 2.0, unsent=False) == set()


def test_realtime_waits_a_period_for_the_peers_own_chance_but_sends_the_own_slot_at_once() -> None:
    g = _gossip()
    g.came(["r3"], 10.0)  # r3's version came at t = 10
    held = {"r1": (0, 7), "r3": (0, 2)}
    g.note_digest("r2", {}, frozenset(), 10.2)  # r2 lacks both, heard 0.2 s after r3's came
    assert g.select(held, 10.2, unsent=False) == {"r1"} and g.urgent
    # A digest a period after r3's version came: r2 had its chance to hear r3 itself.
    g.note_digest("r2", {"r1": (0, 7)}, frozenset(), 10.0 + P + 0.01)
    assert g.select(held, 10.6, unsent=False) == {"r3"}
    # Sent at 10.6: not again until a digest more than a period after that still lacks it.
    g.note_digest("r2", {"r1": (0, 7)}, frozenset(), 10.9)
    assert g.select(held, 10.9, unsent=False) == set()
    g.note_digest("r2", {"r1": (0, 7)}, frozenset(), 10.6 + P + 0.01)
    assert g.select(held, 11.2, unsent=False) == {"r3"}


def test_a_slot_asked_for_goes_with_the_next_tick_not_at_once() -> None:
    g = _gossip()
    g.came(["r3"], 10.0)
    g.note_digest("r2", {"r1": (0, 1)}, frozenset({"r3"}), 10.1)  # r2 asks r1 for r3
    assert g.select({"r1": (0, 1), "r3": (0, 4)}, 10.1, unsent=False) == {"r3"}
    assert not g.urgent and g.asks_answered == 1


def test_a_peer_out_of_reach_is_not_served_in_real_time() -> None:
    g = _gossip()
    g.note_digest("r2", {}, frozenset(), 0.0)
    assert g.select({"r1": (0, 1)}, 0.1, unsent=False) == {"r1"}
    later = DIGEST_LIFE * P + 0.2  # r2 silent for longer than DIGEST_LIFE periods
    assert g.select({"r1": (0, 2)}, later, unsent=False) == set()


def test_asks_go_to_one_relay_per_owner_not_heard_and_end_when_caught_up() -> None:
    g = _gossip()
    g.note_digest("r2", {"r4": (0, 3)}, frozenset(), 1.0)
    g.check_wanted("r2", {"r4": (0, 3)}, {}, 1.0)
    assert g.asks == {"r4": ("r2", 1.0)} and g.asked_now and g.relays_asked == 1
    # r3 shows r4's version too, within a period: the ask stays with r2.
    g.note_digest("r3", {"r4": (0, 3)}, frozenset(), 1.2)
    g.check_wanted("r3", {"r4": (0, 3)}, {}, 1.2)
    assert g.current_asks({}, 1.2) == {"r4": "r2"}
    # Caught up with r4's newest version: no longer behind; r4's own digest heard: no ask.
    g.note_digest("r4", {"r4": (0, 3)}, frozenset(), 1.3)
    assert g.current_asks({"r4": (0, 3)}, 1.3) == {}
    assert not g.behind


def test_pull_at_is_a_period_after_a_lacked_version_was_first_seen() -> None:
    g = _gossip()
    assert g.pull_at({}) == math.inf
    g.check_wanted("r2", {"r3": (0, 4)}, {}, 2.0)
    g.check_wanted("r2", {"r3": (0, 4)}, {}, 2.3)  # the same version: first seen stays
    assert g.pull_at({}) == pytest.approx(2.0 + P)
    assert g.pull_at({"r3": (0, 4)}) == math.inf  # held now: nothing to pull


def test_tables_stay_bounded_and_ignore_robots_outside_the_roster() -> None:
    g = _gossip(max_slots=2)
    g.note_digest("x9", {"r2": (0, 1)}, frozenset(), 0.0)  # not a roster robot
    assert g.digests == {}
    for i, peer in enumerate(("r2", "r3", "r4")):
        g.note_digest(peer, {}, frozenset(), float(i))
    assert list(g.digests) == ["r3", "r4"]  # the longest unheard forgotten first
    g.check_wanted("r2", {"r2": (0, 1), "r3": (0, 1), "r4": (0, 1), "x9": (0, 1)}, {}, 5.0)
    assert set(g.wanted) == {"r3", "r4"}


def test_a_tick_sends_the_stack_once_then_the_digest_when_due() -> None:
    g = _gossip()
    out = Outgoing(stack=b"stack", digest=b"digest", fresh=True)
    assert g.tick(out, 1.0, announce=False) == b"stack"
    assert g.tick(out, 1.1, announce=False) is None  # the same stack: its digest is not due
    assert g.digests_skipped == 1
    assert g.tick(out, 1.1, announce=True) == b"digest"  # new peers: always
    assert g.tick(out, 1.2, announce=False) is None
    assert g.tick(out, 1.1 + DIGEST_REFRESH * P, announce=False) == b"digest"  # refresh
    changed = Outgoing(stack=b"stack", digest=b"digest2", fresh=False)
    assert g.tick(changed, 2.2, announce=False) == b"digest2"  # a changed digest goes
    pull = Outgoing(stack=b"stack", digest=b"digest2", fresh=False, pull_at=2.5)
    assert g.tick(pull, 2.4, announce=False) is None
    assert g.tick(pull, 2.6, announce=False) == b"digest2"  # a peer can push now


def test_send_now_sends_what_a_peer_lacks_at_once_and_a_changed_ask_once_a_period() -> None:
    g = _gossip()
    g.urgent = True
    out = Outgoing(stack=b"s", digest=b"d", fresh=True)
    sent, after = g.send_now(out, 3.0)
    assert sent == (b"s", frozenset()) and not after.fresh and after.digest_sent_at == 3.0
    g.urgent, g.asked_now = False, True
    sent, after = g.send_now(after, 3.1)
    assert sent == (b"d", frozenset()) and g.asked_sent_at == 3.1 and not g.asked_now
    g.asked_now = True
    assert g.send_now(after, 3.2)[0] is None  # within a period of the last: with the tick


# -- Rounds and Answers ----------------------------------------------------------------------


def _message(sender: str, step: int) -> StackMessage:
    return StackMessage(sender, None, Stack(()), step)


def test_a_round_is_ready_when_its_order_and_every_named_stack_are_here() -> None:
    rounds = Rounds("r1", P, window=4, peers=3, max_peers=4)
    rounds.on_order(StepOrder(3, {"r1": ("r3", "r2")}), k=2)
    assert rounds.ready(3) is None and rounds.round_missing(3) == (2, ("r2", "r3"))
    rounds.hold(_message("r3", 2), b"three", k=2)
    assert rounds.round_missing(3) == (2, ("r2",))
    rounds.hold(_message("r2", 2), b"two", k=2)
    rounds.hold(_message("r2", 2), b"copy", k=2)  # the first copy is kept
    held = rounds.ready(3)
    assert held is not None and [data for _, data in held] == [b"two", b"three"]  # sender order
    assert rounds.frames_missing(3, {}) and not rounds.frames_missing(3, {3: None})
    rounds.forget_before(3)
    assert rounds.orders == {} and rounds.held == {}


def test_rounds_keep_only_the_window_and_a_bounded_number_of_stacks() -> None:
    rounds = Rounds("r1", P, window=2, peers=1, max_peers=1)  # at most 1 × 3 stacks held
    rounds.on_order(StepOrder(9, {}), k=2)
    assert rounds.orders_ahead == 1 and rounds.orders == {}
    rounds.hold(_message("r2", 9), b"far", k=2)  # beyond the window: not kept, not counted
    for step in (2, 3, 4):
        rounds.hold(_message("r2", step), b"x", k=2)
    rounds.hold(_message("r3", 2), b"x", k=2)
    assert len(rounds.held) == 3 and rounds.rounds_dropped == 1


def test_round_resends_back_off_exponentially_up_to_the_fleets_cap() -> None:
    rounds = Rounds("r1", P, window=4, peers=2, max_peers=3)
    out = Outgoing(stack=b"now", previous=b"before", k=5)
    sent = [bool(rounds.tick(out, t)[0]) for t in range(40)]
    gaps = [
        j - i
        for i, j in zip(
            [t for t, s in enumerate(sent) if s],
            [t for t, s in enumerate(sent) if s][1:],
            strict=False,
        )
    ]
    assert gaps[:4] == [1, 2, 4, 8] and max(gaps) == LOCKSTEP_RESEND_MAX
    assert rounds.tick(Outgoing(stack=b"next", k=6), 41)[0] == [b"next"]  # a new round at once
    assert resend_max(20) == 40


def test_a_missing_round_stack_is_asked_for_after_a_period_and_answered_once_a_period() -> None:
    rounds = Rounds("r1", P, window=4, peers=3, max_peers=4)
    need = (4, ("r2",))
    out = Outgoing(stack=b"s", k=4, need_round=need)
    assert rounds.tick(out, 0.0)[1] is None  # first seen
    assert rounds.tick(out, 0.2)[1] is None  # not a period yet
    assert rounds.tick(out, 0.6)[1] == NeedRound("r1", 4, ("r2",))
    assert rounds.tick(out, 0.8)[1] is None and rounds.round_requests == 1
    asked = NeedRound("r2", 4, ("r1",))
    made = {4: b"round4", 3: b"round3"}
    assert rounds.answer_round(asked, "r2", made, 1.0) == b"round4"
    assert rounds.answer_round(asked, "r2", made, 1.2) is None  # within a period
    assert rounds.answer_round(asked, "r3", made, 2.0) is None  # asked on another robot's key
    assert rounds.answer_round(NeedRound("r2", 1, ("r1",)), "r2", made, 2.0) is None  # not made


def test_answers_to_repeated_requests() -> None:
    answers = Answers("r1", P, peers=3)
    named = StepOrder(4, {}, waiting=("r1",))
    assert answers.order_due(named, 0.0) and not answers.order_due(named, 0.3)
    assert not answers.order_due(StepOrder(4, {}, waiting=("r2",)), 1.0)  # not waited for
    anyone = StepOrder(5, {})
    waits = [t for t in range(64) if answers.order_due(anyone, t * P)]
    assert waits[:5] == [0, 1, 3, 7, 15]  # after 1, 2, 4, 8 periods ...
    assert answers.due(6, 40.0) and not answers.due(6, 40.1) and answers.due(6, 40.0 + P)


# -- SimRadio --------------------------------------------------------------------------------


def _links(k: int, links: dict[str, tuple[str, ...]]) -> bytes:
    return encode_control(StepOrder(k, links))


def test_the_radio_hears_by_the_links_due_and_subscribes_ahead() -> None:
    radio = SimRadio("r1", window=4, max_control_bytes=4096)
    assert not radio.heard("r2", 0)  # no links yet: nobody
    radio.out_of_range()
    assert radio.ignored_out_of_range == 0  # before the first links nobody is out of range
    assert radio.on_links(_links(1, {"r1": ("r2",)}), ahead=False, k=0) is None
    assert radio.on_links(_links(2, {"r1": ("r3",)}), ahead=True, k=0) is None
    assert radio.heard("r2", 0) and not radio.heard("r3", 0)
    assert radio.listen(0, ROSTER, initial=False) == frozenset({"r2", "r3"})
    assert radio.listen(0, ROSTER, initial=False) is None  # unchanged
    assert radio.hear(0, lambda r: f"stack/{r}") == frozenset({"stack/r2"})
    radio.out_of_range()
    assert radio.ignored_out_of_range == 1 and radio.listen_changes == 1


def test_the_radio_refuses_bad_links_and_forgets_past_steps() -> None:
    radio = SimRadio("r1", window=2, max_control_bytes=4096)
    assert radio.on_links(b"\x00junk", ahead=False, k=0) is not None
    assert radio.on_links(encode_control(NeedRound("r2", 1, ())), ahead=False, k=0) is not None
    assert radio.invalid_links == 2
    radio.on_links(_links(9, {"r1": ("r2",)}), ahead=False, k=0)  # beyond the window
    for k in (1, 2):
        radio.on_links(_links(k, {"r1": (f"r{k + 1}",)}), ahead=False, k=0)
    radio.forget_before(2)
    assert list(radio.links) == [2]  # the verdict in force at step 3 stays


# -- Ledger ----------------------------------------------------------------------------------


def test_the_ledger_commits_stacks_with_the_step_that_fuses_them() -> None:
    ledger = Ledger()
    ledger.took([("r2", (0, 3))], b"stack-a")
    assert ledger.commit(b"f1", fused=False) == [Record(FRAME_UNFUSED, b"f1")]
    assert ledger.suspects == [("r2", (0, 3))] and ledger.deferred_in_row == 1
    records = ledger.commit(b"f2", fused=True)
    assert records == [Record("stack", b"stack-a"), Record(FRAME, b"f2")]
    assert ledger.suspects == [] and ledger.deferred_in_row == 0
    assert ledger.batch == [Record(FRAME_UNFUSED, b"f1"), *records]


def test_a_failed_step_refuses_its_suspects_and_its_frame_bytes_for_good(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import agents.recovery as recovery

    monkeypatch.setattr(recovery, "MAX_REFUSED", 2)
    ledger = Ledger()
    ledger.took([("r2", (0, 1)), ("r3", (0, 1))], b"s1")
    ledger.took([("r4", (0, 1))], b"s2")
    assert ledger.failed(b"frame") == [("r2", (0, 1)), ("r3", (0, 1)), ("r4", (0, 1))]
    assert list(ledger.refused) == [("r3", (0, 1)), ("r4", (0, 1))]  # bounded, oldest gone
    assert ledger.is_bad(b"frame") and not ledger.is_bad(b"other")
    committed = [Record(FRAME, b"f0")]
    assert ledger.rollback(committed) == committed and ledger.uncommitted == []
