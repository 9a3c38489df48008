"""The sensor-frame codec (docs/wire.md, "Sensor frames"): bit-exact round trips, nil ground truth,
one error class per fault naming the field, and fuzzing that proves nothing but a
RemoteProtocolError escapes ``decode_frame`` and that ``encode_frame`` never emits bytes
``decode_frame`` would reject.

Malformed documents are made by unpacking a valid frame, changing one field and repacking it.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.models import LOCAL_IDS, MAX_STEP, NO_ID, NO_IDS, Detection, SensorFrame
from protocol.errors import (
    InvalidValue,
    LimitExceeded,
    LocalProtocolError,
    MalformedMessage,
    RemoteProtocolError,
    UnsupportedVersion,
)
from protocol.frames import FrameLimits, decode_frame, encode_frame
from tests.protocol import fuzz
from tests.protocol.fuzz import FUZZ, Path, field_name, get_at, pack

NO_TRUTH = np.full(3, np.nan)


def make_frame(
    rng: np.random.Generator,
    robot: str = "r1",
    k: int = 7,
    detections: int | None = None,
    scores: int | None = None,
    truth: bool = True,
) -> SensorFrame:
    """A valid frame: 0..5 detections of distinct ids, M ∈ 1..6 scores each."""
    count = int(rng.integers(0, 6)) if detections is None else detections
    m = int(rng.integers(1, 7)) if scores is None else scores
    ids: Any = rng.choice(2**32, size=count, replace=False) if count else []
    dets = tuple(Detection(int(j), fuzz.finite(rng, (3,)), fuzz.finite(rng, (m,))) for j in ids)
    true_pose = fuzz.finite(rng, (3,)) if truth else NO_TRUTH.copy()
    return SensorFrame(robot, k, fuzz.finite(rng, (3,)), dets, true_pose)


def _bits(a: Any) -> bytes:
    return np.asarray(a, dtype="<f8").tobytes()


def assert_same_frame(got: SensorFrame, want: SensorFrame) -> None:
    """Equal to the bit (−0.0 and subnormals included); a missing truth is NaN on both sides."""
    assert (got.robot, got.k, got.ids) == (want.robot, want.k, want.ids)
    assert _bits(got.odometry) == _bits(want.odometry)
    if np.isnan(want.true_pose).all():
        assert got.true_pose.shape == (3,) and np.isnan(got.true_pose).all()
    else:
        assert _bits(got.true_pose) == _bits(want.true_pose)
    assert len(got.detections) == len(want.detections)
    for g, w in zip(got.detections, want.detections, strict=True):
        assert g.object_id == w.object_id
        for a, b in ((g.z_geo, w.z_geo), (g.z_sem, w.z_sem)):
            assert a.dtype == np.float64 and a.shape == b.shape
            assert np.array_equal(a, b) and _bits(a) == _bits(b)


REF = SensorFrame(
    "r1",
    7,
    np.array([0.25, -0.0, 5e-324]),
    (
        Detection(4, np.array([1.0, 2.0, -0.5]), np.array([0.1, 0.9, -0.0])),
        Detection(2**32 - 1, np.array([-3.0, 0.0, 3.0]), np.array([0.7, 0.2, 0.1])),
        Detection(0, np.array([0.5, 0.5, 0.5]), np.array([1e300, -1e-300, 2.0])),
    ),
    np.array([10.0, -2.5, 1.5]),
)
# The same detections under a robot-local tracker's ids, and without ids (docs/wire.md, "ids").
REF_LOCAL = dataclasses.replace(REF, ids=LOCAL_IDS)
REF_NONE = dataclasses.replace(
    REF,
    ids=NO_IDS,
    detections=tuple(dataclasses.replace(d, object_id=NO_ID) for d in REF.detections),
)
REF_BLOB = encode_frame(REF)
REF_DOC: dict[str, Any] = msgpack.unpackb(REF_BLOB, raw=False)
BASE_FRAMES = (
    REF,
    dataclasses.replace(REF, true_pose=NO_TRUTH),
    SensorFrame("x" * 32, MAX_STEP, np.zeros(3), (), np.zeros(3)),
    *(make_frame(np.random.default_rng(seed), truth=seed % 2 == 0) for seed in (1, 2, 3)),
    REF_LOCAL,
    REF_NONE,
)
BASE_BLOBS = tuple(encode_frame(f) for f in BASE_FRAMES)
BASE_DOCS = tuple(msgpack.unpackb(b, raw=False) for b in BASE_BLOBS)


def _check_decoded(frame: SensorFrame, lim: FrameLimits) -> None:
    """What a decoded frame promises, and that it survives another round trip."""
    assert frame.k >= 1 and len(frame.detections) <= lim.max_detections
    assert np.isfinite(frame.odometry).all()
    assert np.isfinite(frame.true_pose).all() or np.isnan(frame.true_pose).all()
    ids = [d.object_id for d in frame.detections]
    if frame.ids == NO_IDS:
        assert set(ids) <= {NO_ID}
    else:
        assert len(set(ids)) == len(ids)
    for d in frame.detections:
        assert np.isfinite(d.z_geo).all() and np.isfinite(d.z_sem).all()
    assert_same_frame(decode_frame(encode_frame(frame, lim), lim), frame)


WIRE = fuzz.Wire(decode_frame, REF_DOC, FrameLimits(), _check_decoded)


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("index", range(len(BASE_FRAMES)))
def test_frames_round_trip_is_bit_exact(index: int) -> None:
    got = decode_frame(BASE_BLOBS[index])
    assert_same_frame(got, BASE_FRAMES[index])
    assert encode_frame(got) == BASE_BLOBS[index]


def test_frames_wire_layout_matches_docs() -> None:
    assert list(REF_DOC) == ["v", "type", "robot", "k", "odo", "truth", "det"]
    assert (REF_DOC["v"], REF_DOC["type"], REF_DOC["robot"], REF_DOC["k"]) == (1, "frame", "r1", 7)
    assert REF_DOC["odo"] == REF.odometry.astype("<f8").tobytes()
    assert REF_DOC["truth"] == REF.true_pose.astype("<f8").tobytes()
    for raw, d in zip(REF_DOC["det"], REF.detections, strict=True):
        assert list(raw) == ["id", "geo", "sem"]
        assert raw["id"] == d.object_id
        assert raw["geo"] == d.z_geo.astype("<f8").tobytes()
        assert raw["sem"] == d.z_sem.astype("<f8").tobytes()


def test_frames_id_kind_travels_only_when_not_global() -> None:
    assert "ids" not in REF_DOC  # a frame of global ids has the bytes it always had
    local = msgpack.unpackb(encode_frame(REF_LOCAL), raw=False)
    assert local["ids"] == "local" and [d["id"] for d in local["det"]] == [4, 2**32 - 1, 0]
    none = msgpack.unpackb(encode_frame(REF_NONE), raw=False)
    assert none["ids"] == "none" and all(list(d) == ["geo", "sem"] for d in none["det"])
    assert decode_frame(pack({**REF_DOC, "ids": "global"})).ids == "global"


@pytest.mark.parametrize(
    ("doc", "error", "field", "says"),
    [
        ({**REF_DOC, "ids": "tracker"}, InvalidValue, "ids", "'tracker': expected one of"),
        ({**REF_DOC, "ids": 2}, MalformedMessage, "ids", "expected a string, got int"),
        ({**REF_DOC, "ids": None}, MalformedMessage, "ids", "expected a string"),
        ({**REF_DOC, "ids": "none"}, MalformedMessage, "det[0]", "unknown keys ['id']"),
        (
            {**msgpack.unpackb(encode_frame(REF_NONE), raw=False), "ids": "local"},
            MalformedMessage,
            "det[0]",
            "missing keys ['id']",
        ),
    ],
)
def test_decode_frame_refuses_a_malformed_id_kind(
    doc: dict[str, Any], error: type[Exception], field: str, says: str
) -> None:
    with pytest.raises(error) as caught:
        decode_frame(pack(doc))
    assert isinstance(caught.value, RemoteProtocolError)
    assert caught.value.field == field and says in str(caught.value)


def test_encode_frame_refuses_an_id_in_a_frame_without_ids() -> None:
    with pytest.raises(LocalProtocolError, match=r"det\[0\]\.id: 4 in a frame without ids"):
        encode_frame(dataclasses.replace(REF, ids=NO_IDS))
    with pytest.raises(LocalProtocolError, match="ids: 'tracker'"):
        encode_frame(dataclasses.replace(REF, ids="tracker"))


def test_frames_missing_truth_travels_as_nil_and_decodes_to_nan() -> None:
    blob = encode_frame(dataclasses.replace(REF, true_pose=NO_TRUTH))
    assert msgpack.unpackb(blob, raw=False)["truth"] is None
    got = decode_frame(blob)
    assert got.true_pose.shape == (3,) and np.isnan(got.true_pose).all()
    assert encode_frame(got) == blob


def test_frames_decode_accepts_bytearray_and_memoryview() -> None:
    assert_same_frame(decode_frame(bytearray(REF_BLOB)), REF)  # type: ignore[arg-type]
    assert_same_frame(decode_frame(memoryview(REF_BLOB)), REF)  # type: ignore[arg-type]


def test_frames_decoded_arrays_are_writable_copies() -> None:
    got = decode_frame(REF_BLOB)
    got.odometry[0] = 1.0
    got.detections[0].z_sem[0] = 1.0
    assert_same_frame(decode_frame(REF_BLOB), REF)


def _int_bytes(value: int) -> int:
    return 1 if value < 128 else 2 if value < 2**8 else 3 if value < 2**16 else 5


@pytest.mark.parametrize(
    ("robot", "k", "count", "m", "truth"),
    [("r1", 1, 0, 2, False), ("x" * 31, 300, 3, 31, True), ("r1", MAX_STEP, 16, 32, True)],
)
def test_frames_size_matches_docs(robot: str, k: int, count: int, m: int, truth: bool) -> None:
    frame = make_frame(np.random.default_rng(0), robot, k, count, m, truth)
    per_detection = sum(40 + 8 * m + _int_bytes(d.object_id) + (m >= 32) for d in frame.detections)
    k_bytes = 9 if k >= 2**32 else _int_bytes(k)
    documented = 65 + 1 + len(robot) + k_bytes + 25 * truth + 2 * (count > 15) + per_detection
    assert len(encode_frame(frame)) == documented


@settings(FUZZ, max_examples=1000)
@given(
    seed=st.integers(0, 2**32 - 1),
    robot=fuzz.ROBOT_IDS,
    k=st.integers(1, MAX_STEP),
    detections=st.integers(0, 8),
    scores=st.integers(1, 64),
    truth=st.booleans(),
)
def test_frames_round_trip_is_bit_exact_fuzz(
    seed: int, robot: str, k: int, detections: int, scores: int, truth: bool
) -> None:
    frame = make_frame(np.random.default_rng(seed), robot, k, detections, scores, truth)
    blob = encode_frame(frame)
    got = decode_frame(blob, FrameLimits(num_classes=scores))
    assert_same_frame(got, frame)
    assert encode_frame(got) == blob


# --------------------------------------------------------------------------- truncation, noise


@pytest.mark.parametrize("index", range(len(BASE_BLOBS)))
def test_frames_every_truncated_prefix_is_malformed(index: int) -> None:
    WIRE.assert_every_prefix_malformed(BASE_BLOBS[index])


def test_frames_trailing_bytes_are_malformed() -> None:
    WIRE.assert_rejected(REF_BLOB + b"\x00", MalformedMessage, "message")


@pytest.mark.parametrize("blob", [b"", b"\xc1", b"\x93\x01\x02\x03", b"\xa5frame", b"\xc0"])
def test_frames_non_map_documents_are_malformed(blob: bytes) -> None:
    WIRE.assert_rejected(blob, MalformedMessage, "message")


def test_frames_decode_rejects_non_bytes_input() -> None:
    WIRE.assert_rejected("not bytes", MalformedMessage, "message")  # type: ignore[arg-type]


@settings(FUZZ, max_examples=1000)
@given(blob=st.binary(max_size=512))
def test_frames_random_bytes_raise_only_remote_errors(blob: bytes) -> None:
    WIRE.decode_or_reject(blob)


@settings(FUZZ, max_examples=1000)
@given(index=st.integers(0, len(BASE_BLOBS) - 1), edits=fuzz.BYTE_EDITS)
def test_frames_corrupted_bytes_raise_only_remote_errors(
    index: int, edits: list[tuple[int, int]]
) -> None:
    WIRE.decode_or_reject(fuzz.corrupt(BASE_BLOBS[index], edits))


# --------------------------------------------------------------------------- one rule at a time


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize(
    ("path", "index"),
    [
        (("odo",), 0),
        (("odo",), 2),
        (("truth",), 1),
        (("det", 0, "geo"), 0),
        (("det", 2, "geo"), 2),
        (("det", 1, "sem"), 0),
        (("det", 2, "sem"), 2),
    ],
)
def test_frames_non_finite_number_is_invalid(path: Path, index: int, value: float) -> None:
    WIRE.assert_rejected(WIRE.poke(path, index, value), InvalidValue, field_name(path))


@pytest.mark.parametrize("path", [("odo",), ("truth",), ("det", 1, "geo")])
@pytest.mark.parametrize("change", [-8, 8, -1, 1, None])
def test_frames_wrong_blob_length_is_malformed(path: Path, change: int | None) -> None:
    """``change`` bytes added or cut; None empties the blob."""
    blob = get_at(REF_DOC, path)
    new = b"" if change is None else blob[:change] if change < 0 else blob + bytes(change)
    WIRE.assert_rejected(WIRE.with_(path, new), MalformedMessage, field_name(path))


@pytest.mark.parametrize(
    ("sem", "error"),
    [
        (b"", MalformedMessage),  # no score
        (bytes(12), MalformedMessage),  # not whole float64s
        (bytes(16), MalformedMessage),  # 2 scores after a detection with 3
        (bytes(32), MalformedMessage),
        (bytes(8 * 65), LimitExceeded),  # more than 64 scores
    ],
)
def test_frames_wrong_score_count_is_rejected(sem: bytes, error: type[RemoteProtocolError]) -> None:
    WIRE.assert_rejected(WIRE.with_(("det", 1, "sem"), sem), error, "det[1].sem")


def test_frames_score_count_must_equal_num_classes_when_given() -> None:
    WIRE.assert_rejected(REF_BLOB, MalformedMessage, "det[0].sem", FrameLimits(num_classes=2))
    assert_same_frame(decode_frame(REF_BLOB, FrameLimits(num_classes=3)), REF)
    frame = make_frame(np.random.default_rng(0), detections=2, scores=64)
    decode_frame(encode_frame(frame))
    with pytest.raises(LocalProtocolError):
        encode_frame(make_frame(np.random.default_rng(0), detections=2, scores=65))


def test_frames_duplicate_object_ids_are_invalid() -> None:
    WIRE.assert_rejected(WIRE.with_(("det", 2, "id"), 4), InvalidValue, "det[2].id")


@pytest.mark.parametrize(
    ("path", "value"),
    [
        (("k",), 0),
        (("k",), -1),
        (("k",), 2**63),
        (("det", 0, "id"), -1),
        (("det", 0, "id"), 2**32),
    ],
)
def test_frames_integer_out_of_range_is_invalid(path: Path, value: int) -> None:
    WIRE.assert_rejected(WIRE.with_(path, value), InvalidValue, field_name(path))


@pytest.mark.parametrize("robot", ["", "x" * 33, "r 1", "r/1", "rö", "r1\n"])
def test_frames_invalid_robot_id_is_invalid(robot: str) -> None:
    WIRE.assert_rejected(WIRE.with_(("robot",), robot), InvalidValue, "robot")


WRONG_TYPES = [
    (("robot",), 5),
    (("robot",), b"r1"),
    (("robot",), None),
    (("k",), 7.0),
    (("k",), "7"),
    (("k",), True),
    (("k",), None),
    (("odo",), [0.0, 0.0, 0.0]),
    (("odo",), None),
    (("odo",), "x" * 24),
    (("truth",), [1.0, 2.0, 3.0]),
    (("truth",), 0.0),
    (("det",), None),
    (("det",), {}),
    (("det",), b""),
    (("det", 0), []),
    (("det", 0), "det"),
    (("det", 0, "id"), 4.0),
    (("det", 0, "id"), "4"),
    (("det", 0, "id"), False),
    (("det", 0, "geo"), [1.0, 2.0, -0.5]),
    (("det", 0, "sem"), None),
    (("det", 0, "sem"), 0.5),
]


@pytest.mark.parametrize(
    ("path", "value"), [pytest.param(p, v, id=f"{field_name(p)}={v!r}") for p, v in WRONG_TYPES]
)
def test_frames_wrong_type_is_malformed(path: Path, value: Any) -> None:
    WIRE.assert_rejected(WIRE.with_(path, value), MalformedMessage, field_name(path))


@pytest.mark.parametrize("version", [0, 2, -1, "1", None, 1.0, True])
def test_frames_unknown_version_is_unsupported(version: Any) -> None:
    WIRE.assert_rejected(WIRE.with_(("v",), version), UnsupportedVersion, "v")


def test_frames_unknown_version_is_unsupported_whatever_its_layout() -> None:
    WIRE.assert_rejected(pack({"v": 2, "frames": []}), UnsupportedVersion, "v")


@pytest.mark.parametrize("kind", ["stack", "estimate", "Frame", "", None, b"frame"])
def test_frames_unknown_message_type_is_unsupported(kind: Any) -> None:
    WIRE.assert_rejected(WIRE.with_(("type",), kind), UnsupportedVersion, "type")


@pytest.mark.parametrize(
    ("path", "field"),
    [((k,), "message") for k in REF_DOC] + [(("det", 1, k), "det[1]") for k in REF_DOC["det"][1]],
)
def test_frames_missing_key_is_malformed(path: Path, field: str) -> None:
    WIRE.assert_rejected(WIRE.without(path), MalformedMessage, field)


@pytest.mark.parametrize("key", ["x", "V", "truth2", ""])
@pytest.mark.parametrize(("path", "field"), [((), "message"), (("det", 1), "det[1]")])
def test_frames_extra_key_is_malformed(path: Path, field: str, key: str) -> None:
    WIRE.assert_rejected(WIRE.with_((*path, key), 0), MalformedMessage, field)


def test_frames_non_string_map_keys_are_malformed() -> None:
    doc: dict[Any, Any] = copy.deepcopy(REF_DOC)
    doc[b"v"] = 1
    WIRE.assert_rejected(pack(doc), MalformedMessage, "message")


@pytest.mark.parametrize(
    ("limits", "field"),
    [
        (FrameLimits(max_detections=2), "det"),
        (FrameLimits(max_message_bytes=len(REF_BLOB) - 1), "message"),
    ],
)
def test_frames_over_limits_is_rejected(limits: FrameLimits, field: str) -> None:
    WIRE.assert_rejected(REF_BLOB, LimitExceeded, field, limits)
    with pytest.raises(LocalProtocolError) as caught:
        encode_frame(REF, limits)
    assert caught.value.field == field


def test_frames_exactly_at_limits_is_accepted() -> None:
    lim = FrameLimits(num_classes=3, max_detections=3, max_message_bytes=len(REF_BLOB))
    assert_same_frame(decode_frame(REF_BLOB, lim), REF)
    assert encode_frame(REF, lim) == REF_BLOB


# --------------------------------------------------------------------------- structured fuzz

MUTATOR = fuzz.Mutator(
    known_keys=("v", "type", "robot", "k", "odo", "truth", "det", "id", "geo", "sem"),
    strings=("frame", "r1", "r1\n", ""),
    edge_ints=(-1, 0, 1, 2**32 - 1, 2**32, MAX_STEP, MAX_STEP + 1, 2**63 - 1, 2**63),
)


@settings(FUZZ, max_examples=1200)
@given(
    index=st.integers(0, len(BASE_DOCS) - 1),
    edits=st.integers(1, 3),
    limits=st.sampled_from([None, None, FrameLimits(num_classes=3, max_detections=2)]),
    data=st.data(),
)
def test_frames_mutated_documents_raise_only_remote_errors(
    index: int, edits: int, limits: FrameLimits | None, data: st.DataObject
) -> None:
    WIRE.decode_or_reject(pack(MUTATOR.mutated(BASE_DOCS[index], edits, data)), limits)


# --------------------------------------------------------------------------- encode


def _nan_at(a: np.ndarray, value: float = math.nan) -> np.ndarray:
    out = np.array(a, dtype=float)
    out[-1] = value
    return out


def _frame(**changes: Any) -> SensorFrame:
    """REF with fields changed, wrong types allowed."""
    return dataclasses.replace(REF, **changes)


def _with_detection(index: int, **changes: Any) -> SensorFrame:
    dets = list(REF.detections)
    dets[index] = dataclasses.replace(dets[index], **changes)
    return dataclasses.replace(REF, detections=tuple(dets))


D0 = REF.detections[0]
ENCODE_REJECTS = [
    ("robot-space", _frame(robot="r 1"), "robot"),
    ("robot-newline", _frame(robot="r1\n"), "robot"),
    ("robot-int", _frame(robot=5), "robot"),
    ("k-0", _frame(k=0), "k"),
    ("k-2**63", _frame(k=2**63), "k"),
    ("k-float", _frame(k=7.0), "k"),
    ("k-bool", _frame(k=True), "k"),
    ("odo-nan", _frame(odometry=_nan_at(REF.odometry)), "odo"),
    ("odo-inf", _frame(odometry=_nan_at(REF.odometry, math.inf)), "odo"),
    ("odo-2", _frame(odometry=np.zeros(2)), "odo"),
    ("odo-3x1", _frame(odometry=np.zeros((3, 1))), "odo"),
    ("odo-complex", _frame(odometry=np.zeros(3, complex)), "odo"),
    ("odo-str", _frame(odometry="abc"), "odo"),
    ("odo-none", _frame(odometry=None), "odo"),
    ("truth-one-nan", _frame(true_pose=_nan_at(REF.true_pose)), "truth"),
    ("truth-inf", _frame(true_pose=np.full(3, math.inf)), "truth"),
    ("truth-4-nan", _frame(true_pose=np.full(4, math.nan)), "truth"),
    ("id-negative", _with_detection(0, object_id=-1), "det[0].id"),
    ("id-2**32", _with_detection(0, object_id=2**32), "det[0].id"),
    ("id-float", _with_detection(0, object_id=4.0), "det[0].id"),
    ("id-duplicate", _with_detection(1, object_id=4), "det[1].id"),
    ("geo-nan", _with_detection(0, z_geo=_nan_at(D0.z_geo)), "det[0].geo"),
    ("geo-4", _with_detection(0, z_geo=np.zeros(4)), "det[0].geo"),
    ("sem-inf", _with_detection(0, z_sem=_nan_at(D0.z_sem, -math.inf)), "det[0].sem"),
    ("sem-empty", _with_detection(0, z_sem=np.zeros(0)), "det[0].sem"),
    ("sem-2d", _with_detection(0, z_sem=np.zeros((3, 1))), "det[0].sem"),
    ("sem-other-length", _with_detection(1, z_sem=np.zeros(2)), "det[1].sem"),
]


@pytest.mark.parametrize(
    ("frame", "field"), [pytest.param(f, d, id=n) for n, f, d in ENCODE_REJECTS]
)
def test_frames_encode_rejects_what_decode_would_reject(frame: SensorFrame, field: str) -> None:
    with pytest.raises(LocalProtocolError) as caught:
        encode_frame(frame)
    assert caught.value.field == field


def test_frames_encode_accepts_integer_arrays_as_floats() -> None:
    frame = dataclasses.replace(REF, odometry=np.array([1, 2, 3]))
    assert decode_frame(encode_frame(frame)).odometry.tolist() == [1.0, 2.0, 3.0]


BAD_FLOATS = st.sampled_from((math.nan, math.inf, -math.inf))
BAD_VECTORS = (
    st.builds(np.zeros, st.integers(0, 5)) | st.builds(np.full, st.just(3), BAD_FLOATS)
).map(np.asarray)


@settings(FUZZ, max_examples=1000)
@given(
    seed=st.integers(0, 2**32 - 1),
    k=st.sampled_from((0, 1, MAX_STEP, MAX_STEP + 1, 2**63 - 1, 2**63, -1)),
    odometry=st.none() | BAD_VECTORS,
    truth=st.none() | BAD_VECTORS,
    ids=st.none() | st.lists(st.sampled_from((-1, 0, 1, 2**32 - 1, 2**32)), min_size=3, max_size=3),
    sems=st.none() | st.lists(BAD_VECTORS, min_size=3, max_size=3),
)
def test_frames_encode_emits_only_what_decode_accepts(
    seed: int,
    k: int,
    odometry: np.ndarray | None,
    truth: np.ndarray | None,
    ids: list[int] | None,
    sems: list[np.ndarray] | None,
) -> None:
    """Frames with some fields replaced by doubtful values: ``encode_frame`` refuses them with a
    LocalProtocolError, or emits bytes that decode back to the same frame."""
    frame = make_frame(np.random.default_rng(seed), k=1, detections=3)
    dets = list(frame.detections)
    for i, d in enumerate(dets):
        dets[i] = Detection(
            d.object_id if ids is None else ids[i], d.z_geo, d.z_sem if sems is None else sems[i]
        )
    frame = SensorFrame(
        frame.robot,
        k,
        frame.odometry if odometry is None else odometry,
        tuple(dets),
        frame.true_pose if truth is None else truth,
    )
    try:
        blob = encode_frame(frame)
    except LocalProtocolError as exc:
        assert exc.field
        return
    assert_same_frame(decode_frame(blob), frame)


def test_a_frame_of_point_detections_round_trips_and_one_kind_per_frame() -> None:
    """Point objects (issue 44): a detection's geo is (bearing, range), 16 bytes; every
    detection of a frame is of one kind; neither 1 nor 4 numbers is a detection."""
    dets = (
        Detection(3, np.array([0.2, 1.5]), np.array([0.1, 0.9])),
        Detection(9, np.array([-1.0, 4.0]), np.array([0.7, 0.3])),
    )
    frame = SensorFrame("r1", 4, np.array([0.1, 0.0, 0.01]), dets, np.full(3, np.nan))
    back = decode_frame(encode_frame(frame))
    assert [d.z_geo.tolist() for d in back.detections] == [[0.2, 1.5], [-1.0, 4.0]]
    mixed = (dets[0], Detection(9, np.array([1.0, 0.0, 0.1]), np.array([0.7, 0.3])))
    with pytest.raises(LocalProtocolError) as caught:
        encode_frame(SensorFrame("r1", 4, frame.odometry, mixed, frame.true_pose))
    assert caught.value.field == "det[1].geo"
    for n in (1, 4):
        odd = (Detection(3, np.zeros(n), np.array([0.1, 0.9])),)
        with pytest.raises(LocalProtocolError) as caught:
            encode_frame(SensorFrame("r1", 4, frame.odometry, odd, frame.true_pose))
        assert caught.value.field == "det[0].geo"
