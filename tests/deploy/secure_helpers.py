"""Shared by the tests of secure fleets: a Zenoh session with a fleet member's identity, and the
operator's status request."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path

from agents.control import Status, encode_control
from agents.transport.base import Inbox, Keys
from agents.transport.zenoh_transport import ZenohSettings, ZenohTransport
from protocol.estimate import EstimateMessage, decode_estimate


def identity_settings(folder: Path, endpoint: str) -> ZenohSettings:
    """A peer session with ``folder``'s identity (its zenoh.json5) that dials ``endpoint`` only."""
    extra = {"listen/endpoints": [], "connect/endpoints": [endpoint], "mode": "peer"}
    return ZenohSettings(config_file=folder / "zenoh.json5", extra=extra)


async def ask_status(
    operator: ZenohTransport,
    inbox: Inbox,
    keys: Keys,
    accept: Callable[[EstimateMessage], bool] = lambda _: True,
) -> EstimateMessage:
    """Send ``ctl/status`` every second until an estimate ``accept`` takes arrives (≤ 60 s)."""
    async with asyncio.timeout(60):
        while True:
            operator.publish(keys.ctl("status"), encode_control(Status()))
            try:
                m = await asyncio.wait_for(inbox.get(), 1.0)
            except TimeoutError:
                continue
            est = decode_estimate(m.payload)
            if accept(est):
                return est
