"""The wire codec of sensor frames, key ``semfleet/<fleet>/frames/<robot>`` (docs/wire.md).

A frame is a msgpack map ``{"v": 1, "type": "frame", "robot": str, "k": int, "odo": bin,
"truth": bin | nil, "det": [{"id": int, "geo": bin, "sem": bin}, ...]}``, every float array raw
little-endian float64; with ``"ids": "local" | "none"`` when the detections' ids are not global
object ids (absent: global; a frame without ids has no ``id`` in its detections). A real robot
has no ground truth: it sends ``truth: nil``, which decodes to a (3,) array of NaN (the one place
a NaN may appear in a decoded frame), and a frame whose ``true_pose`` is all NaN encodes to nil.
As in ``protocol.codec``, ``decode_frame`` raises only :class:`RemoteProtocolError` subclasses
naming the field, and ``encode_frame`` raises :class:`LocalProtocolError` for anything the
decoder would reject under the same limits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import msgpack
import numpy as np
from numpy.typing import NDArray

from estimator.models import (
    GLOBAL_IDS,
    ID_KINDS,
    MAX_STEP,
    NO_ID,
    NO_IDS,
    Detection,
    SensorFrame,
)
from protocol.errors import (
    InvalidValue,
    LimitExceeded,
    LocalProtocolError,
    MalformedMessage,
    RemoteProtocolError,
    UnsupportedVersion,
)
from protocol.validate import as_int, as_map, decode_document, need, robot_id, valid_id

Array = NDArray[np.float64]

VERSION = 1
FRAME = "frame"
MAX_OBJECT_ID = 2**32 - 1
MAX_SCORES = 64  # length of a score vector when FrameLimits.num_classes is not given
_F64 = np.dtype("<f8")
_TOP_KEYS = frozenset({"v", "type", "robot", "k", "odo", "truth", "det"})
_ID_KEY = "ids"  # optional: absent means global ids
_DET_KEYS = frozenset({"id", "geo", "sem"})
_DET_KEYS_NO_ID = frozenset({"geo", "sem"})
_IDS_RULE = f"expected one of {', '.join(repr(k) for k in ID_KINDS)}"
# A detection's geometry: a pose object's relative pose (x, y, θ) or a point's (bearing, range)
# (estimator.models.objects); every detection of a frame is of one kind.
GEO_LENGTHS = (3, 2)
_GEO_RULE = "{} numbers: 3 (x, y, θ of a pose object) or 2 (bearing, range of a point)"
_GEO_SAME = "a frame's detections are of one kind (every geo of det[0]'s length)"


@dataclass(frozen=True, slots=True)
class FrameLimits:
    """What a receiver accepts. ``num_classes``: the exact length M of every score vector, or
    None for any M in 1..64 (the same M for all detections of a frame)."""

    num_classes: int | None = None
    max_detections: int = 256
    max_message_bytes: int = 1024 * 1024


def _scores_problem(m: int, first: int | None, lim: FrameLimits) -> RemoteProtocolError | None:
    """Why a score vector of length ``m`` may not follow one of length ``first``, if it may not
    (the error without its field, which the caller adds)."""
    if lim.num_classes is not None and m != lim.num_classes:
        return MalformedMessage(f"expected {lim.num_classes} scores, got {m}")
    if m < 1:
        return MalformedMessage("expected at least one score")
    if m > MAX_SCORES:
        return LimitExceeded(f"{m} scores > {MAX_SCORES}")
    if first is not None and m != first:
        return MalformedMessage(f"{m} scores, but the frame's first detection has {first}")
    return None


# --------------------------------------------------------------------------- encode


def _local(cond: bool, field: str, message: str) -> None:
    if not cond:
        raise LocalProtocolError(message, field)


def _vector(value: Any, field: str, length: int | None) -> Array:
    """``value`` as a finite little-endian float64 vector, of ``length`` unless None."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError):
        raise LocalProtocolError("expected a float array", field) from None
    _local(arr.dtype.kind in "fiu", field, f"expected real numbers, got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=_F64)
    shape_ok = arr.ndim == 1 and (length is None or arr.shape[0] == length)
    _local(shape_ok, field, f"expected shape ({length if length else 'M'},), got {arr.shape}")
    _local(bool(np.isfinite(arr).all()), field, "non-finite number")
    return arr


def _is_int(value: Any) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)


def encode_frame(frame: SensorFrame, limits: FrameLimits | None = None) -> bytes:
    """Bytes of a sensor frame. A ``true_pose`` of three NaN is sent as ``truth: nil``."""
    lim = limits or FrameLimits()
    _local(valid_id(frame.robot), "robot", f"invalid robot id {frame.robot!r}")
    _local(_is_int(frame.k) and 1 <= frame.k <= MAX_STEP, "k", f"{frame.k!r} outside 1..{MAX_STEP}")
    odo = _vector(frame.odometry, "odo", 3)
    truth = None
    if not _no_truth(frame.true_pose):
        truth = _vector(frame.true_pose, "truth", 3).tobytes()
    ids = frame.ids
    _local(isinstance(ids, str) and ids in ID_KINDS, _ID_KEY, f"{ids!r}: {_IDS_RULE}")
    raw = _encode_detections(frame.detections, lim, ids)
    doc: dict[str, Any] = {
        "v": VERSION,
        "type": FRAME,
        "robot": frame.robot,
        "k": int(frame.k),
        "odo": odo.tobytes(),
        "truth": truth,
        "det": raw,
    }
    if ids != GLOBAL_IDS:  # a frame of global ids keeps the bytes it always had
        doc[_ID_KEY] = ids
    blob = bytes(msgpack.packb(doc, use_bin_type=True))
    _local(
        len(blob) <= lim.max_message_bytes,
        "message",
        f"{len(blob)} bytes > {lim.max_message_bytes}",
    )
    return blob


def _encode_detections(
    dets: tuple[Detection, ...], lim: FrameLimits, ids: str
) -> list[dict[str, Any]]:
    _local(len(dets) <= lim.max_detections, "det", f"{len(dets)} > {lim.max_detections}")
    seen: set[int] = set()
    first: int | None = None
    geo_length: int | None = None
    raw = []
    for i, d in enumerate(dets):
        where = f"det[{i}]"
        oid = d.object_id
        if ids == NO_IDS:
            # nothing but NO_ID: an id in a frame without ids would be carried nowhere (and a
            # simulator's truth must not ride along unseen)
            _local(
                oid == NO_ID, f"{where}.id", f"{oid!r} in a frame without ids (expected {NO_ID})"
            )
        else:
            id_ok = _is_int(oid) and 0 <= oid <= MAX_OBJECT_ID
            _local(id_ok, f"{where}.id", f"{oid!r} outside 0..2³²−1")
            _local(int(oid) not in seen, f"{where}.id", f"duplicate object id {oid}")
            seen.add(int(oid))
        geo = _vector(d.z_geo, f"{where}.geo", None)
        _local(geo.shape[0] in GEO_LENGTHS, f"{where}.geo", _GEO_RULE.format(geo.shape[0]))
        _local(geo.shape[0] == (geo_length or geo.shape[0]), f"{where}.geo", _GEO_SAME)
        geo_length = geo.shape[0]
        sem = _vector(d.z_sem, f"{where}.sem", None)
        problem = _scores_problem(sem.shape[0], first, lim)
        _local(problem is None, f"{where}.sem", str(problem))
        first = sem.shape[0]
        det: dict[str, Any] = {"geo": geo.tobytes(), "sem": sem.tobytes()}
        if ids != NO_IDS:
            det = {"id": int(oid), **det}
        raw.append(det)
    return raw


def _no_truth(value: Any) -> bool:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return False
    return arr.shape == (3,) and bool(np.isnan(arr).all())


# --------------------------------------------------------------------------- decode


def decode_frame(data: bytes, limits: FrameLimits | None = None) -> SensorFrame:
    """Parse and validate a frame. Raises only :class:`RemoteProtocolError` subclasses."""
    lim = limits or FrameLimits()
    return decode_document(data, lim.max_message_bytes, lambda doc: _decode_doc(doc, lim))


def _floats(value: Any, field: str, length: int | None) -> Array:
    """A float64 blob of ``length`` numbers (any whole number of them if None), all finite."""
    need(isinstance(value, bytes), field, "expected binary float64 data")
    if length is None:
        need(len(value) % 8 == 0, field, f"{len(value)} bytes is not a whole number of float64")
    else:
        need(len(value) == 8 * length, field, f"expected {8 * length} bytes, got {len(value)}")
    arr = np.frombuffer(value, dtype=_F64).astype(np.float64)
    need(bool(np.isfinite(arr).all()), field, "non-finite number", InvalidValue)
    return arr


def _decode_doc(doc: Any, lim: FrameLimits) -> SensorFrame:
    need(isinstance(doc, dict), "message", f"expected a map, got {type(doc).__name__}")
    if "v" in doc and (type(doc["v"]) is not int or doc["v"] != VERSION):
        raise UnsupportedVersion(f"schema version {doc['v']!r} (this side speaks {VERSION})", "v")
    ids = GLOBAL_IDS
    if _ID_KEY in doc:
        ids = doc[_ID_KEY]
        need(isinstance(ids, str), _ID_KEY, f"expected a string, got {type(ids).__name__}")
        need(ids in ID_KINDS, _ID_KEY, f"{ids!r}: {_IDS_RULE}", InvalidValue)
        doc = {key: value for key, value in doc.items() if key != _ID_KEY}
    top = as_map(doc, "message", _TOP_KEYS)
    if top["type"] != FRAME:
        raise UnsupportedVersion(f"message type {top['type']!r}", "type")
    robot = robot_id(top["robot"], "robot")
    k = as_int(top["k"], "k", 1, MAX_STEP)
    odo = _floats(top["odo"], "odo", 3)
    truth = np.full(3, np.nan) if top["truth"] is None else _floats(top["truth"], "truth", 3)
    dets = _decode_detections(top["det"], lim, ids)
    return SensorFrame(robot, k, odo, tuple(dets), truth, ids)


def _decode_detections(raw: Any, lim: FrameLimits, ids: str) -> list[Detection]:
    need(isinstance(raw, list), "det", "expected an array")
    need(len(raw) <= lim.max_detections, "det", f"{len(raw)} > {lim.max_detections}", LimitExceeded)
    seen: set[int] = set()
    first: int | None = None
    geo_length: int | None = None
    dets = []
    for i, value in enumerate(raw):
        where = f"det[{i}]"
        if ids == NO_IDS:
            d = as_map(value, where, _DET_KEYS_NO_ID)
            oid = NO_ID
        else:
            d = as_map(value, where, _DET_KEYS)
            oid = as_int(d["id"], f"{where}.id", 0, MAX_OBJECT_ID)
            need(oid not in seen, f"{where}.id", f"duplicate object id {oid}", InvalidValue)
            seen.add(oid)
        geo = _floats(d["geo"], f"{where}.geo", None)
        # malformed, as a score vector of the wrong length is: the blob's shape is wrong
        need(geo.shape[0] in GEO_LENGTHS, f"{where}.geo", _GEO_RULE.format(geo.shape[0]))
        need(geo.shape[0] == (geo_length or geo.shape[0]), f"{where}.geo", _GEO_SAME)
        geo_length = geo.shape[0]
        sem = _floats(d["sem"], f"{where}.sem", None)
        problem = _scores_problem(sem.shape[0], first, lim)
        if problem is not None:
            raise type(problem)(str(problem), f"{where}.sem")
        first = sem.shape[0]
        dets.append(Detection(oid, geo, sem))
    return dets
