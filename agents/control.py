"""Run-control messages between a conductor and its agents (``semfleet/<fleet>/ctl/**``).

``step``: the conductor's order for lock-step round k, with, for every robot, the peers whose
stacks of round k − 1 it must merge first (the link model evaluated on ground truth).
``need``: an agent asks for frames from step k on (after a restart or a gap).
``status``: every agent publishes its estimate with its counters now. ``stop``: end of the run.
Payloads are msgpack maps; ``decode_control`` raises only
:class:`~protocol.errors.RemoteProtocolError` subclasses naming the field.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import msgpack

from protocol.errors import InvalidValue, MalformedMessage, RemoteProtocolError
from protocol.validate import valid_id

MAX_STEP = 10**9


@dataclass(frozen=True, slots=True)
class StepOrder:
    """Lock-step round ``k``: ``links[robot]`` = the senders ``robot`` hears before stepping."""

    k: int
    links: dict[str, tuple[str, ...]] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class NeedFrames:
    """``robot`` is missing its frames from step ``k`` on."""

    robot: str
    k: int


@dataclass(frozen=True, slots=True)
class Status:
    """Asks every agent to publish its estimate (with all its counters) now."""


@dataclass(frozen=True, slots=True)
class Stop:
    """The run is over: agents finish and exit."""

    reason: str = ""


Control = StepOrder | NeedFrames | Status | Stop


def encode_control(message: Control) -> bytes:
    doc: dict[str, Any]
    if isinstance(message, StepOrder):
        doc = {
            "type": "step",
            "k": message.k,
            "links": {r: list(s) for r, s in message.links.items()},
        }
    elif isinstance(message, NeedFrames):
        doc = {"type": "need", "robot": message.robot, "k": message.k}
    elif isinstance(message, Status):
        doc = {"type": "status"}
    else:
        doc = {"type": "stop", "reason": message.reason}
    return bytes(msgpack.packb(doc, use_bin_type=True))


def decode_control(data: bytes) -> Control:
    try:
        doc = msgpack.unpackb(data, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises many types for bad input; all mean malformed
        raise MalformedMessage(f"not a msgpack document ({type(exc).__name__})", "ctl") from None
    if not isinstance(doc, dict):
        raise MalformedMessage("expected a map", "ctl")
    kind = doc.get("type")
    if kind == "step":
        _keys(doc, {"type", "k", "links"})
        links = doc["links"]
        if not isinstance(links, dict):
            raise MalformedMessage("expected a map", "ctl.links")
        out: dict[str, tuple[str, ...]] = {}
        for robot, senders in links.items():
            _robot(robot, "ctl.links")
            if not isinstance(senders, list):
                raise MalformedMessage("expected an array", f"ctl.links.{robot}")
            out[robot] = tuple(_robot(s, f"ctl.links.{robot}") for s in senders)
        return StepOrder(_step(doc["k"]), out)
    if kind == "need":
        _keys(doc, {"type", "robot", "k"})
        return NeedFrames(_robot(doc["robot"], "ctl.robot"), _step(doc["k"]))
    if kind == "status":
        _keys(doc, {"type"})
        return Status()
    if kind == "stop":
        _keys(doc, {"type", "reason"})
        if not isinstance(doc["reason"], str):
            raise MalformedMessage("expected a string", "ctl.reason")
        return Stop(doc["reason"])
    raise MalformedMessage(f"unknown control type {kind!r}", "ctl.type")


def _keys(doc: dict[Any, Any], keys: set[str]) -> None:
    if set(doc) != keys:
        raise MalformedMessage(f"expected keys {sorted(keys)}, got {sorted(map(str, doc))}", "ctl")


def _step(value: Any) -> int:
    if not isinstance(value, int) or isinstance(value, bool):
        raise MalformedMessage("expected an integer", "ctl.k")
    if not 0 <= value <= MAX_STEP:
        raise InvalidValue(f"{value} outside 0..{MAX_STEP}", "ctl.k")
    return value


def _robot(value: Any, where: str) -> str:
    if not valid_id(value):
        raise InvalidValue(f"invalid robot id {value!r}", where)
    return str(value)


__all__ = [
    "Control",
    "NeedFrames",
    "RemoteProtocolError",
    "Status",
    "StepOrder",
    "Stop",
    "decode_control",
    "encode_control",
]
