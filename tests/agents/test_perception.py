"""RobotLink, the perception side of a robot (agents/perception.py), over the in-memory transport:
frames go out without ground truth, ``ctl/need`` is answered from the bounded buffer, estimates come
in decoded (invalid ones counted and skipped), and the agent's liveliness is visible.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging

import numpy as np
import pytest

from agents.control import NeedFrames, Stop, encode_control
from agents.perception import RobotLink
from agents.transport import Inbox, Keys, MemoryBus, MemoryTransport
from protocol.errors import LocalProtocolError
from protocol.estimate import EstimateMessage, encode_estimate
from protocol.frames import decode_frame
from sim.loader import load_scenario
from sim.sensors import Simulator
from tests.protocol.test_estimate import make_snapshot

KEYS = Keys("fleet")
FRAMES = Simulator(load_scenario("paper"), 4).frames("r1")[:6]


async def _settle() -> None:
    """Let the memory bus deliver what was published (deliveries are scheduled on the loop)."""
    for _ in range(3):
        await asyncio.sleep(0)


async def _agent_side(bus: MemoryBus) -> tuple[MemoryTransport, Inbox]:
    """The agent's end of the bus, open, with everything published on ``frames/r1``."""
    agent = MemoryTransport(bus)
    frames = Inbox(1000)
    agent.subscribe(KEYS.frames("r1"), frames)
    await agent.open()
    return agent, frames


def _link(bus: MemoryBus, history: int = 1000) -> RobotLink:
    return RobotLink("r1", "fleet", history=history, transport=MemoryTransport(bus))


def _ks(inbox: Inbox) -> list[int]:
    return [decode_frame(m.payload).k for m in inbox.drain()]


@pytest.mark.asyncio
async def test_robot_link_publishes_frames_without_truth() -> None:
    bus = MemoryBus()
    _, frames = await _agent_side(bus)
    async with _link(bus) as link:
        assert np.isfinite(FRAMES[0].true_pose).all()
        link.publish_frame(FRAMES[0])
        await _settle()
    got = [decode_frame(m.payload) for m in frames.drain()]
    assert [f.k for f in got] == [1]
    assert np.isnan(got[0].true_pose).all()
    assert np.array_equal(got[0].odometry, FRAMES[0].odometry)


@pytest.mark.asyncio
async def test_robot_link_answers_need_from_step_k() -> None:
    bus = MemoryBus()
    agent, frames = await _agent_side(bus)
    async with _link(bus) as link:
        for frame in FRAMES[:5]:
            link.publish_frame(frame)
        await _settle()
        assert _ks(frames) == [1, 2, 3, 4, 5]
        agent.publish(KEYS.ctl("need", "r1"), encode_control(NeedFrames("r1", 3)))
        await _settle()
        assert _ks(frames) == [3, 4, 5]
        agent.publish(KEYS.ctl("need", "r1"), encode_control(NeedFrames("r1", 6)))
        await _settle()
        assert _ks(frames) == []  # nothing sent from 6 on yet
        assert (link.counters.need_requests, link.counters.frames_resent) == (2, 3)


@pytest.mark.asyncio
async def test_robot_link_history_is_bounded_and_says_what_it_cannot_serve(
    caplog: pytest.LogCaptureFixture,
) -> None:
    bus = MemoryBus()
    agent, frames = await _agent_side(bus)
    async with _link(bus, history=2) as link:
        for frame in FRAMES[:5]:
            link.publish_frame(frame)
        await _settle()
        frames.drain()
        with caplog.at_level(logging.WARNING, logger="agents.perception"):
            agent.publish(KEYS.ctl("need", "r1"), encode_control(NeedFrames("r1", 1)))
            await _settle()
        assert _ks(frames) == [4, 5]
        assert link.counters.need_unserved == 1
        assert "needs frames from step 1, the oldest kept is step 4" in caplog.text


@pytest.mark.asyncio
async def test_robot_link_counts_invalid_control_and_lives_on() -> None:
    bus = MemoryBus()
    agent, frames = await _agent_side(bus)
    async with _link(bus) as link:
        link.publish_frame(FRAMES[0])
        for payload in (
            b"\xc1garbage",
            encode_control(Stop("x")),
            encode_control(NeedFrames("r2", 1)),
        ):
            agent.publish(KEYS.ctl("need", "r1"), payload)
        await _settle()
        assert link.counters.invalid_control == 3
        assert _ks(frames) == [1]
        agent.publish(KEYS.ctl("need", "r1"), encode_control(NeedFrames("r1", 1)))
        await _settle()
        assert _ks(frames) == [1]


@pytest.mark.asyncio
async def test_robot_link_publish_frame_rules() -> None:
    bus = MemoryBus()
    agent, frames = await _agent_side(bus)
    link = _link(bus)
    with pytest.raises(RuntimeError, match="not open"):
        link.publish_frame(FRAMES[0])
    async with link:
        link.publish_frame(FRAMES[1])
        with pytest.raises(ValueError, match="steps never go backwards"):
            link.publish_frame(FRAMES[0])
        with pytest.raises(ValueError, match="frame of robot 'r2'"):
            link.publish_frame(dataclasses.replace(FRAMES[2], robot="r2"))
        bad = dataclasses.replace(FRAMES[2], odometry=np.array([0.0, np.nan, 0.0]))
        with pytest.raises(LocalProtocolError, match="odo: non-finite"):
            link.publish_frame(bad)
        link.publish_frame(FRAMES[1])  # the latest again: re-sent, kept once
        await _settle()
        assert _ks(frames) == [2, 2]
        agent.publish(KEYS.ctl("need", "r1"), encode_control(NeedFrames("r1", 1)))
        await _settle()
        assert _ks(frames) == [2]
    with pytest.raises(RuntimeError, match="not open"):
        link.publish_frame(FRAMES[2])


def _estimate(robot: str, k: int) -> bytes:
    snap = make_snapshot(np.random.default_rng(k), num_classes=2)
    return encode_estimate(EstimateMessage(robot, k, {"distributed": snap}, {"steps": k}))


@pytest.mark.asyncio
async def test_robot_link_estimates_decoded_until_the_link_closes() -> None:
    bus = MemoryBus()
    agent = MemoryTransport(bus)
    await agent.open()
    link = _link(bus)
    async with link:
        own, everyone = link.estimates(), link.estimates("*")
        agent.publish(KEYS.estimate("r1"), _estimate("r1", 1))
        agent.publish(KEYS.estimate("r1"), b"\x93not an estimate")
        agent.publish(KEYS.estimate("r2"), _estimate("r2", 7))
        agent.publish(KEYS.estimate("r1"), _estimate("r1", 2))
        await _settle()
        first = await anext(own)
        assert (first.robot, first.k, first.counters) == ("r1", 1, {"steps": 1})
        assert (await anext(own)).k == 2
        assert [(e.robot, e.k) for e in [await anext(everyone) for _ in range(3)]] == [
            ("r1", 1),
            ("r2", 7),
            ("r1", 2),
        ]
        assert link.counters.invalid_estimates == 2  # the bad one, seen by both iterators
    async with asyncio.timeout(1):
        assert [e async for e in own] == []  # the link closed: the iteration ends


@pytest.mark.asyncio
async def test_robot_link_sees_the_agent_come_and_go() -> None:
    bus = MemoryBus()
    async with _link(bus) as link:
        assert not link.agent_alive
        agent = MemoryTransport(bus)
        agent.declare_alive(KEYS.alive("r1"))
        await agent.open()
        async with asyncio.timeout(1):
            await link.wait_for_agent()
        assert link.agent_alive
        await agent.close()
        await _settle()
        assert not link.agent_alive
