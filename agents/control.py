"""Run-control messages between a conductor and its agents (``semfleet/<fleet>/ctl/**``).

``step``: the conductor's order for lock-step round k, with, for every robot, the peers whose
stacks of round k − 1 it must merge first (the link model evaluated on ground truth), and
optionally the robots whose estimate of round k it still waits for.
``need``: an agent asks for frames from step k on (after a restart or a gap). ``round`` (on the
same key): a lock-step agent asks peers for their stacks of round k it lacks.
``status``: every agent publishes its estimate with its counters now. ``stop``: end of the run.
Payloads are msgpack maps of at most ``max_bytes`` (64 KiB by default, checked before anything is
unpacked) and step orders hold at most ``MAX_LINKS`` robots of ``MAX_LINKS`` senders each, so
one message costs a receiver little (≈ 15 ms at worst, measured). ``decode_control`` raises only
:class:`~protocol.errors.RemoteProtocolError` subclasses naming the field; ``encode_control``
raises :class:`~protocol.errors.LocalProtocolError` for what it would refuse.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import msgpack

from estimator.models.frames import MAX_STEP
from protocol.errors import (
    InvalidValue,
    LimitExceeded,
    LocalProtocolError,
    MalformedMessage,
    RemoteProtocolError,
)
from protocol.validate import decode_document, valid_id

# Far above any fleet's roster. The byte cap bounds the work of a decode on its own (the worst
# case, 64 KiB of one-letter sender ids, 28 k of them, decodes in ≈ 15 ms); this cap bounds what a
# receiver keeps of a step order when a deployment raises max_bytes.
MAX_LINKS = 1024
MAX_CONTROL_BYTES = 64 * 1024


@dataclass(frozen=True, slots=True)
class StepOrder:
    """Lock-step round ``k``: ``links[robot]`` = the senders ``robot`` hears before stepping.
    ``waiting``: the robots whose estimate of round k the conductor still lacks (a re-sent order
    is answered by those only); None: every robot (an operator's order, or an older conductor)."""

    k: int
    links: dict[str, tuple[str, ...]] = field(default_factory=dict)
    waiting: tuple[str, ...] | None = None


@dataclass(frozen=True, slots=True)
class NeedFrames:
    """``robot`` is missing its frames from step ``k`` on."""

    robot: str
    k: int


@dataclass(frozen=True, slots=True)
class NeedRound:
    """Lock-step: ``robot`` lacks the stacks of round ``k`` of ``senders`` (lost, or never
    sent yet); each named sender that has made its round-k stack sends it again."""

    robot: str
    k: int
    senders: tuple[str, ...]


@dataclass(frozen=True, slots=True)
class Status:
    """Asks every agent to publish its estimate (with all its counters) now."""


@dataclass(frozen=True, slots=True)
class Stop:
    """The run is over: agents finish and exit."""

    reason: str = ""


Control = StepOrder | NeedFrames | NeedRound | Status | Stop
# The one key each kind of control message may come on (under ``ctl/``; ``need/<robot>`` for the
# requests of that robot): a message on another key is refused (:func:`fits_key`).
KEY_OF: dict[type, str] = {StepOrder: "step", Stop: "stop", Status: "status"}


def fits_key(message: Control, where: str) -> bool:
    """Whether ``message`` may come on the control key ``ctl/<where>``: a step order only on
    ``step``, a stop only on ``stop``, a status request only on ``status``, and on
    ``need/<robot>`` only that robot's requests (``NeedFrames``, ``NeedRound``) — the one control
    key a fleet member may put on (``deploy.operator.access_control``), so that a member's key
    never carries an order for the whole fleet (docs/deploy.md, "Threat model")."""
    if isinstance(message, NeedFrames | NeedRound):
        return where == f"need/{message.robot}"
    return KEY_OF.get(type(message)) == where


def encode_control(message: Control, max_bytes: int = MAX_CONTROL_BYTES) -> bytes:
    """Bytes of a control message; :class:`LocalProtocolError` for anything ``decode_control``
    would refuse under the same ``max_bytes``."""
    doc: dict[str, Any]
    if isinstance(message, StepOrder):
        _local(_valid_step(message.k), "ctl.k", f"{message.k!r} outside 0..{MAX_STEP}")
        links = message.links
        _local(len(links) <= MAX_LINKS, "ctl.links", f"{len(links)} robots > {MAX_LINKS}")
        for robot, senders in links.items():
            _local(valid_id(robot), "ctl.links", f"invalid robot id {robot!r}")
            where = f"ctl.links.{robot}"
            _local(len(senders) <= MAX_LINKS, where, f"{len(senders)} senders > {MAX_LINKS}")
            _local(all(valid_id(s) for s in senders), where, "invalid robot id")
        doc = {"type": "step", "k": message.k, "links": {r: list(s) for r, s in links.items()}}
        if message.waiting is not None:
            waiting = message.waiting
            _local(len(waiting) <= MAX_LINKS, "ctl.waiting", f"{len(waiting)} robots > {MAX_LINKS}")
            _local(all(valid_id(r) for r in waiting), "ctl.waiting", "invalid robot id")
            doc["waiting"] = list(waiting)
    elif isinstance(message, NeedFrames):
        _local(valid_id(message.robot), "ctl.robot", f"invalid robot id {message.robot!r}")
        _local(_valid_step(message.k), "ctl.k", f"{message.k!r} outside 0..{MAX_STEP}")
        doc = {"type": "need", "robot": message.robot, "k": message.k}
    elif isinstance(message, NeedRound):
        _local(valid_id(message.robot), "ctl.robot", f"invalid robot id {message.robot!r}")
        _local(_valid_step(message.k), "ctl.k", f"{message.k!r} outside 0..{MAX_STEP}")
        senders = message.senders
        _local(len(senders) <= MAX_LINKS, "ctl.senders", f"{len(senders)} robots > {MAX_LINKS}")
        _local(all(valid_id(r) for r in senders), "ctl.senders", "invalid robot id")
        doc = {"type": "round", "robot": message.robot, "k": message.k, "senders": list(senders)}
    elif isinstance(message, Status):
        doc = {"type": "status"}
    elif isinstance(message, Stop):
        _local(isinstance(message.reason, str), "ctl.reason", "expected a string")
        doc = {"type": "stop", "reason": message.reason}
    else:
        raise LocalProtocolError(f"not a control message: {type(message).__name__}", "ctl")
    data = bytes(msgpack.packb(doc, use_bin_type=True))
    _local(len(data) <= max_bytes, "ctl", f"{len(data)} bytes > {max_bytes}")
    return data


def decode_control(data: bytes, max_bytes: int = MAX_CONTROL_BYTES) -> Control:
    """Parse a control message of at most ``max_bytes``. Raises only
    :class:`~protocol.errors.RemoteProtocolError` subclasses."""
    return decode_document(data, max_bytes, _parse, "ctl")


def _parse(doc: Any) -> Control:
    if not isinstance(doc, dict):
        raise MalformedMessage("expected a map", "ctl")
    kind = doc.get("type")
    if kind == "step":
        _keys(doc, {"type", "k", "links"} | ({"waiting"} & set(doc)))
        k = _step(doc["k"])
        links = doc["links"]
        if not isinstance(links, dict):
            raise MalformedMessage("expected a map", "ctl.links")
        if len(links) > MAX_LINKS:
            raise LimitExceeded(f"{len(links)} robots > {MAX_LINKS}", "ctl.links")
        out: dict[str, tuple[str, ...]] = {}
        for robot, senders in links.items():
            _robot(robot, "ctl.links")
            where = f"ctl.links.{robot}"
            if not isinstance(senders, list):
                raise MalformedMessage("expected an array", where)
            if len(senders) > MAX_LINKS:
                raise LimitExceeded(f"{len(senders)} senders > {MAX_LINKS}", where)
            out[robot] = tuple(_robot(s, where) for s in senders)
        waiting = None
        if "waiting" in doc:
            raw = doc["waiting"]
            if not isinstance(raw, list):
                raise MalformedMessage("expected an array", "ctl.waiting")
            if len(raw) > MAX_LINKS:
                raise LimitExceeded(f"{len(raw)} robots > {MAX_LINKS}", "ctl.waiting")
            waiting = tuple(_robot(r, "ctl.waiting") for r in raw)
        return StepOrder(k, out, waiting)
    if kind == "need":
        _keys(doc, {"type", "robot", "k"})
        return NeedFrames(_robot(doc["robot"], "ctl.robot"), _step(doc["k"]))
    if kind == "round":
        _keys(doc, {"type", "robot", "k", "senders"})
        senders = doc["senders"]
        if not isinstance(senders, list):
            raise MalformedMessage("expected an array", "ctl.senders")
        if len(senders) > MAX_LINKS:
            raise LimitExceeded(f"{len(senders)} robots > {MAX_LINKS}", "ctl.senders")
        return NeedRound(
            _robot(doc["robot"], "ctl.robot"),
            _step(doc["k"]),
            tuple(_robot(r, "ctl.senders") for r in senders),
        )
    if kind == "status":
        _keys(doc, {"type"})
        return Status()
    if kind == "stop":
        _keys(doc, {"type", "reason"})
        if not isinstance(doc["reason"], str):
            raise MalformedMessage("expected a string", "ctl.reason")
        return Stop(doc["reason"])
    raise MalformedMessage(f"unknown control type {kind!r}", "ctl.type")


def _local(cond: bool, where: str, message: str) -> None:
    if not cond:
        raise LocalProtocolError(message, where)


def _valid_step(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= MAX_STEP


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
    "MAX_CONTROL_BYTES",
    "MAX_LINKS",
    "Control",
    "NeedFrames",
    "NeedRound",
    "RemoteProtocolError",
    "Status",
    "StepOrder",
    "Stop",
    "decode_control",
    "encode_control",
]
