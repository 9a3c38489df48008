"""Delta gossip (issue 14, item 1; docs/wire.md): a stack carries only what some peer lacks by
the digests peers send, and the fleet's beliefs are those of full-stack gossip — bit for bit in
lock-step — with fewer bytes; a peer that joins late gets every slot it lacks. Real agent
processes over Zenoh on loopback; the core-level test uses real cores and codecs."""

from __future__ import annotations

from pathlib import Path

import pytest

from agents.core import AgentCore, CoreSettings, Publish
from agents.gossip import DIGEST_LIFE, DIGEST_REFRESH
from agents.runtime import MemoryLog, execute_journal_actions
from agents.transport.base import Keys
from deploy.base.build import belief_model, make_node
from deploy.launch import LaunchPlan, launch
from estimator.hybrid import BeliefConfig
from estimator.models import SensorFrame
from protocol.codec import decode
from protocol.frames import encode_frame
from sim.loader import load_scenario, parse_scenario
from sim.sensors import Simulator
from tests.deploy.test_launch import assert_same_snapshot, world_text

KEYS = Keys("t")


@pytest.mark.slow
def test_delta_and_full_gossip_give_the_same_beliefs_in_lockstep_on_a_chain(
    tmp_path: Path,
) -> None:
    """Six robots 8 m apart, range 10 m: a chain, every slot relayed over up to four hops."""
    text = world_text("line6", 6, 8.0, 10, 0.05)
    scenario = parse_scenario(text, str(tmp_path / "line6.toml"))
    ids = list(scenario.robot_ids)
    runs = {}
    for gossip in ("full", "delta", "ask"):  # lock-step makes no asks: "ask" is "delta" there
        plan = LaunchPlan(
            scenario, 3, ids, tmp_path / gossip, keep_estimates=True, stack_gossip=gossip
        )
        runs[gossip] = launch(plan)
    full = runs["full"].collected
    for gossip in ("delta", "ask"):
        other = runs[gossip].collected
        assert (
            set(full.estimates)
            == set(other.estimates)
            == {(r, k) for r in ids for k in range(1, scenario.steps + 1)}
        )
        for key, est in full.estimates.items():
            for belief, snap in est.beliefs.items():
                got = other.estimates[key].beliefs[belief]
                assert_same_snapshot(got, snap, f"{gossip} {key} {belief}")
        assert all(c["relays_asked"] == 0 for c in other.counters.values())
    final = full.estimates[("r6", scenario.steps)].beliefs["distributed"]
    assert len(final.object_ids) == 12  # r1's objects reached r6 over four relays
    sent = {g: sum(c["bytes_sent"] for c in runs[g].collected.counters.values()) for g in runs}
    print(f"bytes sent after steps: full {sent['full']:,}, delta {sent['delta']:,}")
    # In lock-step a round must carry whatever any robot may lack when it merges the round (the
    # conductor names the listeners only after): never more than a full stack. The savings are
    # real time's (bench_agents).
    assert sent["delta"] <= sent["full"], sent


def _core(robot: str, epoch: int = 1, relay: str = "event") -> tuple[AgentCore, MemoryLog]:
    s = load_scenario("paper")
    model = belief_model(s)
    start = s.robot(robot).start

    def make():  # type: ignore[no-untyped-def]
        return make_node(robot, start, model, 4, BeliefConfig(), epoch=epoch)

    log = MemoryLog()
    settings = CoreSettings(gossip_period=0.5, relay=relay)
    return AgentCore(make, KEYS, settings, log.records), log


def _stacks(actions: list[object], log: MemoryLog, robot: str) -> list[bytes]:
    """The stacks ``robot`` publishes, to every robot in range or to one alone (a push)."""
    rest = execute_journal_actions(log, actions)  # type: ignore[arg-type]
    return [a.payload for a in rest if isinstance(a, Publish) and KEYS.stack_sender(a.key) == robot]


_Pair = tuple[AgentCore, MemoryLog, AgentCore, MemoryLog, dict[str, list[SensorFrame]], float]


def _tick(core: AgentCore, t: float) -> list[bytes]:
    """The stacks ``core``'s gossip tick at ``t`` publishes."""
    return [a.payload for a in core.on_timer(t) if isinstance(a, Publish)]


def _hearing_pair(steps: int, relay: str = "event") -> _Pair:
    """r1 and r2 of the paper scenario after ``steps`` steps, one a second, each hearing the
    other's stack: (r1, its log, r2, its log, the frames, the time of the last step); both
    relay asked slots as ``relay`` says."""
    frames = Simulator(load_scenario("paper"), 4).all_frames()
    r1, log1 = _core("r1", relay=relay)
    r2, log2 = _core("r2", relay=relay)
    now = 0.0
    for k in range(steps):
        now += 1.0
        s1 = _stacks(
            r1.on_message(KEYS.frames("r1"), encode_frame(frames["r1"][k]), now), log1, "r1"
        )
        s2 = _stacks(
            r2.on_message(KEYS.frames("r2"), encode_frame(frames["r2"][k]), now), log2, "r2"
        )
        _stacks(r1.on_message(KEYS.stack("r2"), s2[-1], now), log1, "r1")
        _stacks(r2.on_message(KEYS.stack("r1"), s1[-1], now), log2, "r2")
    return r1, log1, r2, log2, frames, now


def test_a_peer_that_joins_late_gets_every_slot_it_lacks_and_nothing_else_is_resent() -> None:
    r1, log1, r2, _, _, now = _hearing_pair(3)
    held = r1.node.current_stack().versions()
    assert set(held) == {"r1", "r2"}
    # r2's digest says it holds everything r1 has: a tick sends r1's digest alone.
    now += 1.0
    _stacks(r1.on_message(KEYS.stack("r2"), r2.node.encoded_delta(()), now), log1, "r1")
    tick = [a.payload for a in r1.on_timer(now) if isinstance(a, Publish)]
    assert [len(decode(t).stack) for t in tick] == [0]
    assert decode(tick[0]).have == held
    # r3 starts with an empty journal: its first stack is an empty digest. r1 answers at once
    # with every slot r3 lacks — its own and the one it relays for r2.
    r3, log3 = _core("r3")
    first = _stacks(r3.start(now), log3, "r3")
    assert decode(first[0]).have == {}
    now += 1.0
    answer = _stacks(r1.on_message(KEYS.stack("r3"), first[0], now), log1, "r1")
    assert len(answer) == 1
    got = decode(answer[0])
    assert got.stack.versions() == held
    _stacks(r3.on_message(KEYS.stack("r1"), answer[0], now), log3, "r3")
    assert r3.node.stack.versions() == held
    # Sent once. The answer carried r1's digest too, so the next tick sends nothing; the tick
    # when the digest is due again carries it alone.
    skipped = r1.gossip.digests_skipped
    assert [a for a in r1.on_timer(now + 0.1) if isinstance(a, Publish)] == []
    assert r1.gossip.digests_skipped == skipped + 1
    due = now + DIGEST_REFRESH * r1.settings.gossip_period
    later = [a.payload for a in r1.on_timer(due) if isinstance(a, Publish)]
    assert len(later) == 1 and len(decode(later[0]).stack) == 0


def test_a_relayed_version_goes_once_the_peer_had_its_chance_and_again_only_if_lost() -> None:
    """Real time: a peer whose digest lacks a version this robot relays gets it only once it had
    its chance to get it from the owner itself — a digest of it that came a gossip period after
    the version came here — then at once; and again only if a digest a period after the send
    still lacks it (the send was lost). The own slot's new version goes at once."""
    from protocol.codec import StackMessage, encode
    from protocol.stack import Stack

    r1, log1, r2, log2, frames, now = _hearing_pair(2)
    period = r2.settings.gossip_period
    now += 1.0
    stepped = r1.on_message(KEYS.frames("r1"), encode_frame(frames["r1"][2]), now)
    _stacks(r2.on_message(KEYS.stack("r1"), _stacks(stepped, log1, "r1")[-1], now), log2, "r2")
    held = r2.node.current_stack().versions()
    version = held["r1"]
    assert version == r1.node.stack.versions()["r1"]
    # r3 holds everything r2 holds but r1's newest version: the one before it.
    have = {**held, "r1": (version[0], version[1] - 1)}
    lacking = encode(StackMessage("r3", None, Stack(), 0, have=have))

    def sent(messages: list[object]) -> list[dict[str, tuple[int, int]]]:
        return [decode(p).stack.versions() for p in _stacks(messages, log2, "r2")]

    def digest(t: float) -> list[dict[str, tuple[int, int]]]:
        return sent(r2.on_message(KEYS.stack("r3"), lacking, t))

    assert digest(now + 0.1) == []  # r3 may hear r1: not yet
    assert all("r1" not in v for v in sent(r2.on_timer(now + 0.2)))
    assert digest(now + period + 0.01) == [{"r1": version}]  # its chance went by: at once
    assert digest(now + period + 0.1) == []  # just sent
    assert all("r1" not in v for v in sent(r2.on_timer(now + period + 0.2)))
    assert digest(now + 2 * period + 0.05) == [{"r1": version}]  # still lacking: lost, again
    # r2's own new slot goes at once, with the stack of the step that made it.
    own = r2.on_message(KEYS.frames("r2"), encode_frame(frames["r2"][2]), now + 2 * period + 0.1)
    assert sent(own) == [{"r2": r2.node.current_stack().versions()["r2"]}]


def test_an_unchanged_digest_goes_only_when_due() -> None:
    """Real time: a tick with nothing new sends the digest alone only when it changed since it
    last went (by a tick, or with a stack: a stack's ``have`` is the digest), when that was
    DIGEST_REFRESH gossip periods ago (peers keep counting this robot), or to pull: a period
    after a peer's digest first showed a version this robot lacks — the peer pushes a slot only
    to a digest that comes a period after the slot came to it — once."""
    r1, log1, r2, log2, frames, now = _hearing_pair(2)
    _stacks(r1.on_message(KEYS.stack("r2"), r2.node.encoded_delta(()), now), log1, "r1")
    period = r1.settings.gossip_period

    def tick(t: float) -> list[bytes]:
        return [a.payload for a in r1.on_timer(t) if isinstance(a, Publish)]

    # r1's stack of its step carried this very digest, at ``now``.
    assert tick(now) == [] and r1.gossip.digests_skipped == 1
    assert tick(now + 0.1) == [] and r1.gossip.digests_skipped == 2  # unchanged, 0.1 s later
    assert tick(now + (DIGEST_REFRESH - 0.05) * period) == []
    assert len(tick(now + DIGEST_REFRESH * period)) == 1  # due again
    now += DIGEST_REFRESH * period
    assert tick(now + 0.1) == []
    # r2 steps; r1 hears only its digest, which holds a version of r2 that r1 lacks. r1 pulls
    # (sends its digest) a period after it first saw that version, not before, and once.
    _stacks(r2.on_message(KEYS.frames("r2"), encode_frame(frames["r2"][2]), now), log2, "r2")
    _stacks(r1.on_message(KEYS.stack("r2"), r2.node.encoded_delta(()), now + 0.2), log1, "r1")
    assert tick(now + 0.3) == []
    _stacks(r1.on_message(KEYS.stack("r2"), r2.node.encoded_delta(()), now + 0.4), log1, "r1")
    assert tick(now + 0.2 + period - 0.01) == []  # seen again: still from its first sight
    pulled = tick(now + 0.2 + period)
    assert len(pulled) == 1 and len(decode(pulled[0]).stack) == 0
    assert tick(now + 0.3 + period) == []
    assert r1.counter_values()["digests_skipped"] == r1.gossip.digests_skipped == 7
    # r2 answers the pull with its slot, at once.
    pushed = _stacks(r2.on_message(KEYS.stack("r1"), pulled[0], now + 0.25 + period), log2, "r2")
    assert [decode(p).stack.versions().get("r2") for p in pushed] == [
        r2.node.stack.versions()["r2"]
    ]
    _stacks(r1.on_message(KEYS.stack("r2"), pushed[0], now + 0.3 + period), log1, "r1")
    assert r1.node.stack.versions() == r2.node.stack.versions()
    # r1 steps: the stack of its new own slot carries its digest (a tick right after it would
    # send nothing, as at the start); r1 merges r2's next slot before any tick: its digest
    # changed since the stack went, and the next tick sends it.
    now += 2.0
    _stacks(r2.on_message(KEYS.frames("r2"), encode_frame(frames["r2"][3]), now), log2, "r2")
    own = _stacks(r1.on_message(KEYS.frames("r1"), encode_frame(frames["r1"][2]), now), log1, "r1")
    _stacks(r2.on_message(KEYS.stack("r1"), own[-1], now + 0.1), log2, "r2")
    got = r1.on_message(KEYS.stack("r2"), r2.node.encoded_delta(("r2",)), now + 0.1)
    assert _stacks(got, log1, "r1") == []  # r2 lacks nothing of r1's
    assert r1.node.stack.versions() == r2.node.stack.versions()
    sent = tick(now + 0.15)
    assert len(sent) == 1 and len(decode(sent[0]).stack) == 0
    assert decode(sent[0]).have == r1.node.stack.versions()
    assert tick(now + 0.2) == []


def test_a_tick_sends_a_digest_a_merge_changed_before_a_refresh_is_due() -> None:
    """Real time: a merge that changes the holdings makes the next tick send the digest alone,
    long before DIGEST_REFRESH periods have gone by (peers learn at once what they may pull)."""
    r1, log1, r2, log2, frames, now = _hearing_pair(4)
    _stacks(r1.on_message(KEYS.stack("r2"), r2.node.encoded_delta(()), now), log1, "r1")

    assert len(_tick(r1, now)) == 1  # r1 merged r2's slot after the stack of its step went
    assert _tick(r1, now + 0.05) == []
    stepped = _stacks(
        r2.on_message(KEYS.frames("r2"), encode_frame(frames["r2"][4]), now + 0.1), log2, "r2"
    )
    assert _stacks(r1.on_message(KEYS.stack("r2"), stepped[-1], now + 0.1), log1, "r1") == []
    assert r1.node.stack.versions() == r2.node.stack.versions()
    sent = _tick(r1, now + 0.2)
    assert len(sent) == 1 and len(decode(sent[0]).stack) == 0
    assert decode(sent[0]).have == r1.node.current_stack().versions()


def test_a_newer_version_in_a_peers_digest_starts_the_pull_period_over() -> None:
    """Real time: the ticks pull a version a peer's digest shows a gossip period after they
    first saw it; a newer version of the same slot starts that period over (the peer pushes only
    to a digest that comes a period after the newest one came to it)."""
    r1, log1, r2, log2, frames, now = _hearing_pair(4)
    period = r1.settings.gossip_period

    assert len(_tick(r1, now)) == 1 and _tick(r1, now + 0.05) == []  # as above
    for k, t in ((4, now + 0.1), (5, now + 0.3)):  # r1 hears r2's digests only
        _stacks(r2.on_message(KEYS.frames("r2"), encode_frame(frames["r2"][k]), t), log2, "r2")
        _stacks(r1.on_message(KEYS.stack("r2"), r2.node.encoded_delta(()), t), log1, "r1")
    assert _tick(r1, now + 0.1 + period + 0.01) == []  # a period after the first: too early
    pulled = _tick(r1, now + 0.3 + period + 0.01)
    assert len(pulled) == 1 and len(decode(pulled[0]).stack) == 0


def test_a_version_once_held_no_longer_times_the_pulls() -> None:
    """Real time: a version a peer's digest showed is forgotten once it is held here, so that the
    pull period of the next version lacked (another owner's) counts from its own first sight."""
    from protocol.codec import StackMessage, encode
    from protocol.stack import Stack

    r1, log1, r2, log2, frames, now = _hearing_pair(4)
    period = r1.settings.gossip_period

    assert len(_tick(r1, now)) == 1 and _tick(r1, now + 0.05) == []  # as above
    stepped = r2.on_message(KEYS.frames("r2"), encode_frame(frames["r2"][4]), now + 0.1)
    _stacks(r1.on_message(KEYS.stack("r2"), r2.node.encoded_delta(()), now + 0.1), log1, "r1")
    slot = _stacks(stepped, log2, "r2")[-1]
    _stacks(r1.on_message(KEYS.stack("r2"), slot, now + 0.2), log1, "r1")
    assert r1.node.stack.versions() == r2.node.stack.versions()
    assert len(_tick(r1, now + 0.25)) == 1  # the changed digest
    have = {**r1.node.current_stack().versions(), "r3": (1, 5)}
    claim = encode(StackMessage("r3", None, Stack(), 0, have=have))
    assert _stacks(r1.on_message(KEYS.stack("r3"), claim, now + 0.3), log1, "r1") == []
    assert _tick(r1, now + 0.1 + period + 0.01) == []  # r2's version is held: it times nothing
    assert len(_tick(r1, now + 0.3 + period + 0.01)) == 1  # r3's, a period after it was first seen


def test_a_peer_whose_digest_is_older_than_digest_life_gets_nothing() -> None:
    """Real time: a peer counts while its digest is fresher than DIGEST_LIFE gossip periods;
    then it is out of reach and its lacks send nothing, until its next digest."""
    from protocol.codec import StackMessage, encode
    from protocol.stack import Stack

    r1, log1, _, _, frames, now = _hearing_pair(4)
    period = r1.settings.gossip_period
    held = r1.node.current_stack().versions()
    assert "r1" in held
    digest = encode(StackMessage("r3", None, Stack(), 0, have=held))
    assert _stacks(r1.on_message(KEYS.stack("r3"), digest, now + 0.1), log1, "r1") == []
    # r2's digest came at ``now``, r3's at now + 0.1: both out of reach by this step.
    later = now + 0.1 + DIGEST_LIFE * period + 0.05
    step = _stacks(
        r1.on_message(KEYS.frames("r1"), encode_frame(frames["r1"][4]), later), log1, "r1"
    )
    own = r1.node.current_stack().versions()["r1"]
    assert own > held["r1"] and [decode(s).stack.versions() for s in step] == [{}]
    # r3 is heard again, still without r1's new version: it goes at once.
    back = _stacks(r1.on_message(KEYS.stack("r3"), digest, later + 0.1), log1, "r1")
    assert [decode(s).stack.versions() for s in back] == [{"r1": own}]


def test_digests_of_made_up_senders_are_bounded() -> None:
    """A flood of stacks from ever new sender ids (each on its own key) cannot grow what an agent
    keeps of its peers' digests beyond the stack's slot limit."""
    from protocol.codec import StackMessage, encode
    from protocol.stack import Stack

    r1, _ = _core("r1")
    for i in range(300):
        sender = f"x{i}"
        data = encode(StackMessage(sender, None, Stack(), 0, have={f"o{i}": (1, 1)}))
        r1.on_message(KEYS.stack(sender), data, float(i))
    assert len(r1.gossip.digests) == r1.node.limits.max_slots
    assert "x299" in r1.gossip.digests and "x0" not in r1.gossip.digests
    # Nor what it keeps of the versions they claim to hold (each a version r1 lacks).
    assert len(r1.gossip.wanted) == r1.node.limits.max_slots
    assert "o299" in r1.gossip.wanted and "o0" not in r1.gossip.wanted


def test_a_roster_fleet_wants_only_roster_robots_slots_from_roster_robots() -> None:
    """A digest from outside the roster, or versions of robots outside it, never make an agent
    pull: no such slot is ever taken, so it would want them for good."""
    from protocol.codec import StackMessage, encode
    from protocol.stack import Stack

    s = load_scenario("paper")
    roster = frozenset(s.robot_ids)

    def make():  # type: ignore[no-untyped-def]
        return make_node(
            "r1", s.robot("r1").start, belief_model(s), 4, BeliefConfig(), roster=roster
        )

    r1 = AgentCore(make, KEYS, CoreSettings(gossip_period=0.5), MemoryLog().records)
    outsider = encode(StackMessage("x1", None, Stack(), 0, have={"r2": (1, 5)}))
    r1.on_message(KEYS.stack("x1"), outsider, 1.0)
    # Nor does an outsider's digest count as a peer's: what it lacks is never sent for it (an
    # outsider's empty digests would otherwise have every robot re-send its whole stack).
    assert "x1" not in r1.gossip.digests
    claims = encode(StackMessage("r2", None, Stack(), 0, have={"x9": (1, 5), "r3": (1, 2)}))
    r1.on_message(KEYS.stack("r2"), claims, 1.0)
    assert set(r1.gossip.wanted) == {"r3"}


def test_ever_newer_claimed_versions_add_no_digest_sends() -> None:
    """A peer whose digests claim an ever newer version of a slot (forged: it never comes) does
    not make an agent send more than its refreshing digests, however often its digests come."""
    from protocol.codec import StackMessage, encode
    from protocol.stack import Stack

    r1, log1 = _core("r1")
    period = r1.settings.gossip_period
    _stacks(r1.start(0.0), log1, "r1")
    pulls = 0
    t = 0.0
    for i in range(400):  # 20 s: a claim every 0.05 s, a tick every period
        t = round(t + 0.05, 2)
        claim = encode(StackMessage("r2", None, Stack(), 0, have={"r2": (1, 10**6 + i)}))
        _stacks(r1.on_message(KEYS.stack("r2"), claim, t), log1, "r1")
        if i % round(period / 0.05) == 0:
            pulls += len([a for a in r1.on_timer(t) if isinstance(a, Publish)])
    # Only the refreshes go: the version it lacks is always new, so no peer could push it yet.
    assert pulls <= t / (DIGEST_REFRESH * period) + 1, pulls
    assert len(r1.gossip.wanted) == 1
