"""Publishing a robot's frame log to its running agent, as its perception process would
(:func:`replay`), through :class:`agents.perception.RobotLink`, which answers the agent's
``ctl/need`` from the whole log. ``semfleet replay`` (deploy/cli/commands/replay.py) parses its
options and calls these.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from agents.perception import RobotLink
from agents.transport.zenoh_transport import ZenohSettings
from deploy.base.errors import RunFailure
from estimator.models import SensorFrame
from protocol.estimate import EstimateMessage
from protocol.framelog import FrameLogError, read_frame_log

RESEND_S = 1.0  # while waiting: the last frame again, in case it or its estimate was lost


@dataclass(frozen=True, slots=True)
class ReplayReport:
    frames: int
    wall_s: float  # from the first frame to the last (to the agent's last estimate with --wait)
    need_requests: int
    frames_resent: int
    reached: int | None  # the agent's latest step seen (--wait only)


def read_frames_file(path: Path) -> list[SensorFrame]:
    """The frames of a log file. Raises ``FrameLogError`` (line and field) or ``OSError``."""
    with open(path, "rb") as f:
        return read_frame_log(_text_lines(f))


def _text_lines(f: IO[bytes]) -> Iterator[str]:
    for lineno, raw in enumerate(f, start=1):
        try:
            yield raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise FrameLogError(lineno, "json", f"not UTF-8 text (byte {exc.start})") from None


def replay_settings(agent: ZenohSettings) -> ZenohSettings:
    """The replay's session: the agent's own settings, its ``config_file`` too (TLS identity,
    access control), that listens on nothing, since the agent's ports are the agent's, and
    dials the agent: where it listens (every interface, ``0.0.0.0`` or ``[::]``, dialled on
    loopback: a replay runs on the robot), or, for an agent that listens nowhere, where it
    dials (a router or a conductor that routes for it)."""
    listen, connect = agent.endpoints()
    dial = tuple(dict.fromkeys(_on_this_machine(e) for e in listen)) or connect
    return agent.dialling(dial)


def _on_this_machine(endpoint: str) -> str:
    """A listen endpoint as this machine dials it: a wildcard host becomes loopback."""
    for wildcard, loopback in (("/0.0.0.0:", "/127.0.0.1:"), ("/[::]:", "/[::1]:")):
        endpoint = endpoint.replace(wildcard, loopback, 1)
    return endpoint


async def replay(
    frames: list[SensorFrame],
    fleet: str,
    settings: ZenohSettings,
    period: float,
    wait: bool,
    timeout: float,
) -> ReplayReport:
    """Wait for the robot's agent (at most ``timeout`` s), publish one frame every ``period`` s;
    with ``wait``, then wait (at most ``timeout`` s) until the agent's estimate reaches the last
    step. Raises ``RunFailure`` saying which wait timed out."""
    robot = frames[0].robot
    async with RobotLink(robot, fleet, settings, history=len(frames)) as link:
        try:
            async with asyncio.timeout(timeout):
                await link.wait_for_agent()
        except TimeoutError:
            dialled = ", ".join(settings.endpoints()[1]) or "no endpoint"
            raise RunFailure(
                f"no agent {robot} alive on fleet {fleet} within {timeout:g} s (dialled {dialled})"
            ) from None
        estimates = link.estimates() if wait else None  # subscribed before the first frame
        loop = asyncio.get_running_loop()
        start = loop.time()
        for i, frame in enumerate(frames):
            await asyncio.sleep(max(0.0, start + i * period - loop.time()))
            link.publish_frame(frame)
        reached = None
        if estimates is None:
            await asyncio.sleep(period)  # time for a ctl/need about the last frame
        else:
            reached = await wait_until_step(link, estimates, frames[-1], timeout)
        return ReplayReport(
            len(frames),
            loop.time() - start,
            link.counters.need_requests,
            link.counters.frames_resent,
            reached,
        )


async def wait_until_step(
    link: RobotLink, estimates: AsyncIterator[EstimateMessage], frame: SensorFrame, timeout: float
) -> int:
    """Until an estimate from ``estimates`` reaches ``frame``'s step (the step reached), sending
    ``frame`` again every ``RESEND_S``: an agent that lost it steps, one that has it answers the
    copy with its latest estimate. ``RunFailure`` after ``timeout`` s."""
    reached = 0

    async def follow() -> None:
        nonlocal reached
        async for estimate in estimates:
            reached = max(reached, estimate.k)
            if reached >= frame.k:
                return

    task = asyncio.create_task(follow())
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    try:
        while not task.done():
            left = deadline - loop.time()
            if left <= 0:
                seen = f"step {reached}" if reached else "none received"
                raise RunFailure(
                    f"{frame.robot}'s agent did not reach step {frame.k} within {timeout:g} s "
                    f"of the last frame (its latest estimate: {seen})"
                )
            await asyncio.wait({task}, timeout=min(RESEND_S, left))
            if not task.done():
                link.publish_frame(frame)
    finally:
        task.cancel()
    task.result()  # the iteration's own error, if it ended with one
    return reached
