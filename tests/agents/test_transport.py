"""Transports: key expressions, the bounded drop-oldest inbox, the in-memory bus, and a real pair
of Zenoh sessions on loopback (put → inbox, liveliness alive/gone, no multicast discovery)."""

from __future__ import annotations

import asyncio
import dataclasses
import threading
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import zenoh

from agents.transport import Inbox, Keys, MemoryBus, MemoryTransport, Message
from agents.transport.base import Kind, key_matches
from agents.transport.subscriptions import StackSubscriptions
from agents.transport.zenoh_transport import (
    CLOSE_WAIT_S,
    ZenohSettings,
    ZenohTransport,
    settings_for,
)
from deploy.launch import free_ports

KEYS = Keys("t1")


async def _until(predicate: Callable[[], bool], timeout: float, poll: float = 0.01) -> None:
    async with asyncio.timeout(timeout):
        while not predicate():
            await asyncio.sleep(poll)


# --------------------------------------------------------------------------- keys


@pytest.mark.parametrize(
    ("expr", "key", "matches"),
    [
        ("a/b/c", "a/b/c", True),
        ("a/b/c", "a/b", False),
        ("a/b", "a/b/c", False),
        ("a/*/c", "a/x/c", True),
        ("a/*/c", "a/x/y/c", False),
        ("a/*", "a", False),
        ("a/**", "a", True),
        ("a/**", "a/b/c/d", True),
        ("a/**/d", "a/d", True),
        ("a/**/d", "a/b/c/d", True),
        ("a/**/d", "a/b/c/e", False),
        ("**", "x/y", True),
        ("semfleet/f/stack/*", "semfleet/f/stack/r1", True),
        ("semfleet/f/stack/*", "semfleet/g/stack/r1", False),
        ("semfleet/f/ctl/**", "semfleet/f/ctl/need/r2", True),
    ],
)
def test_key_matches_follows_zenoh_wildcards(expr: str, key: str, matches: bool) -> None:
    assert key_matches(expr, key) is matches


def test_keys_live_under_one_fleet_prefix() -> None:
    assert KEYS.stack("r1") == "semfleet/t1/stack/r1"
    assert KEYS.alive("r2") == "semfleet/t1/alive/r2"
    assert KEYS.frames("r3") == "semfleet/t1/frames/r3"
    assert KEYS.estimate("*") == "semfleet/t1/estimate/*"
    assert KEYS.ctl("need", "r1") == "semfleet/t1/ctl/need/r1"
    assert KEYS.ctl("**") == "semfleet/t1/ctl/**"
    assert KEYS.robot_of(KEYS.stack("r_9-x")) == "r_9-x"
    assert KEYS.robot_of("semfleet/t1/stack/bad id") is None


@pytest.mark.parametrize("bad", ["", "a b", "x/y", "x" * 33, "**"])
def test_keys_refuse_invalid_fleet_and_robot_ids(bad: str) -> None:
    with pytest.raises(ValueError, match="1–32"):
        Keys(bad)
    with pytest.raises(ValueError, match="robot id"):
        KEYS.stack(bad)


# --------------------------------------------------------------------------- inbox


def _m(i: int) -> Message:
    return Message(f"k/{i}", bytes([i]))


def test_inbox_full_drops_the_oldest_and_counts_it() -> None:
    inbox = Inbox(3)
    for i in range(5):
        inbox.put(_m(i))
    assert len(inbox) == 3
    assert (inbox.dropped, inbox.received) == (2, 5)
    assert inbox.drain() == [_m(2), _m(3), _m(4)]
    assert len(inbox) == 0
    assert inbox.drain() == []


def test_inbox_bounds_its_bytes_dropping_older_messages_of_the_same_key_first() -> None:
    """Bounded in payload bytes too: a message that does not fit makes room by dropping older
    messages on its own key first (stacks are latest-wins), then the oldest of all; one larger
    than the whole bound is dropped at once. Every drop is counted."""
    inbox = Inbox(100, max_bytes=10)
    b1, a1, a2 = Message("b", b"b" * 4), Message("a", b"a" * 4), Message("a", b"A" * 4)
    for m in (b1, a1, a2):  # a2 does not fit: a1 goes, though b1 is older
        inbox.put(m)
    assert (inbox.drain(), inbox.dropped) == ([b1, a2], 1)
    c1 = Message("c", b"c" * 4)
    for m in (b1, a1, c1):  # no older c: the oldest of all goes
        inbox.put(m)
    assert (inbox.drain(), inbox.dropped) == ([a1, c1], 2)
    inbox.put(Message("d", b"d" * 11))  # larger than the bound on its own
    assert (len(inbox), inbox.bytes, inbox.dropped, inbox.received) == (0, 0, 3, 7)


def test_inbox_capacity_must_be_positive() -> None:
    with pytest.raises(ValueError, match="capacity"):
        Inbox(0)


@pytest.mark.asyncio
async def test_inbox_get_and_wait_block_until_a_message_arrives() -> None:
    inbox = Inbox(4)
    assert await inbox.wait(0.01) is False
    asyncio.get_running_loop().call_later(0.02, inbox.put, _m(1))
    assert await inbox.get() == _m(1)
    asyncio.get_running_loop().call_later(0.02, inbox.put, _m(2))
    assert await inbox.wait(5.0) is True
    assert await inbox.wait(0.0) is True  # already queued: no waiting
    assert inbox.drain() == [_m(2)]


@pytest.mark.asyncio
async def test_inboxes_ring_one_doorbell_from_other_threads_once_per_drain() -> None:
    """The agent's main loop waits on one event for all its inboxes: a put from a transport's
    thread into any of them rings it; puts that follow before a drain do not ring again (one
    wake-up per batch); after the drain the next put rings again."""
    loop = asyncio.get_running_loop()
    a, b, doorbell = Inbox(8), Inbox(8), asyncio.Event()
    for inbox in (a, b):
        inbox.bind(loop)
        inbox.ring(doorbell)
    rings = 0
    original = doorbell.set

    def counted() -> None:
        nonlocal rings
        rings += 1
        original()

    doorbell.set = counted  # type: ignore[method-assign]
    await loop.run_in_executor(None, b.put, _m(1))
    await asyncio.wait_for(doorbell.wait(), 5.0)
    await loop.run_in_executor(None, b.put, _m(2))  # not drained yet: no second ring
    await asyncio.sleep(0.01)
    assert rings == 1 and len(b) == 2
    doorbell.clear()
    assert a.drain() == [] and b.drain() == [_m(1), _m(2)]
    await loop.run_in_executor(None, a.put, _m(3))
    await asyncio.wait_for(doorbell.wait(), 5.0)
    assert rings == 2 and a.drain() == [_m(3)]


@pytest.mark.asyncio
async def test_an_inbox_wakes_for_its_loud_keys_only_and_keeps_the_others_for_the_next_batch() -> (
    None
):
    loop = asyncio.get_running_loop()
    inbox, doorbell = Inbox(8), asyncio.Event()
    inbox.bind(loop)
    inbox.ring(doorbell)
    inbox.wake_for(frozenset({"k/loud"}))
    quiet, loud = Message("k/quiet", b"q"), Message("k/loud", b"l")
    await loop.run_in_executor(None, inbox.put, quiet)
    await asyncio.sleep(0.02)
    assert not doorbell.is_set() and len(inbox) == 1  # queued, silently
    await loop.run_in_executor(None, inbox.put, loud)
    await asyncio.wait_for(doorbell.wait(), 5.0)
    assert inbox.drain() == [quiet, loud]  # in arrival order, the quiet one with the batch
    doorbell.clear()
    await loop.run_in_executor(None, inbox.put, quiet)
    await asyncio.sleep(0.02)
    assert not doorbell.is_set()
    inbox.wake_for(frozenset({"k/quiet"}))  # a key turned loud: what waits on it wakes now
    assert doorbell.is_set() and inbox.drain() == [quiet]
    inbox.wake_for(None)
    doorbell.clear()
    await loop.run_in_executor(None, inbox.put, quiet)
    await asyncio.wait_for(doorbell.wait(), 5.0)  # every key wakes again


# --------------------------------------------------------------------------- memory


@pytest.mark.asyncio
async def test_memory_transport_delivers_on_the_loop_to_matching_subscriptions_only() -> None:
    bus = MemoryBus()
    a, b = MemoryTransport(bus), MemoryTransport(bus)
    stacks, frames_r2 = Inbox(8), Inbox(8)
    b.subscribe(KEYS.stack("*"), stacks)
    b.subscribe(KEYS.frames("r2"), frames_r2)
    await a.open()
    await b.open()
    payload = bytearray(b"stack of r1")
    a.publish(KEYS.stack("r1"), payload)
    a.publish(KEYS.frames("r1"), b"not for r2")
    a.publish(KEYS.frames("r2"), b"frame")
    payload[:] = b"overwritten"  # the transport copied the bytes
    assert len(stacks) == 0  # scheduled on the loop, never delivered synchronously
    await asyncio.sleep(0)
    assert stacks.drain() == [Message(KEYS.stack("r1"), b"stack of r1")]
    assert frames_r2.drain() == [Message(KEYS.frames("r2"), b"frame")]
    assert (a.sent, bus.published) == (3, 3)


@pytest.mark.asyncio
async def test_memory_transport_closed_sends_and_receives_nothing() -> None:
    bus = MemoryBus()
    a, b = MemoryTransport(bus), MemoryTransport(bus)
    inbox = Inbox(8)
    b.subscribe(KEYS.stack("*"), inbox)
    await a.open()
    await b.open()
    await b.close()
    await b.close()  # twice is harmless
    a.publish(KEYS.stack("r1"), b"x")
    await a.close()
    a.publish(KEYS.stack("r1"), b"y")
    await asyncio.sleep(0)
    assert len(inbox) == 0
    assert a.sent == 1


@pytest.mark.asyncio
async def test_memory_transport_liveliness_announces_alive_and_gone() -> None:
    bus = MemoryBus()
    watcher, early, late = MemoryTransport(bus), MemoryTransport(bus), MemoryTransport(bus)
    early.declare_alive(KEYS.alive("r1"))
    await early.open()
    await watcher.open()
    events = Inbox(8)
    watcher.watch_alive(KEYS.alive("*"), events)
    await asyncio.sleep(0)
    assert events.drain() == [Message(KEYS.alive("r1"), b"", "alive")]  # a token already there
    await late.open()
    late.declare_alive(KEYS.alive("r2"))
    late.declare_alive("semfleet/other/alive/r9")
    await early.close()
    await asyncio.sleep(0)
    assert events.drain() == [
        Message(KEYS.alive("r2"), b"", "alive"),
        Message(KEYS.alive("r1"), b"", "gone"),
    ]


# --------------------------------------------------------------------------- zenoh


def test_zenoh_settings_peer_mode_without_multicast_or_shared_memory() -> None:
    cfg = settings_for(17001, [17002, 17003], gossip=False).config()
    assert cfg.get_json("mode") == '"peer"'
    assert cfg.get_json("scouting/multicast/enabled") == "false"
    assert cfg.get_json("scouting/gossip/enabled") == "false"
    assert cfg.get_json("transport/shared_memory/enabled") == "false"
    assert cfg.get_json("listen/endpoints") == '["tcp/127.0.0.1:17001"]'
    assert cfg.get_json("connect/endpoints") == '["tcp/127.0.0.1:17002","tcp/127.0.0.1:17003"]'
    # Multicast stays off whatever else is asked for.
    assert ZenohSettings().config().get_json("scouting/multicast/enabled") == "false"


@pytest.mark.asyncio
async def test_zenoh_pair_on_loopback_put_reaches_the_inbox() -> None:
    port_a, port_b = free_ports(2)
    a = ZenohTransport(settings_for(port_a, []))
    b = ZenohTransport(settings_for(port_b, [port_a]))
    stacks = Inbox(64)
    b.subscribe(KEYS.stack("*"), stacks)
    payload = bytes(range(256)) * 400  # 100 KB: several Zenoh batches
    try:
        await a.open()
        await b.open()
        assert a.is_open and b.is_open

        # A put sent before b's subscription reached a is dropped: re-publish, as gossip does.
        async def delivered() -> None:
            while not len(stacks):
                a.publish(KEYS.stack("r1"), payload)
                await stacks.wait(0.1)

        async with asyncio.timeout(15):
            await delivered()
        message = stacks.drain()[0]
        assert message == Message(KEYS.stack("r1"), payload)
        a.publish(KEYS.frames("r1"), b"not subscribed")
        a.publish(KEYS.stack("r2"), b"second")
        async with asyncio.timeout(5):
            while not any(m.payload == b"second" for m in stacks.drain()):
                await stacks.wait(0.1)
        assert a.sent >= 3 and a.send_errors == 0
    finally:
        await b.close()
        await a.close()
    assert not a.is_open and not b.is_open
    a.publish(KEYS.stack("r1"), b"after close")  # a no-op, not an error


@pytest.mark.asyncio
async def test_zenoh_close_is_bounded_even_when_the_session_hangs() -> None:
    """A real session closes within CLOSE_WAIT_S (no timeout counted); one whose close hangs (as
    Zenoh's can for seconds on a lossy network) is left to the process's exit after
    CLOSE_WAIT_S, counted, so that an agent still writes its stop record before a launcher's
    SIGKILL."""
    real = ZenohTransport(settings_for(free_ports(1)[0], []))
    await real.open()
    await real.close()
    assert real.close_timeouts == 0 and not real.is_open

    released = threading.Event()

    class Hanging:
        def close(self) -> None:
            released.wait(10.0)

    t = ZenohTransport(settings_for(free_ports(1)[0], []))
    t._session = Hanging()  # type: ignore[assignment]
    start = time.monotonic()
    await t.close()
    waited = time.monotonic() - start
    released.set()
    assert CLOSE_WAIT_S <= waited < 5.0, waited  # not the 10 s the close hangs
    assert t.close_timeouts == 1 and not t.is_open


@pytest.mark.asyncio
async def test_zenoh_stack_subscriptions_follow_the_peers_heard() -> None:
    """``StackSubscriptions.follow`` on real sessions: the stacks of the peers followed arrive,
    the others are not delivered once unsubscribed (undeclared at the publisher's side), and
    None subscribes to every robot's again."""
    port_a, port_b = free_ports(2)
    a = ZenohTransport(settings_for(port_a, []))
    b = ZenohTransport(settings_for(port_b, [port_a]))
    stacks = Inbox(256)
    subs = StackSubscriptions(b, KEYS, stacks, "r9")
    subs.follow(frozenset({"r1"}))  # before open: declared on open

    async def heard(robots: set[str], silent: set[str]) -> None:
        # Publish until every robot of ``robots`` was heard since the last call (declarations
        # take a moment to reach the publisher); none of ``silent`` may be, meanwhile.
        got: set[str] = set()
        async with asyncio.timeout(15):
            while got != robots:
                for r in sorted(robots | silent):
                    a.publish(KEYS.stack(r), r.encode())
                await stacks.wait(0.1)
                await asyncio.sleep(0.05)
                senders = {m.payload.decode() for m in stacks.drain()}
                assert not senders & silent, senders
                got |= senders

    try:
        await a.open()
        await b.open()
        await heard({"r1"}, {"r2", "r3"})
        subs.follow(frozenset({"r2", "r3"}))
        assert subs.exprs == {KEYS.stack("r2"), KEYS.stack("r3")}
        await asyncio.sleep(0.5)  # the undeclaration of r1's reaches a
        stacks.drain()
        await heard({"r2", "r3"}, {"r1"})
        subs.follow(None)
        await heard({"r1", "r2", "r3"}, set())
        subs.follow(frozenset())
        await asyncio.sleep(0.5)
        stacks.drain()
        for r in ("r1", "r2"):
            a.publish(KEYS.stack(r), r.encode())
        await asyncio.sleep(0.3)
        assert not stacks.drain()
    finally:
        await b.close()
        await a.close()


@pytest.mark.asyncio
async def test_memory_stack_subscriptions_follow_the_peers_heard() -> None:
    bus = MemoryBus()
    a, b = MemoryTransport(bus), MemoryTransport(bus)
    await a.open()
    await b.open()
    stacks = Inbox(16)
    subs = StackSubscriptions(b, KEYS, stacks, "r9")
    assert subs.follow(frozenset({"r2"}))  # a subscription added (the runtime echoes then)
    assert not subs.follow(frozenset({"r2"}))  # no second one: one message per put
    for r in ("r1", "r2"):
        a.publish(KEYS.stack(r), r.encode())
    await asyncio.sleep(0)
    assert [m.payload for m in stacks.drain()] == [b"r2"]
    subs.follow(None)
    for r in ("r1", "r2"):
        a.publish(KEYS.stack(r), r.encode())
    await asyncio.sleep(0)
    assert [m.payload for m in stacks.drain()] == [b"r1", b"r2"]
    assert sorted(b.subscriptions) == sorted(
        [(KEYS.stack_to("*", "r9"), stacks), (KEYS.stack("*"), stacks)]
    )
    # The pushes addressed to this robot come whoever is followed, and no one else's do.
    subs.follow(frozenset())
    a.publish(KEYS.stack_to("r1", "r9"), b"to me")
    a.publish(KEYS.stack_to("r1", "r8"), b"to r8")
    await asyncio.sleep(0)
    assert [m.payload for m in stacks.drain()] == [b"to me"]


def test_keys_name_the_sender_of_a_stack_and_of_a_push() -> None:
    assert KEYS.stack_to("r1", "r2") == KEYS.stack("r1") + "/to/r2"
    assert KEYS.stack_sender(KEYS.stack("r1")) == "r1"
    assert KEYS.stack_sender(KEYS.stack_to("r1", "r2")) == "r1"
    for bad in (KEYS.estimate("r1"), KEYS.stack("r1") + "/to", KEYS.stack("r1") + "/x/r2",
                "semfleet/other/stack/r1", KEYS.stack("r1") + "/to/r2/x",
                "semfleet/t12/stack/r1", KEYS.stack("r1") + "/to/" + "x" * 40):  # fmt: skip
        assert KEYS.stack_sender(bad) is None, bad


def test_zenoh_settings_recover_fast_after_a_cut_and_pair_udp_with_tcp(tmp_path: Path) -> None:
    """Re-dials every 100–250 ms; a link attempt keeps Zenoh's own open timeout (10 s): 2 s
    abandoned the handshakes of a 50-agent launch on 2 cores, whose late agents never got a
    frame; a UDP endpoint makes a second link per session."""
    doc = settings_for(17001, [17002]).document()
    assert doc["connect"]["retry"]["period_max_ms"] == 250
    assert "unicast" not in doc["transport"]  # Zenoh's open timeout, one link per session
    udp = ZenohSettings(listen=("tcp/127.0.0.1:17001?rel=1", "udp/127.0.0.1:17001?rel=0"))
    assert udp.document()["transport"]["unicast"]["max_links"] == 2
    # what a file sets wins
    f = tmp_path / "zenoh.json5"
    f.write_text("{transport: {unicast: {open_timeout: 9000, max_links: 1}}}")
    held = dataclasses.replace(udp, config_file=f).document()["transport"]["unicast"]
    assert (held["open_timeout"], held["max_links"]) == (9000, 1)


@pytest.mark.asyncio
async def test_zenoh_udp_next_to_tcp_carries_the_gossip_best_effort() -> None:
    """A session to a peer listening on TCP and UDP has both links; stacks are put
    best-effort (they then take the UDP link), everything else reliable."""
    (port,) = free_ports(1)
    here = (f"tcp/127.0.0.1:{port}?rel=1", f"udp/127.0.0.1:{port}?rel=0")
    a = ZenohTransport(ZenohSettings(listen=here, gossip=False))
    b = ZenohTransport(ZenohSettings(connect=here, gossip=False))
    stacks = Inbox(64)
    b.subscribe(KEYS.stack("*"), stacks)
    payload = bytes(range(256)) * 120  # 30 KB: the paper's largest stack
    try:
        await a.open()
        await b.open()
        async with asyncio.timeout(15):
            while a.links() != {"stream": 1, "datagram": 1} or not len(stacks):
                a.publish(KEYS.stack("r1"), payload)
                await stacks.wait(0.1)
        assert stacks.drain()[0] == Message(KEYS.stack("r1"), payload)
        assert b.links() == {"stream": 1, "datagram": 1}
        a.publish(KEYS.estimate("r1"), b"e")
        publishers = a._publishers
        assert publishers[KEYS.stack("r1")].reliability == zenoh.Reliability.BEST_EFFORT
        assert publishers[KEYS.estimate("r1")].reliability == zenoh.Reliability.RELIABLE
    finally:
        await b.close()
        await a.close()
    assert a.links() == {"stream": 0, "datagram": 0}


@pytest.mark.asyncio
async def test_zenoh_liveliness_tokens_are_seen_alive_then_gone() -> None:
    port_a, port_b = free_ports(2)
    watcher = ZenohTransport(settings_for(port_a, []))
    robot = ZenohTransport(settings_for(port_b, [port_a]))
    events = Inbox(64)
    watcher.watch_alive(KEYS.alive("*"), events)
    robot.declare_alive(KEYS.alive("r2"))
    seen: list[Message] = []

    def saw(kind: Kind) -> bool:
        seen.extend(events.drain())
        return Message(KEYS.alive("r2"), b"", kind) in seen

    try:
        await watcher.open()
        await robot.open()
        await _until(lambda: saw("alive"), 15)
        await robot.close()
        await _until(lambda: saw("gone"), 10)  # a closed session ends its tokens at once
    finally:
        await robot.close()
        await watcher.close()
    assert all(m.key == KEYS.alive("r2") for m in seen)


@pytest.mark.asyncio
async def test_zenoh_sessions_without_endpoints_in_common_never_meet() -> None:
    """Multicast scouting is off: a session that dials nobody and is dialled by nobody hears
    nothing, even on the same host and key."""
    port_a, port_b, port_c = free_ports(3)
    a = ZenohTransport(settings_for(port_a, []))
    b = ZenohTransport(settings_for(port_b, [port_a]))
    loner = ZenohTransport(settings_for(port_c, []))
    heard, control = Inbox(64), Inbox(64)
    loner.subscribe(KEYS.stack("*"), heard)
    b.subscribe(KEYS.stack("*"), control)
    try:
        for t in (a, b, loner):
            await t.open()
        async with asyncio.timeout(15):
            while not len(control):  # until the linked peer hears a, for 1 s more after that
                a.publish(KEYS.stack("r1"), b"hello")
                await control.wait(0.1)
        for _ in range(10):
            a.publish(KEYS.stack("r1"), b"hello")
            await asyncio.sleep(0.1)
    finally:
        for t in (loner, b, a):
            await t.close()
    assert len(heard) == 0
    assert len(control) > 0
