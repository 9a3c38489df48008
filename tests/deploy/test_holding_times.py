"""Holding times (issue 47, item 1; docs/wire.md, "Holding times"; ``agents.ages``): every stack
says how old each of its slots is, summed over the robots that held it, each on its own clock;
an estimate reports the age of the peers' versions its fusion used. Real cores and codecs, three
robots on a line (r1 — r2 — r3), a made-up clock so that every millisecond is known."""

from __future__ import annotations

from agents.core import AgentCore, CoreSettings, Publish
from agents.runtime import MemoryLog, execute_journal_actions
from deploy.base.build import belief_model, make_node
from estimator.hybrid import BeliefConfig
from protocol.codec import StackMessage, decode, encode
from protocol.frames import encode_frame
from protocol.stack import Slot, Stack
from sim.loader import load_scenario
from sim.sensors import Simulator
from tests.deploy.test_delta_gossip import KEYS

PERIOD = 0.5


class Clock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _core(robot: str, clock: Clock) -> tuple[AgentCore, MemoryLog]:
    s = load_scenario("paper")
    model, start = belief_model(s), s.robot(robot).start

    def make():  # type: ignore[no-untyped-def]
        return make_node(robot, start, model, 4, BeliefConfig(), epoch=1)

    log = MemoryLog()
    settings = CoreSettings(gossip_period=PERIOD)
    return AgentCore(make, KEYS, settings, log.records, clock=clock), log


def _stacks(core: AgentCore, log: MemoryLog, actions: list[object]) -> list[bytes]:
    rest = execute_journal_actions(log, actions)  # type: ignore[arg-type]
    mine = (a for a in rest if isinstance(a, Publish) and KEYS.stack_sender(a.key) == core.robot)
    return [a.payload for a in mine]


def _line() -> tuple[dict[str, AgentCore], dict[str, MemoryLog], dict[str, Clock], dict]:  # type: ignore[type-arg]
    """r1, r2 and r3 of the paper scenario, each with its own clock; r2 has stepped twice with
    r1, r3 not yet; r3 asks r2 for r1 (it does not hear r1)."""
    frames = Simulator(load_scenario("paper"), 4).all_frames()
    clocks = {r: Clock() for r in ("r1", "r2", "r3")}
    made = {r: _core(r, clocks[r]) for r in clocks}
    cores, logs = {r: c for r, (c, _) in made.items()}, {r: lg for r, (_, lg) in made.items()}
    for r in ("r1", "r2", "r3"):
        _stacks(cores[r], logs[r], cores[r].start(0.0))
    for k in (0, 1):
        t = 1.0 + k
        for c in clocks.values():
            c.t = t
        s1 = _stacks(cores["r1"], logs["r1"], cores["r1"].on_message(
            KEYS.frames("r1"), encode_frame(frames["r1"][k]), t))  # fmt: skip
        s2 = _stacks(cores["r2"], logs["r2"], cores["r2"].on_message(
            KEYS.frames("r2"), encode_frame(frames["r2"][k]), t))  # fmt: skip
        _stacks(cores["r1"], logs["r1"], cores["r1"].on_message(KEYS.stack("r2"), s2[-1], t))
        _stacks(cores["r2"], logs["r2"], cores["r2"].on_message(KEYS.stack("r1"), s1[-1], t))
    digest = cores["r2"].node.encoded_delta(())
    asks = _stacks(cores["r3"], logs["r3"], cores["r3"].on_message(KEYS.stack("r2"), digest, 2.0))
    assert [decode(a).ask for a in asks] == [{"r1": "r2"}]
    _stacks(cores["r2"], logs["r2"], cores["r2"].on_message(KEYS.stack("r3"), asks[0], 2.0))
    return cores, logs, clocks, frames


def test_each_holder_adds_the_time_it_held_a_slot_and_the_estimate_reports_the_sum() -> None:
    cores, logs, clocks, frames = _line()
    r1, r2, r3 = cores["r1"], cores["r2"], cores["r3"]
    # r1's step 3: its batch starts at 3.000, the step ends at 3.020 (r1's clock).
    clocks["r1"].t = 3.020
    own = _stacks(
        r1, logs["r1"], r1.on_message(KEYS.frames("r1"), encode_frame(frames["r1"][2]), 3.0)
    )
    version = r1.node.stack.versions()["r1"]
    assert decode(own[-1]).age == {"r1": 0}  # sent as the step ended
    # r2 gets it at 3.030 but is busy until 3.045: it pushes it to r3, which asked for r1, as
    # 15 ms old.
    clocks["r2"].t = 3.045
    pushed = _stacks(r2, logs["r2"], r2.on_messages([(KEYS.stack("r1"), own[-1])], 3.045, [3.030]))
    assert [decode(p).age for p in pushed if "r1" in decode(p).stack.versions()] == [{"r1": 15}]
    # A tick that sends the same slot later says it is older by as much (r3's digest lacks it).
    clocks["r2"].t = 3.245
    later = [p for p in (a.payload for a in r2.on_timer(3.245) if isinstance(a, Publish))]
    assert all(decode(p).age in (None, {"r1": 215}) for p in later)
    # r3 gets the push at 7.000 (its own clock, unlike r2's) and steps at 7.300, its step ending
    # at 7.320: r1's version it fused is 15 + 320 ms old then.
    _stacks(r3, logs["r3"], r3.on_messages([(KEYS.stack("r2"), pushed[-1])], 7.0, [7.0]))
    assert r3.node.stack.versions()["r1"] == version
    clocks["r3"].t = 7.320
    actions = r3.on_message(KEYS.frames("r3"), encode_frame(frames["r3"][0]), 7.3)
    assert r3.node.distributed.stamps.get("r1") == version[1]
    assert r3.ages.report({"r1": version[1]}, 7.320)["peer_age_max_ms"] == 335
    estimates = [
        a for a in execute_journal_actions(logs["r3"], actions)
        if isinstance(a, Publish) and a.key == KEYS.estimate("r3")
    ]  # fmt: skip
    assert estimates
    # The estimate's counters: r1 is the one peer D fused (r2's own slot has not reached r3).
    fused = {o: s for o, s in r3.node.distributed.stamps.items() if o != "r3"}
    assert set(fused) == {"r1"}
    counters = r3.counter_values()
    assert (counters["peers_aged"], counters["peer_age_median_ms"]) == (1, 335)
    assert counters["peer_age_max_ms"] == 335


def test_a_version_that_came_without_an_age_is_never_given_one() -> None:
    """A stack from an agent of an earlier version (or a full stack) says no ages: a relay sends
    that slot on without ``age`` at all, and the estimate leaves it out."""
    cores, logs, clocks, frames = _line()
    r1, r2, r3 = cores["r1"], cores["r2"], cores["r3"]
    clocks["r1"].t = 3.02
    _stacks(r1, logs["r1"], r1.on_message(KEYS.frames("r1"), encode_frame(frames["r1"][2]), 3.0))
    held = r1.node.current_stack()
    plain = encode(StackMessage("r1", None, Stack(tuple(s for s in held if s.owner == "r1")), 3,
                                have=held.versions()))  # fmt: skip
    assert decode(plain).age is None
    clocks["r2"].t = 3.05
    pushed = _stacks(r2, logs["r2"], r2.on_messages([(KEYS.stack("r1"), plain)], 3.05, [3.03]))
    relayed = [decode(p) for p in pushed if "r1" in decode(p).stack.versions()]
    assert relayed and all(m.age is None for m in relayed)
    _stacks(r3, logs["r3"], r3.on_message(KEYS.stack("r2"), pushed[-1], 3.06))
    clocks["r3"].t = 3.4
    r3.on_message(KEYS.frames("r3"), encode_frame(frames["r3"][0]), 3.38)
    assert r3.node.distributed.stamps.get("r1") == held.versions()["r1"][1]
    assert r3.ages.report({"r1": held.versions()["r1"][1]}, 3.4)["peers_aged"] == 0


def _owned(owner: str, stamp: int, summary: object, age: int) -> bytes:
    slot = Slot(owner, stamp, summary)  # type: ignore[arg-type]
    have = {owner: (0, stamp)}
    return encode(StackMessage(owner, None, Stack((slot,)), stamp, have=have, age={owner: age}))


def test_a_full_stack_lets_go_of_the_oldest_information_not_of_the_lowest_stamp() -> None:
    """Real time, two peers' slots kept (``keep_slots = 3``): a robot that started later (lower
    stamps) gets no place while both held peers are heard of, and takes the place of the one
    whose information grew older than a digest's life (1.5 s at a 0.5 s gossip period) beyond
    its own — which the stamps alone would never give it (its stamp stays below)."""
    s = load_scenario("paper")
    frames = Simulator(s, 4).all_frames()
    clock = Clock()
    model = belief_model(s)
    donor = make_node("r3", s.robot("r3").start, model, 4, BeliefConfig())
    for f in frames["r3"][:4]:
        donor.on_frame(f)
    summary = decode(donor.outgoing() or b"").stack.by_owner()["r3"].summary

    def make():  # type: ignore[no-untyped-def]
        return make_node("r1", s.robot("r1").start, model, 4, BeliefConfig(), keep_slots=3)

    log = MemoryLog()
    core = AgentCore(make, KEYS, CoreSettings(gossip_period=PERIOD), log.records, clock=clock)
    core.start(0.0)
    assert core.node.age_margin_ms == 1500
    t = 10.0
    for stamp in (40, 41):
        for owner in ("a", "b"):
            core.on_messages([(KEYS.stack(owner), _owned(owner, stamp, summary, 20))], t, [t])
        t += 0.5
    assert {sl.owner for sl in core.node.stack} == {"a", "b"}
    late = _owned("c", 3, summary, 20)  # started 38 steps later, as fresh as the others
    core.on_messages([(KEYS.stack("c"), late)], t, [t])
    assert {sl.owner for sl in core.node.stack} == {"a", "b"}
    # b falls silent; a goes on. 1.6 s after b's last version, c's next one takes b's place.
    for stamp in (42, 43, 44):
        core.on_messages([(KEYS.stack("a"), _owned("a", stamp, summary, 20))], t, [t])
        t += 0.5
    assert t - 10.5 > 1.52  # b's version: 20 ms old at 10.5
    core.on_messages([(KEYS.stack("c"), _owned("c", 6, summary, 20))], t, [t])
    assert {sl.owner for sl in core.node.stack} == {"a", "c"}
    assert core.counter_values()["slots_evicted"] == 1
