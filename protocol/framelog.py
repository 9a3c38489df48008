"""Frame logs: one robot's sensor frames as JSON lines (docs/wire.md, "Frame logs").

What a robot's logger writes and ``semfleet replay`` publishes on ``frames/<robot>``: an optional
header line ``{"v": 1, "type": "frame_log"}``, then one frame per line,
``{"robot": id, "k": int, "odometry": [dx, dy, dθ],
"detections": [{"id": int, "z_geo": [x, y, θ], "z_sem": [s₁, …, s_M]}, ...]}``, with k = 1, 2, 3…
(``z_geo`` of a point object: [bearing, range]). A frame whose ids are not global object ids says
so: ``"ids": "local"`` (a robot-local tracker's ids) or ``"ids": "none"`` (then its detections
have no ``id``); a line without ``ids`` holds global ids, as every log written before.
A log never holds ground truth: a parsed frame's ``true_pose`` is three NaN.

Sans-I/O: these functions take and return ``str`` lines; the caller opens the file. A line is
accepted exactly when the frame it holds would be accepted on the wire: after the JSON-specific
checks (types, key sets, array lengths) the frame goes through ``protocol.frames.encode_frame``
under the caller's :class:`~protocol.frames.FrameLimits`, the one place those rules live. Every
error is a :class:`FrameLogError` naming the line and the field:
``line 12: detections[0].z_sem: non-finite number``.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from estimator.models import GLOBAL_IDS, ID_KINDS, NO_ID, NO_IDS, Detection, SensorFrame
from protocol.errors import (
    InvalidValue,
    LimitExceeded,
    LocalProtocolError,
    MalformedMessage,
    ProtocolError,
    RemoteProtocolError,
    UnsupportedVersion,
)
from protocol.frames import MAX_OBJECT_ID, MAX_STEP, FrameLimits, encode_frame
from protocol.validate import as_int, as_map, need, robot_id

VERSION = 1
LOG_TYPE = "frame_log"
# A float64 takes at most 24 characters of JSON against 8 bytes on the wire, so no valid frame
# needs a line longer than this many characters per wire byte; longer lines are refused unparsed.
CHARS_PER_WIRE_BYTE = 4
_HEADER_KEYS = frozenset({"v", "type"})
_FRAME_KEYS = frozenset({"robot", "k", "odometry", "detections"})
_ID_KEY = "ids"  # optional: absent means global ids
_DETECTION_KEYS = frozenset({"id", "z_geo", "z_sem"})
_DETECTION_KEYS_NO_ID = frozenset({"z_geo", "z_sem"})
# encode_frame's field names → the log's: odo → odometry, det[i].geo → detections[i].z_geo …
_LOG_NAMES = {
    "odo": "odometry",
    "det": "detections",
    "geo": "z_geo",
    "sem": "z_sem",
    "message": "frame",  # the frame as a whole: over max_message_bytes on the wire
}
_WIRE_NAME = re.compile(r"\b(odo|det|geo|sem|message)\b")


class FrameLogError(RemoteProtocolError):
    """A frame log that is not valid. ``line``: 1-based line number; ``field``: as in the log
    (``k``, ``detections[0].z_sem``, ``json`` for a line that is not JSON, ``frames`` for the log
    as a whole); the message reads ``line 12: detections[0].z_sem: non-finite number``."""

    def __init__(self, line: int, field: str, message: str) -> None:
        super().__init__(message, field)
        self.args = (f"line {line}: {self.args[0]}",)
        self.line = line


def format_header() -> str:
    """The optional first line of a log (without its newline)."""
    return json.dumps({"v": VERSION, "type": LOG_TYPE}, separators=(",", ":"))


def format_frame_line(frame: SensorFrame, limits: FrameLimits | None = None) -> str:
    """One line (without its newline) holding ``frame`` without its ground truth. Raises
    :class:`LocalProtocolError` for a frame the wire would refuse. Floats are written in Python's
    shortest round-trip form, so ``parse_frame_line`` gives back the same bits."""
    frame = replace(frame, true_pose=np.full(3, np.nan))  # a log never holds ground truth
    encode_frame(frame, limits)
    with_id = frame.ids != NO_IDS
    doc: dict[str, Any] = {
        "robot": frame.robot,
        "k": int(frame.k),
        "odometry": _floats(frame.odometry),
        "detections": [
            {
                **({"id": int(d.object_id)} if with_id else {}),
                "z_geo": _floats(d.z_geo),
                "z_sem": _floats(d.z_sem),
            }
            for d in frame.detections
        ],
    }
    if frame.ids != GLOBAL_IDS:  # a log of global ids reads as every log written before
        doc[_ID_KEY] = frame.ids
    return json.dumps(doc, separators=(",", ":"), allow_nan=False)


def parse_frame_line(line: str, lineno: int, limits: FrameLimits | None = None) -> SensorFrame:
    """The frame on one line (``lineno`` only names it in errors); ``true_pose`` is three NaN.
    Raises only :class:`FrameLogError`."""
    lim = limits or FrameLimits()
    with _at(lineno):
        return _frame(_load(line, lim), lim)


def read_frame_log(lines: Iterable[str], limits: FrameLimits | None = None) -> list[SensorFrame]:
    """Every frame of a log, checked as a whole: an optional header first, then frames of one
    robot with k = 1, 2, 3…, one id kind and one score length M throughout. Blank lines are
    skipped (line numbers still count them). Raises only :class:`FrameLogError`; a log without
    frames is one."""
    frames = list(_frames(lines, limits or FrameLimits()))
    if not frames:
        raise FrameLogError(1, "frames", "the log holds no frame")
    return frames


def _frames(lines: Iterable[str], lim: FrameLimits) -> Iterator[SensorFrame]:
    previous: SensorFrame | None = None
    scores: tuple[int, int] | None = None  # (M, the line that fixed it)
    id_line = 0  # the line of the first frame, whose id kind the whole log keeps
    first = True
    for lineno, line in enumerate(lines, start=1):
        if isinstance(line, str) and not line.strip():
            continue
        with _at(lineno):
            doc = _load(line, lim)
            if isinstance(doc, dict) and "v" in doc:
                need(first, "header", "only the first line may be a header")
                _header(doc)
                first = False
                continue
            first = False
            frame = _frame(doc, lim)
            _follows(frame, previous)
            if previous is not None and frame.ids != previous.ids:
                problem = f"{frame.ids!r}, but line {id_line} holds {previous.ids!r} ids"
                raise MalformedMessage(problem, _ID_KEY)
            id_line = lineno if previous is None else id_line
            if frame.detections:
                m = len(frame.detections[0].z_sem)
                if scores is not None and m != scores[0]:
                    problem = f"{m} scores, but line {scores[1]} has {scores[0]}"
                    raise MalformedMessage(problem, "detections[0].z_sem")
                scores = scores or (m, lineno)
        previous = frame
        yield frame


def _follows(frame: SensorFrame, previous: SensorFrame | None) -> None:
    """Frames of one robot, consecutive from k = 1 (an agent steps through every k)."""
    expected = 1 if previous is None else previous.k + 1
    need(frame.k == expected, "k", f"expected {expected}, got {frame.k} (steps run 1, 2, 3…)")
    if previous is not None:
        same = frame.robot == previous.robot
        need(same, "robot", f"{frame.robot!r}, but the log is robot {previous.robot!r}'s")


@contextmanager
def _at(lineno: int) -> Iterator[None]:
    """Re-raise a protocol error as a :class:`FrameLogError` of line ``lineno``."""
    try:
        yield
    except FrameLogError:
        raise
    except ProtocolError as exc:
        reason = str(exc).removeprefix(f"{exc.field}: ")
        raise FrameLogError(lineno, exc.field, reason) from exc


def _load(line: Any, lim: FrameLimits) -> Any:
    need(isinstance(line, str), "json", f"expected text, got {type(line).__name__}")
    most = CHARS_PER_WIRE_BYTE * lim.max_message_bytes
    need(len(line) <= most, "json", f"{len(line)} characters > {most}", LimitExceeded)
    try:
        return json.loads(line, object_pairs_hook=_unique_keys)
    except json.JSONDecodeError as exc:
        raise MalformedMessage(f"not JSON: {exc.msg} at column {exc.colno}", "json") from None
    except RecursionError:
        raise MalformedMessage("not JSON: nested too deeply", "json") from None


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    doc: dict[str, Any] = {}
    for key, value in pairs:
        need(key not in doc, "json", f"duplicate key {key!r}")
        doc[key] = value
    return doc


def _header(doc: dict[str, Any]) -> None:
    """Checked as the wire checks ``v``: first, so a later version may change everything else."""
    if type(doc["v"]) is not int or doc["v"] != VERSION:
        raise UnsupportedVersion(f"log version {doc['v']!r} (this side reads {VERSION})", "v")
    header = as_map(doc, "header", _HEADER_KEYS)
    if header["type"] != LOG_TYPE:
        raise UnsupportedVersion(f"log type {header['type']!r} (expected {LOG_TYPE!r})", "type")


def _frame(doc: Any, lim: FrameLimits) -> SensorFrame:
    ids = GLOBAL_IDS
    if isinstance(doc, dict) and _ID_KEY in doc:
        ids = doc[_ID_KEY]
        need(isinstance(ids, str), _ID_KEY, f"expected a string, got {type(ids).__name__}")
        known = ", ".join(repr(k) for k in ID_KINDS)
        need(ids in ID_KINDS, _ID_KEY, f"{ids!r}: expected one of {known}", InvalidValue)
        doc = {key: value for key, value in doc.items() if key != _ID_KEY}
    top = as_map(doc, "frame", _FRAME_KEYS)
    robot = robot_id(top["robot"], "robot")
    k = as_int(top["k"], "k", 1, MAX_STEP)
    odometry = _numbers(top["odometry"], "odometry", 3)
    raw = top["detections"]
    need(isinstance(raw, list), "detections", "expected an array")
    dets = tuple(_detection(d, f"detections[{i}]", ids) for i, d in enumerate(raw))
    frame = SensorFrame(robot, k, odometry, dets, np.full(3, np.nan), ids)
    try:
        encode_frame(frame, lim)  # the wire's value rules: finite, ids unique, M, limits
    except LocalProtocolError as exc:
        field = _WIRE_NAME.sub(lambda m: _LOG_NAMES[m.group(1)], exc.field)
        raise MalformedMessage(str(exc).removeprefix(f"{exc.field}: "), field) from None
    return frame


def _detection(value: Any, where: str, ids: str) -> Detection:
    if ids == NO_IDS:
        d = as_map(value, where, _DETECTION_KEYS_NO_ID)
        oid = NO_ID
    else:
        d = as_map(value, where, _DETECTION_KEYS)
        oid = as_int(d["id"], f"{where}.id", 0, MAX_OBJECT_ID)
    # z_geo: 3 numbers (a pose object) or 2 (a point's bearing and range); encode_frame checks
    # which, and that a frame's detections agree
    return Detection(
        oid, _numbers(d["z_geo"], f"{where}.z_geo"), _numbers(d["z_sem"], f"{where}.z_sem")
    )


def _numbers(value: Any, field: str, length: int | None = None) -> NDArray[np.float64]:
    """A JSON array of numbers (not booleans) as float64, of ``length`` unless None."""
    need(isinstance(value, list), field, "expected an array of numbers")
    if length is not None:
        need(len(value) == length, field, f"expected {length} numbers, got {len(value)}")
    need(all(type(x) in (int, float) for x in value), field, "expected numbers only")
    try:
        return np.array(value, dtype=np.float64)
    except OverflowError:  # an integer beyond float64's range
        raise InvalidValue("number out of range", field) from None


def _floats(values: Any) -> list[float]:
    return [float(x) for x in np.asarray(values, dtype=np.float64)]
