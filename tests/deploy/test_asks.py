"""Standing asks (``stack_gossip = "ask"``, the default; docs/wire.md, "Asks"): a robot that does
not hear an owner asks one relay to push that owner's versions; the relay pushes each new
version on arrival (``relay = "event"``, the default: at once, at most one stack a push window)
or with its next gossip tick (``relay = "tick"``), not a gossip period after the version came; a
forged or repeated ask sends nothing more than a lacking digest would. Real cores and codecs,
simulated time."""

from __future__ import annotations

from agents.core import AgentCore, CoreSettings, Flush, Publish
from agents.gossip import DIGEST_LIFE, PUSH_WINDOW_S
from agents.runtime import MemoryLog, execute_journal_actions
from deploy.base.build import belief_model, make_node
from estimator.hybrid import BeliefConfig
from protocol.codec import StackMessage, decode, encode
from protocol.frames import encode_frame
from protocol.stack import Stack
from sim.loader import load_scenario
from tests.deploy.test_delta_gossip import KEYS, _hearing_pair, _stacks, _tick

PERIOD = 0.5


def _asks_in_force(core: AgentCore) -> dict[str, str]:
    return core.gossip.current_asks(core.node.stack.versions(), core._now)


def _asker(gossip: str = "ask") -> tuple[AgentCore, MemoryLog]:
    """r3 of the paper scenario, before its first step, with ``stack_gossip = gossip``."""
    s = load_scenario("paper")

    def make():  # type: ignore[no-untyped-def]
        return make_node("r3", s.robot("r3").start, belief_model(s), 4, BeliefConfig())

    log = MemoryLog()
    settings = CoreSettings(gossip_period=PERIOD, stack_gossip=gossip)
    return AgentCore(make, KEYS, settings, log.records), log


def _digest(sender: str, have: dict[str, tuple[int, int]]) -> bytes:
    return encode(StackMessage(sender, None, Stack(), 0, have=have))


def _slots_of(payloads: list[bytes], owner: str) -> list[tuple[int, int] | None]:
    return [decode(p).stack.versions().get(owner) for p in payloads]


def test_a_robot_asks_one_relay_for_an_owner_it_does_not_hear_and_it_pushes_at_its_tick() -> None:
    r1, log1, r2, log2, frames, now = _hearing_pair(2, relay="tick")
    r3, log3 = _asker()
    _stacks(r3.start(now), log3, "r3")
    held = r2.node.current_stack().versions()
    # r3 hears r2 only. r2's digest shows r1's slot: r3 asks r2 for it, at once.
    sent = _stacks(r3.on_message(KEYS.stack("r2"), r2.node.encoded_delta(()), now), log3, "r3")
    assert [decode(p).ask for p in sent] == [{"r1": "r2"}]
    assert r3.counter_values()["relays_asked"] == 1
    # Without the ask, r1's slot waits for r3's chance (a gossip period after the version came to
    # r2: r3 might hear r1 itself); r2's next tick does not carry it.
    plain = _digest("r3", r3.node.current_stack().versions())
    assert _slots_of(_stacks(r2.on_message(KEYS.stack("r3"), plain, now + 0.01), log2, "r2"),
                     "r1") == []  # fmt: skip
    assert all(v is None for v in _slots_of(_tick(r2, now + 0.02), "r1"))
    # With it, not at once either (a tick comes within a period), but with r2's next tick.
    assert _stacks(r2.on_message(KEYS.stack("r3"), sent[0], now + 0.03), log2, "r2") == []
    pushed = _tick(r2, now + 0.04)
    assert [v for v in _slots_of(pushed, "r1") if v] == [held["r1"]]
    assert r2.counter_values()["asks_answered"] == 1
    for p in pushed:
        _stacks(r3.on_message(KEYS.stack("r2"), p, now + 0.05), log3, "r3")
    assert r3.node.stack.versions()["r1"] == held["r1"]
    # The ask stands in r3's digests, and r2 pushes r1's next version with the tick after it
    # merged it.
    tick = [decode(a.payload) for a in r3.on_timer(now + 0.1) if isinstance(a, Publish)]
    assert [m.ask for m in tick] == [{"r1": "r2"}]
    _stacks(r2.on_message(KEYS.stack("r3"), r3.node.encoded_delta((), {"r1": "r2"}), now + 0.1),
            log2, "r2")  # fmt: skip
    now += 1.0
    stepped = _stacks(
        r1.on_message(KEYS.frames("r1"), encode_frame(frames["r1"][2]), now), log1, "r1"
    )
    merged = _stacks(r2.on_message(KEYS.stack("r1"), stepped[-1], now + 0.01), log2, "r2")
    newest = r1.node.stack.versions()["r1"]
    assert newest > held["r1"] and _slots_of(merged, "r1") == []
    assert [v for v in _slots_of(_tick(r2, now + 0.02), "r1") if v] == [newest]
    # Another relay's digest showing the same version does not make r3 ask again.
    again = _stacks(r3.on_message(KEYS.stack("r4"), _digest("r4", {"r1": newest}), now + 0.02),
                    log3, "r3")  # fmt: skip
    assert again == [] and r3.counter_values()["relays_asked"] == 1
    # Once r3 hears r1 itself, it asks nobody for r1's slot.
    _stacks(r3.on_message(KEYS.stack("r1"), stepped[-1], now + 0.05), log3, "r3")
    tick = [decode(a.payload) for a in r3.on_timer(now + 0.1) if isinstance(a, Publish)]
    assert len(tick) == 1 and not tick[0].ask


def test_a_relay_that_leaves_the_robot_behind_a_period_is_replaced_and_a_silent_one_dropped() -> (
    None
):
    r3, log3 = _asker()
    now = 1.0
    _stacks(r3.start(now), log3, "r3")
    v = (1, 5)
    # r2's digest shows its own slot too, which r3 lacks; but r3 hears r2: asked for r1 only.
    first = _digest("r2", {"r1": v, "r2": (1, 4)})
    sent = _stacks(r3.on_message(KEYS.stack("r2"), first, now), log3, "r3")
    assert [decode(p).ask for p in sent] == [{"r1": "r2"}]
    assert _asks_in_force(r3) == {"r1": "r2"} and r3.counter_values()["relays_asked"] == 1
    # r4 shows a newer version; r2, heard, was asked just now: no switch.
    _stacks(r3.on_message(KEYS.stack("r4"), _digest("r4", {"r1": (1, 6)}), now + 0.1), log3, "r3")
    assert _asks_in_force(r3) == {"r1": "r2"}
    # Still behind a period later (r2 keeps sending digests, but not r1's slot): switch to r4.
    _stacks(r3.on_message(KEYS.stack("r2"), _digest("r2", {"r1": v}), now + PERIOD), log3, "r3")
    later = now + PERIOD + 0.05
    sent = _stacks(
        r3.on_message(KEYS.stack("r4"), _digest("r4", {"r1": (1, 6)}), later), log3, "r3"
    )
    assert _asks_in_force(r3) == {"r1": "r4"}
    assert [decode(p).ask for p in sent] == [{"r1": "r4"}]
    assert r3.counter_values()["relays_asked"] == 2
    # r4 falls silent for DIGEST_LIFE periods, and r2 no longer holds r1's slot: the ask goes,
    # and the digest shows none.
    silent = later + DIGEST_LIFE * PERIOD + 0.05
    _stacks(r3.on_message(KEYS.stack("r2"), _digest("r2", {}), silent), log3, "r3")
    tick = [decode(a.payload) for a in r3.on_timer(silent + 0.05) if isinstance(a, Publish)]
    assert _asks_in_force(r3) == {} and [m.ask for m in tick] == [None]
    # A heard robot whose digest shows the version again is asked for it.
    _stacks(r3.on_message(KEYS.stack("r2"), _digest("r2", {"r1": v}), silent + 0.1), log3, "r3")
    assert _asks_in_force(r3) == {"r1": "r2"}


def test_delta_gossip_makes_no_asks_and_an_ask_for_another_relay_is_not_answered() -> None:
    _, _, r2, log2, _, now = _hearing_pair(2)
    r3, log3 = _asker("delta")
    _stacks(r3.start(now), log3, "r3")
    sent = _stacks(r3.on_message(KEYS.stack("r2"), r2.node.encoded_delta(()), now), log3, "r3")
    assert all(decode(p).ask is None for p in sent)
    assert r3.counter_values()["relays_asked"] == 0
    have = r3.node.current_stack().versions()
    other = encode(StackMessage("r3", None, Stack(), 0, have=have, ask={"r1": "r4"}))
    got = _stacks(r2.on_message(KEYS.stack("r3"), other, now + 0.01), log2, "r2")
    assert all("r1" not in decode(p).stack.by_owner() for p in got)


def test_a_repeated_or_forged_ask_pushes_once_a_period_and_asks_go_at_once_once_a_period() -> None:
    _, _, r2, log2, _, now = _hearing_pair(2)
    version = r2.node.current_stack().versions()["r1"]
    lacking = encode(StackMessage("r3", None, Stack(), 0, have={}, ask={"r1": "r2"}))

    def pushed(t: float) -> list[tuple[int, int] | None]:
        """r1's versions in what r2 sends on r3's ask at ``t`` and at its tick just after."""
        got = _stacks(r2.on_message(KEYS.stack("r3"), lacking, t), log2, "r2")
        return [v for v in _slots_of(got + _tick(r2, t + 0.001), "r1") if v]

    assert pushed(now + 0.01) == [version]
    for i in range(9):  # the same ask, over and over, within the period: nothing more
        assert pushed(now + 0.02 + 0.05 * i) == []
    assert pushed(now + PERIOD + 0.05) == [version]  # still lacking a period later: lost, again
    # An asker sends at once at most once a gossip period, whatever forged digests make it ask.
    r3, log3 = _asker()
    _stacks(r3.start(0.0), log3, "r3")
    at_once = 0
    for i in range(40):  # 2 s: a new owner to ask for every 0.05 s
        t = 1.0 + 0.05 * i
        sent = _stacks(
            r3.on_message(KEYS.stack("x"), _digest("x", {f"o{i}": (1, 1)}), t), log3, "r3"
        )
        at_once += len(sent)
    assert r3.counter_values()["relays_asked"] == 40
    assert at_once <= 2.0 / PERIOD + 1, at_once


def test_two_relays_whose_digests_alternate_make_at_most_one_switch_a_period() -> None:
    """Two heard peers whose digests both show a version of an unheard owner that never comes
    (forged, or their pushes are lost): the asker switches between them at most once a gossip
    period, whatever the rate of their digests."""
    r3, log3 = _asker()
    _stacks(r3.start(0.0), log3, "r3")
    for i in range(80):  # 4 s: a digest every 0.05 s, from r2 and r4 in turn
        sender = ("r2", "r4")[i % 2]
        t = 1.0 + 0.05 * i
        _stacks(r3.on_message(KEYS.stack(sender), _digest(sender, {"r1": (1, 9)}), t), log3, "r3")
    asked = r3.counter_values()["relays_asked"]
    assert 2 <= asked <= 4.0 / PERIOD + 1, asked
    # One relay that never delivers is not asked again: its ask stands.
    r3, log3 = _asker()
    _stacks(r3.start(0.0), log3, "r3")
    for i in range(80):
        t = 1.0 + 0.05 * i
        _stacks(r3.on_message(KEYS.stack("r2"), _digest("r2", {"r1": (1, 9)}), t), log3, "r3")
    assert r3.counter_values()["relays_asked"] == 1


def test_what_an_asker_keeps_is_bounded_by_the_slot_limit() -> None:
    """Digests claiming ever new owners (forged) cannot grow the asks, or what the asker
    remembers of being behind, beyond ``max_slots``; its digest stays sendable."""
    r3, log3 = _asker()
    _stacks(r3.start(0.0), log3, "r3")
    limit = r3.node.limits.max_slots
    for i in range(300):
        claim = _digest("x", {f"o{j}": (1, 1) for j in range(i, i + 3)})
        _stacks(r3.on_message(KEYS.stack("x"), claim, 1.0 + 0.01 * i), log3, "r3")
    assert len(r3.gossip.asks) == limit and len(r3.gossip.behind) <= limit
    tick = [decode(a.payload) for a in r3.on_timer(4.5) if isinstance(a, Publish)]
    assert len(tick) == 1 and len(tick[0].ask or {}) == limit


def test_event_relay_pushes_an_asked_slot_on_arrival_and_coalesces_a_burst_in_one_window() -> None:
    r1, log1, r2, log2, frames, now = _hearing_pair(2)
    r3, log3 = _asker()
    _stacks(r3.start(now), log3, "r3")
    held = r2.node.current_stack().versions()
    sent = _stacks(r3.on_message(KEYS.stack("r2"), r2.node.encoded_delta(()), now), log3, "r3")
    assert [decode(p).ask for p in sent] == [{"r1": "r2"}]
    # The ask itself is answered at once, not with r2's next tick.
    answer = _stacks(r2.on_message(KEYS.stack("r3"), sent[0], now + 0.01), log2, "r2")
    assert [v for v in _slots_of(answer, "r1") if v] == [held["r1"]]
    assert r2.counter_values()["relay_pushes"] == 1
    # r1's next version goes on as soon as r2 merged it: no tick in between.
    now += 1.0
    versions = []
    for k in (2, 3):
        s1 = _stacks(
            r1.on_message(KEYS.frames("r1"), encode_frame(frames["r1"][k]), now), log1, "r1"
        )
        versions.append((s1[-1], r1.node.stack.versions()["r1"]))
    first = r2.on_message(KEYS.stack("r1"), versions[0][0], now)
    assert [v for v in _slots_of(_stacks(first, log2, "r2"), "r1") if v] == [versions[0][1]]
    # The next version, within the push window: held back, and a Flush asked for at its end.
    second = execute_journal_actions(
        log2, r2.on_message(KEYS.stack("r1"), versions[1][0], now + 0.001)
    )
    assert [a for a in second if isinstance(a, Publish)] == []
    assert [a.at for a in second if isinstance(a, Flush)] == [now + PUSH_WINDOW_S]
    flushed = [a.payload for a in r2.on_flush(now + PUSH_WINDOW_S) if isinstance(a, Publish)]
    assert [v for v in _slots_of(flushed, "r1") if v] == [versions[1][1]]
    assert r2.counter_values()["relay_pushes"] == 3
    # Flushed is sent: a second flush and the next tick carry no slot of r1.
    assert r2.on_flush(now + 2 * PUSH_WINDOW_S) == []
    assert all(v is None for v in _slots_of(_tick(r2, now + 0.1), "r1"))
    # r3 takes both pushes as they come.
    _stacks(r3.on_message(KEYS.stack("r2"), flushed[0], now + 0.01), log3, "r3")
    assert r3.node.stack.versions()["r1"] == versions[1][1]


def test_tick_relay_never_asks_for_a_flush() -> None:
    _, _, r2, _, _, now = _hearing_pair(2, relay="tick")
    r3, log3 = _asker()
    _stacks(r3.start(now), log3, "r3")
    sent = _stacks(r3.on_message(KEYS.stack("r2"), r2.node.encoded_delta(()), now), log3, "r3")
    actions = r2.on_message(KEYS.stack("r3"), sent[0], now + 0.01)
    assert not [a for a in actions if isinstance(a, (Publish, Flush))]
    assert r2.counter_values()["relay_pushes"] == 0


def test_an_event_push_goes_to_its_askers_alone_and_what_a_peer_lacks_to_everyone() -> None:
    """A push carries slots only asks send: it goes on ``Keys.stack_to`` to each asker (the
    other robots in range neither need it nor decode it); a stack with a slot some peer lacks
    after its chance goes on the robot's own key, to every robot in range."""
    r1, log1, r2, log2, frames, now = _hearing_pair(2)
    askers = {}
    s = load_scenario("paper")
    for robot in ("r3", "r4"):

        def make(robot: str = robot):  # type: ignore[no-untyped-def]
            # r4: a fourth robot, which the paper does not have, where r3 starts.
            return make_node(robot, s.robot("r3").start, belief_model(s), 4, BeliefConfig())

        log = MemoryLog()
        core = AgentCore(make, KEYS, CoreSettings(gossip_period=PERIOD), log.records)
        _stacks(core.start(now), log, robot)
        ask = _stacks(core.on_message(KEYS.stack("r2"), r2.node.encoded_delta(()), now), log, robot)
        assert [decode(p).ask for p in ask] == [{"r1": "r2"}]
        askers[robot] = ask[0]
    # r3's ask is answered at once, to r3 alone.
    first = execute_journal_actions(log2, r2.on_message(KEYS.stack("r3"), askers["r3"], now))
    assert [a.key for a in first if isinstance(a, Publish)] == [KEYS.stack_to("r2", "r3")]
    # Both ask; r1's next version goes to each of them, the same bytes, and to nobody else.
    now += 0.1
    execute_journal_actions(log2, r2.on_message(KEYS.stack("r4"), askers["r4"], now))
    for core_ask in ("r3", "r4"):
        execute_journal_actions(log2, r2.on_message(KEYS.stack(core_ask), askers[core_ask], now))
    now += 1.0
    s1 = _stacks(r1.on_message(KEYS.frames("r1"), encode_frame(frames["r1"][2]), now), log1, "r1")
    pushed = [
        a for a in execute_journal_actions(log2, r2.on_message(KEYS.stack("r1"), s1[-1], now))
        if isinstance(a, Publish)
    ]  # fmt: skip
    assert sorted(a.key for a in pushed) == [KEYS.stack_to("r2", "r3"), KEYS.stack_to("r2", "r4")]
    assert len({a.payload for a in pushed}) == 1
    assert decode(pushed[0].payload).stack.versions()["r1"] == r1.node.stack.versions()["r1"]
    # r2's own new slot, which every peer lacks after its chance: on r2's own key.
    own = execute_journal_actions(
        log2, r2.on_message(KEYS.frames("r2"), encode_frame(frames["r2"][2]), now + 0.2)
    )
    assert [a.key for a in own if isinstance(a, Publish) and "/stack/" in a.key] == [
        KEYS.stack("r2")
    ]
