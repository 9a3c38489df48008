"""The estimate codec (docs/wire.md, "Estimates"): bit-exact round trips of belief snapshots, one
error class per fault naming the field, and fuzzing that proves nothing but a RemoteProtocolError
escapes ``decode_estimate`` and that ``encode_estimate`` never emits bytes it would reject.

Malformed documents are made by unpacking a valid estimate, changing one field and repacking it.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import struct
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.hybrid import BeliefSnapshot
from estimator.models import MAX_STEP
from protocol.errors import (
    InvalidValue,
    LimitExceeded,
    LocalProtocolError,
    MalformedMessage,
    RemoteProtocolError,
    UnsupportedVersion,
)
from protocol.estimate import (
    MAX_COUNTERS,
    EstimateLimits,
    EstimateMessage,
    decode_estimate,
    decode_estimate_head,
    encode_estimate,
)
from tests.protocol import fuzz
from tests.protocol.fuzz import FUZZ, Path, field_name, get_at, pack

ARRAYS = ("weights", "classes", "robot_pose", "robot_cov", "object_pose", "object_cov")
FLOAT_ARRAYS = tuple(a for a in ARRAYS if a != "classes")


def _symmetric(rng: np.random.Generator, count: int) -> np.ndarray:
    """(count, 3, 3) exactly symmetric matrices (the upper triangle mirrored, −0.0 kept)."""
    upper = fuzz.finite(rng, (count, 3, 3))
    return np.where(np.triu(np.ones((3, 3), bool)), upper, upper.transpose(0, 2, 1))


def _weights(rng: np.random.Generator, h: int) -> np.ndarray:
    """Normalised weights, some exactly 0.0 or −0.0."""
    w = rng.random(h) * (rng.random(h) < 0.8)
    w[int(rng.integers(h))] += 1.0
    w /= w.sum()
    return np.where(w == 0.0, rng.choice([0.0, -0.0], size=h), w)


def make_snapshot(
    rng: np.random.Generator, h: int | None = None, n: int | None = None, num_classes: int = 3
) -> BeliefSnapshot:
    """A valid snapshot: H ∈ 1..5 hypotheses over n ∈ 0..5 distinct objects."""
    h = int(rng.integers(1, 6)) if h is None else h
    n = int(rng.integers(0, 6)) if n is None else n
    ids = tuple(int(j) for j in rng.choice(2**32, size=n, replace=False)) if n else ()
    return BeliefSnapshot(
        ids,
        _weights(rng, h),
        rng.integers(0, num_classes, (h, n)).astype(np.int64),
        fuzz.finite(rng, (h, 3)),
        _symmetric(rng, h),
        fuzz.finite(rng, (h, n, 3)),
        _symmetric(rng, h * n).reshape(h, n, 3, 3),
    )


def _probs(rng: np.random.Generator, n: int, m: int) -> np.ndarray:
    """(n, m) rows that each sum to 1, some entries exactly 0.0 or −0.0."""
    p = rng.random((n, m)) * (rng.random((n, m)) < 0.7)
    p[np.arange(n), rng.integers(0, m, n)] += 1.0
    p /= p.sum(axis=1, keepdims=True)
    return np.where(p == 0.0, rng.choice([0.0, -0.0], size=(n, m)), p)


def make_per_object_snapshot(
    rng: np.random.Generator, n: int | None = None, num_classes: int = 3
) -> BeliefSnapshot:
    """A valid snapshot of a belief with per-object class marginals: one hypothesis, its classes
    the most probable of each object, ``class_probs`` (n, num_classes)."""
    snap = make_snapshot(rng, h=1, n=n, num_classes=num_classes)
    probs = _probs(rng, len(snap.object_ids), num_classes)
    best = np.argmax(probs, axis=1).astype(np.int64)[None]
    return dataclasses.replace(snap, classes=best, class_probs=probs)


def assert_same_snapshot(got: BeliefSnapshot, want: BeliefSnapshot) -> None:
    """Equal to the bit, −0.0 and subnormals included, with the snapshot's dtypes."""
    assert got.object_ids == tuple(want.object_ids)
    for name in ARRAYS:
        g, w = getattr(got, name), getattr(want, name)
        assert g.dtype == (np.int64 if name == "classes" else np.float64), name
        assert g.shape == w.shape and np.array_equal(g, w), name
        assert g.tobytes() == np.asarray(w, dtype=g.dtype).tobytes(), name
    if want.class_probs is None:
        assert got.class_probs is None
    else:
        g, w = got.class_probs, np.asarray(want.class_probs)
        assert g is not None and g.dtype == np.float64
        assert g.shape == w.shape and g.tobytes() == w.astype(np.float64).tobytes()


def assert_same_estimate(got: EstimateMessage, want: EstimateMessage) -> None:
    assert (got.robot, got.k, got.counters) == (want.robot, want.k, want.counters)
    assert got.fused == want.fused
    assert sorted(got.beliefs) == sorted(want.beliefs)
    for name, snap in want.beliefs.items():
        assert_same_snapshot(got.beliefs[name], snap)


REF = EstimateMessage(
    "r2",
    12,
    {
        "local": make_snapshot(np.random.default_rng(1), h=2, n=3, num_classes=2),
        "distributed": make_snapshot(np.random.default_rng(2), h=3, n=4, num_classes=2),
    },
    {"stacks_sent": 12, "invalid": 0},
)
REF_BLOB = encode_estimate(REF)
REF_DOC: dict[str, Any] = msgpack.unpackb(REF_BLOB, raw=False)
BASE_MESSAGES = (
    REF,
    EstimateMessage("x" * 32, 0, {"local": make_snapshot(np.random.default_rng(3), h=1, n=0)}),
    EstimateMessage(
        "r9",
        MAX_STEP,
        {
            "a": make_snapshot(np.random.default_rng(4)),
            "b_c": make_snapshot(np.random.default_rng(5)),
        },
        {"x" * 48: 2**63 - 1},
    ),
    EstimateMessage(  # per-object class marginals beside a realisation table
        "r3",
        7,
        {
            "distributed": make_per_object_snapshot(np.random.default_rng(6), n=4),
            "local": make_snapshot(np.random.default_rng(7), h=2, n=2),
        },
    ),
    EstimateMessage(  # the versions its fusion integrated
        "r4",
        9,
        {"distributed": make_snapshot(np.random.default_rng(8), h=2, n=2)},
        {"stacks_sent": 3},
        {"r1": 8, "r2": 0, "x" * 32: MAX_STEP},
    ),
)
BASE_BLOBS = tuple(encode_estimate(m) for m in BASE_MESSAGES)
BASE_DOCS = tuple(msgpack.unpackb(b, raw=False) for b in BASE_BLOBS)
LOCAL = ("beliefs", "local")  # 2 hypotheses, 3 objects


def _array(path: Path, values: Any, dtype: str = "<f8") -> bytes:
    return WIRE.with_(path, np.asarray(values, dtype=dtype).tobytes())


def _check_valid(msg: EstimateMessage, lim: EstimateLimits) -> None:
    """What a decoded estimate promises, and that it survives another round trip."""
    assert msg.k >= 0 and 1 <= len(msg.beliefs) <= 8
    assert all(v >= 0 for v in msg.counters.values())
    for snap in msg.beliefs.values():
        n, h = len(snap.object_ids), snap.weights.shape[0]
        assert len(set(snap.object_ids)) == n <= lim.max_objects and 1 <= h <= lim.max_hypotheses
        assert abs(snap.weights.sum() - 1.0) <= lim.weight_tol and (snap.weights >= 0).all()
        assert snap.classes.shape == (h, n) and ((snap.classes >= 0) & (snap.classes < 64)).all()
        assert snap.object_cov.shape == (h, n, 3, 3) and snap.robot_cov.shape == (h, 3, 3)
        for name in FLOAT_ARRAYS:
            assert np.isfinite(getattr(snap, name)).all()
        p = snap.class_probs
        if p is not None:
            assert p.ndim == 2 and p.shape[0] == n and 1 <= p.shape[1] <= lim.num_classes
            assert np.isfinite(p).all() and ((p >= 0) & (p <= 1)).all()
            assert (np.abs(p.sum(axis=1) - 1.0) <= lim.weight_tol).all()
    if msg.fused is not None:
        assert len(msg.fused) <= lim.max_fused
        assert all(0 <= stamp <= MAX_STEP for stamp in msg.fused.values())
    assert_same_estimate(decode_estimate(encode_estimate(msg, lim), lim), msg)


WIRE = fuzz.Wire(decode_estimate, REF_DOC, EstimateLimits(), _check_valid)


# --------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("index", range(len(BASE_MESSAGES)))
def test_estimate_round_trip_is_bit_exact(index: int) -> None:
    got = decode_estimate(BASE_BLOBS[index])
    assert_same_estimate(got, BASE_MESSAGES[index])
    assert encode_estimate(got) == BASE_BLOBS[index]


def test_estimate_wire_layout_matches_docs() -> None:
    assert list(REF_DOC) == ["v", "type", "robot", "k", "beliefs", "counters"]
    assert (REF_DOC["v"], REF_DOC["type"], REF_DOC["robot"], REF_DOC["k"]) == (
        3,
        "estimate",
        "r2",
        12,
    )
    assert list(REF_DOC["beliefs"]) == ["distributed", "local"]  # sorted by name
    assert REF_DOC["counters"] == {"invalid": 0, "stacks_sent": 12}
    local = REF.beliefs["local"]
    raw = REF_DOC["beliefs"]["local"]
    assert list(raw) == ["objects", *ARRAYS]
    assert raw["objects"] == list(local.object_ids)
    assert raw["classes"] == local.classes.astype("<u1").tobytes()  # one byte per class
    for name in FLOAT_ARRAYS:
        assert raw[name] == getattr(local, name).astype("<f8").tobytes()


def test_estimate_counters_are_optional() -> None:
    msg = EstimateMessage("r1", 3, {"local": REF.beliefs["local"]})
    assert msg.counters == {}
    assert msgpack.unpackb(encode_estimate(msg), raw=False)["counters"] == {}
    assert_same_estimate(decode_estimate(encode_estimate(msg)), msg)


def test_estimate_decode_accepts_bytearray_and_memoryview() -> None:
    assert_same_estimate(decode_estimate(bytearray(REF_BLOB)), REF)  # type: ignore[arg-type]
    assert_same_estimate(decode_estimate(memoryview(REF_BLOB)), REF)  # type: ignore[arg-type]


def test_estimate_negative_zero_and_subnormals_survive() -> None:
    snap = make_snapshot(np.random.default_rng(0), h=2, n=1)
    tiny = dataclasses.replace(
        snap,
        weights=np.array([-0.0, 1.0]),
        robot_pose=np.array([[-0.0, 5e-324, -5e-324], [0.0, -0.0, 1e-310]]),
    )
    got = decode_estimate(encode_estimate(EstimateMessage("r1", 1, {"local": tiny})))
    assert_same_snapshot(got.beliefs["local"], tiny)
    assert math.copysign(1.0, got.beliefs["local"].weights[0]) == -1.0


@settings(FUZZ, max_examples=600)
@given(
    seed=st.integers(0, 2**32 - 1),
    k=st.integers(0, MAX_STEP),
    names=st.lists(st.text("abcxyz_", min_size=1, max_size=32), min_size=1, max_size=3),
    counters=st.dictionaries(
        st.text("abcxyz_", min_size=1, max_size=48), st.integers(0, 2**63 - 1), max_size=6
    ),
)
def test_estimate_round_trip_is_bit_exact_fuzz(
    seed: int, k: int, names: list[str], counters: dict[str, int]
) -> None:
    rng = np.random.default_rng(seed)
    msg = EstimateMessage("r1", k, {name: make_snapshot(rng) for name in names}, counters)
    blob = encode_estimate(msg)
    got = decode_estimate(blob)
    assert_same_estimate(got, msg)
    assert encode_estimate(got) == blob


# --------------------------------------------------------------------------- truncation, noise


@pytest.mark.parametrize("index", range(len(BASE_BLOBS)))
def test_estimate_every_truncated_prefix_is_malformed(index: int) -> None:
    WIRE.assert_every_prefix_malformed(BASE_BLOBS[index])


def test_estimate_trailing_bytes_are_malformed() -> None:
    WIRE.assert_rejected(REF_BLOB + b"\x00", MalformedMessage, "message")


@pytest.mark.parametrize("blob", [b"", b"\xc1", b"\x93\x01\x02\x03", b"\xa8estimate", b"\xc0"])
def test_estimate_non_map_documents_are_malformed(blob: bytes) -> None:
    WIRE.assert_rejected(blob, MalformedMessage, "message")


def test_estimate_decode_rejects_non_bytes_input() -> None:
    WIRE.assert_rejected(None, MalformedMessage, "message")  # type: ignore[arg-type]


@settings(FUZZ, max_examples=500)
@given(blob=st.binary(max_size=512))
def test_estimate_random_bytes_raise_only_remote_errors(blob: bytes) -> None:
    WIRE.decode_or_reject(blob)


@settings(FUZZ, max_examples=500)
@given(index=st.integers(0, len(BASE_BLOBS) - 1), edits=fuzz.BYTE_EDITS)
def test_estimate_corrupted_bytes_raise_only_remote_errors(
    index: int, edits: list[tuple[int, int]]
) -> None:
    WIRE.decode_or_reject(fuzz.corrupt(BASE_BLOBS[index], edits))


# --------------------------------------------------------------------------- one rule at a time


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize(
    ("name", "index"),
    [(n, 0) for n in FLOAT_ARRAYS] + [("robot_pose", 5), ("object_cov", 53), ("weights", 1)],
)
def test_estimate_non_finite_number_is_invalid(name: str, index: int, value: float) -> None:
    WIRE.assert_rejected(
        WIRE.poke((*LOCAL, name), index, value), InvalidValue, f"beliefs.local.{name}"
    )


def test_estimate_negative_weight_is_invalid() -> None:
    WIRE.assert_rejected(
        _array((*LOCAL, "weights"), [1.5, -0.5]), InvalidValue, "beliefs.local.weights"
    )


@pytest.mark.parametrize("weights", [[0.5, 0.5 - 2e-6], [0.5, 0.5 + 2e-6], [0.0, 0.0], [2.0, 0.0]])
def test_estimate_weights_not_summing_to_one_are_invalid(weights: list[float]) -> None:
    WIRE.assert_rejected(
        _array((*LOCAL, "weights"), weights), InvalidValue, "beliefs.local.weights"
    )


@pytest.mark.parametrize("weights", [[0.5, 0.5 - 5e-7], [0.5, 0.5 + 5e-7], [1.0, -0.0]])
def test_estimate_weights_within_tolerance_are_accepted(weights: list[float]) -> None:
    got = decode_estimate(_array((*LOCAL, "weights"), weights))
    assert got.beliefs["local"].weights.tobytes() == np.array(weights).tobytes()


def _class_poked(index: int, value: int) -> bytes:
    """The reference document (version 3) with class ``index`` of ``local`` set to ``value``."""
    path = (*LOCAL, "classes")
    blob = get_at(REF_DOC, path)
    return WIRE.with_(path, blob[:index] + bytes([value]) + blob[index + 1 :])


def _int64_classes(doc: dict[str, Any], version: int) -> dict[str, Any]:
    """``doc`` (version 3) as a document of ``version`` 1 or 2: classes as int64."""
    old = copy.deepcopy(doc)
    old["v"] = version
    for snap in old["beliefs"].values():
        snap["classes"] = np.frombuffer(snap["classes"], "<u1").astype("<i8").tobytes()
    return old


@pytest.mark.parametrize("value", [64, 200, 255])
def test_estimate_class_out_of_range_is_invalid(value: int) -> None:
    WIRE.assert_rejected(_class_poked(4, value), InvalidValue, "beliefs.local.classes")


@pytest.mark.parametrize("value", [-1, 64, 2**62, -(2**63)])
def test_estimate_int64_class_out_of_range_is_invalid(value: int) -> None:
    """Versions 1 and 2 carry classes as int64: negative and huge ones are refused too."""
    path = (*LOCAL, "classes")
    for version in (1, 2):
        doc = _int64_classes(REF_DOC, version)
        blob = get_at(doc, path)
        doc["beliefs"]["local"]["classes"] = blob[:32] + struct.pack("<q", value) + blob[40:]
        WIRE.assert_rejected(pack(doc), InvalidValue, "beliefs.local.classes")


def test_estimate_int64_classes_of_versions_1_and_2_still_decode() -> None:
    """An estimate of an agent before version 3 (classes as int64) decodes to the same beliefs,
    and its classes must have 8 bytes each there (one each in version 3)."""
    for version in (1, 2):
        doc = _int64_classes(REF_DOC, version)
        assert_same_estimate(decode_estimate(pack(doc)), REF)
        as_bytes = copy.deepcopy(doc)
        as_bytes["beliefs"]["local"]["classes"] = REF_DOC["beliefs"]["local"]["classes"]
        WIRE.assert_rejected(pack(as_bytes), MalformedMessage, "beliefs.local.classes")
    doc = copy.deepcopy(REF_DOC)
    doc["beliefs"]["local"]["classes"] = _int64_classes(REF_DOC, 2)["beliefs"]["local"]["classes"]
    WIRE.assert_rejected(pack(doc), MalformedMessage, "beliefs.local.classes")


def test_estimate_classes_over_255_travel_as_int64() -> None:
    """A model with more than 256 classes: its estimates keep int64 classes (version 1 or 2)."""
    lim = EstimateLimits(num_classes=1000)
    snap = dataclasses.replace(
        REF.beliefs["local"], classes=np.array([[0, 999, 2], [256, 1, 0]], dtype=np.int64)
    )
    msg = EstimateMessage("r1", 3, {"local": snap, "distributed": REF.beliefs["distributed"]})
    blob = encode_estimate(msg, lim)
    doc = msgpack.unpackb(blob)
    assert doc["v"] == 1 and len(doc["beliefs"]["local"]["classes"]) == 8 * 2 * 3
    assert_same_estimate(decode_estimate(blob, lim), msg)


def test_estimate_class_limit_follows_num_classes() -> None:
    blob = _class_poked(4, 2)
    WIRE.assert_rejected(blob, InvalidValue, "beliefs.local.classes", EstimateLimits(num_classes=2))
    assert decode_estimate(blob, EstimateLimits(num_classes=3)).beliefs["local"].classes[1, 1] == 2


@pytest.mark.parametrize("name", ["robot_cov", "object_cov"])
@pytest.mark.parametrize("relative", [1e-6, 1e-3, 1.0])
def test_estimate_asymmetric_covariance_is_invalid(name: str, relative: float) -> None:
    cov = np.tile(np.diag([4.0, 4.0, 1.0]), (2 if name == "robot_cov" else 6, 1, 1))
    cov[-1, 0, 2] += relative * 4.0
    blob = _array((*LOCAL, name), cov)
    WIRE.assert_rejected(blob, InvalidValue, f"beliefs.local.{name}")


def test_estimate_covariance_symmetric_within_tolerance_is_accepted() -> None:
    cov = np.tile(np.diag([4.0, 4.0, 1.0]), (2, 1, 1))
    cov[1, 0, 1] = 1e-9
    blob = _array((*LOCAL, "robot_cov"), cov)
    assert decode_estimate(blob).beliefs["local"].robot_cov[1, 0, 1] == 1e-9
    with pytest.raises(InvalidValue):
        decode_estimate(blob, EstimateLimits(symmetry_tol=1e-12))


@pytest.mark.parametrize("name", ARRAYS)
@pytest.mark.parametrize("change", [-8, 8, -1, 1, None])
def test_estimate_wrong_array_length_is_malformed(name: str, change: int | None) -> None:
    """``change`` bytes added or cut; None empties the blob. The weights fix H, so changing them
    by a whole float64 makes the next array the wrong length."""
    path = (*LOCAL, name)
    blob = get_at(REF_DOC, path)
    new = b"" if change is None else blob[:change] if change < 0 else blob + bytes(change)
    field = f"beliefs.local.{name}"
    if name == "weights" and change in (8, -8):
        field = "beliefs.local.classes"
    error = InvalidValue if name == "weights" and change is None else MalformedMessage
    WIRE.assert_rejected(WIRE.with_(path, new), error, field)


def test_estimate_object_count_disagreeing_with_arrays_is_malformed() -> None:
    objects = get_at(REF_DOC, (*LOCAL, "objects"))
    WIRE.assert_rejected(
        WIRE.with_((*LOCAL, "objects"), objects[:-1]), MalformedMessage, "beliefs.local.classes"
    )


def test_estimate_duplicate_object_ids_are_invalid() -> None:
    WIRE.assert_rejected(
        WIRE.with_((*LOCAL, "objects"), [5, 6, 5]), InvalidValue, "beliefs.local.objects"
    )


@pytest.mark.parametrize(
    ("path", "value"),
    [
        (("k",), -1),
        (("k",), 2**63),
        ((*LOCAL, "objects", 1), -1),
        ((*LOCAL, "objects", 1), 2**32),
        (("counters", "invalid"), -1),
        (("counters", "invalid"), 2**63),
    ],
)
def test_estimate_integer_out_of_range_is_invalid(path: Path, value: int) -> None:
    WIRE.assert_rejected(WIRE.with_(path, value), InvalidValue, field_name(path))


@pytest.mark.parametrize("robot", ["", "x" * 33, "r 1", "r/1", "rö", "r1\n"])
def test_estimate_invalid_robot_id_is_invalid(robot: str) -> None:
    WIRE.assert_rejected(WIRE.with_(("robot",), robot), InvalidValue, "robot")


@pytest.mark.parametrize("name", ["", "Local", "local1", "a-b", "x" * 33, "lócal"])
def test_estimate_invalid_belief_name_is_invalid(name: str) -> None:
    doc = copy.deepcopy(REF_DOC)
    doc["beliefs"][name] = doc["beliefs"].pop("local")
    WIRE.assert_rejected(pack(doc), InvalidValue, "beliefs")


@pytest.mark.parametrize("name", ["", "Invalid", "x" * 49, "a b"])
def test_estimate_invalid_counter_name_is_invalid(name: str) -> None:
    WIRE.assert_rejected(WIRE.with_(("counters", name), 1), InvalidValue, "counters")


def test_estimate_without_beliefs_is_invalid() -> None:
    WIRE.assert_rejected(WIRE.with_(("beliefs",), {}), InvalidValue, "beliefs")


def test_estimate_too_many_beliefs_or_counters_exceed_limits() -> None:
    local = REF_DOC["beliefs"]["local"]
    beliefs = {"b" + "_" * i: local for i in range(9)}
    WIRE.assert_rejected(WIRE.with_(("beliefs",), beliefs), LimitExceeded, "beliefs")
    counters = {"c" + "_" * i: i for i in range(MAX_COUNTERS + 1)}
    WIRE.assert_rejected(WIRE.with_(("counters",), counters), LimitExceeded, "counters")
    assert (
        len(decode_estimate(WIRE.with_(("beliefs",), dict(list(beliefs.items())[:8]))).beliefs) == 8
    )


WRONG_TYPES = [
    (("robot",), 5),
    (("robot",), b"r2"),
    (("k",), 12.0),
    (("k",), True),
    (("k",), "12"),
    (("beliefs",), []),
    (("beliefs",), None),
    (LOCAL, []),
    (LOCAL, b""),
    ((*LOCAL, "objects"), b"\x01\x02\x03"),
    ((*LOCAL, "objects"), None),
    ((*LOCAL, "objects", 0), 1.0),
    ((*LOCAL, "objects", 0), "1"),
    ((*LOCAL, "objects", 0), True),
    *(((*LOCAL, name), value) for name in ARRAYS for value in (None, [0.0, 1.0], "ab")),
    (("counters",), []),
    (("counters",), None),
    (("counters", "invalid"), 0.0),
    (("counters", "invalid"), False),
    (("counters", "invalid"), "0"),
]


@pytest.mark.parametrize(
    ("path", "value"), [pytest.param(p, v, id=f"{field_name(p)}={v!r}") for p, v in WRONG_TYPES]
)
def test_estimate_wrong_type_is_malformed(path: Path, value: Any) -> None:
    WIRE.assert_rejected(WIRE.with_(path, value), MalformedMessage, field_name(path))


def test_estimate_non_string_names_are_malformed() -> None:
    doc = copy.deepcopy(REF_DOC)
    doc["beliefs"][b"local"] = doc["beliefs"].pop("local")
    WIRE.assert_rejected(pack(doc), MalformedMessage, "beliefs")
    WIRE.assert_rejected(WIRE.with_(("counters",), {b"invalid": 1}), MalformedMessage, "counters")


@pytest.mark.parametrize("version", [0, 4, -1, "1", None, 1.0, True])
def test_estimate_unknown_version_is_unsupported(version: Any) -> None:
    WIRE.assert_rejected(WIRE.with_(("v",), version), UnsupportedVersion, "v")


def _shared(rng: np.random.Generator, h: int, n: int) -> BeliefSnapshot:
    """A snapshot whose hypotheses differ only in weights and classes (one continuous belief)."""
    one = make_snapshot(rng, 1, n)
    many = make_snapshot(rng, h, n)
    tile = {name: np.repeat(getattr(one, name), h, axis=0) for name in SHAREABLE}
    return dataclasses.replace(many, **tile)


SHAREABLE = ("robot_pose", "robot_cov", "object_pose", "object_cov")


@pytest.mark.parametrize("seed", range(4))
def test_estimate_poses_every_hypothesis_shares_travel_once(seed: int) -> None:
    """The pose arrays of hypotheses that share one continuous belief are sent once (wire
    versions 2 and 3) and come back bit for bit, H times; a belief with one differing entry, or
    one hypothesis, sends each hypothesis' own."""
    rng = np.random.default_rng(seed)
    h, n = 6, 4
    snap = _shared(rng, h, n)
    blob = encode_estimate(EstimateMessage("r1", 3, {"distributed": snap}))
    doc = msgpack.unpackb(blob)
    assert doc["v"] == 3
    sent = doc["beliefs"]["distributed"]
    assert [len(sent[a]) for a in SHAREABLE] == [24, 72, 24 * n, 72 * n]
    assert len(sent["classes"]) == h * n and len(sent["weights"]) == 8 * h
    got = decode_estimate(blob).beliefs["distributed"]
    assert_same_snapshot(got, snap)
    # one entry of one hypothesis differs: that array goes whole, the others still once
    cov = snap.object_cov.copy()
    cov[h - 1, n - 1, 2, 2] = np.nextafter(cov[h - 1, n - 1, 2, 2], np.inf)
    apart = dataclasses.replace(snap, object_cov=cov)
    blob = encode_estimate(EstimateMessage("r1", 3, {"distributed": apart}))
    sent = msgpack.unpackb(blob)["beliefs"]["distributed"]
    assert (len(sent["object_cov"]), len(sent["object_pose"])) == (72 * h * n, 24 * n)
    assert_same_snapshot(decode_estimate(blob).beliefs["distributed"], apart)
    # −0.0 where the others hold 0.0 compares equal, but is not the same bits: sent whole
    pose = np.array(snap.object_pose)
    pose[:, 0, 0] = 0.0
    pose[h - 1, 0, 0] = -0.0
    signed = dataclasses.replace(snap, object_pose=pose)
    blob = encode_estimate(EstimateMessage("r1", 3, {"distributed": signed}))
    assert len(msgpack.unpackb(blob)["beliefs"]["distributed"]["object_pose"]) == 24 * h * n
    assert_same_snapshot(decode_estimate(blob).beliefs["distributed"], signed)
    # a read-only view of one hypothesis for all (what a belief's snapshot gives): sent once
    view = dataclasses.replace(
        snap, object_cov=np.broadcast_to(snap.object_cov[:1], snap.object_cov.shape)
    )
    blob = encode_estimate(EstimateMessage("r1", 3, {"distributed": view}))
    assert len(msgpack.unpackb(blob)["beliefs"]["distributed"]["object_cov"]) == 72 * n
    single = make_snapshot(rng, 1, n)
    blob = encode_estimate(EstimateMessage("r1", 3, {"local": single}))
    assert len(msgpack.unpackb(blob)["beliefs"]["local"]["object_cov"]) == 72 * n


def test_estimate_arrays_sent_once_are_refused_where_they_may_not_be() -> None:
    """Version 1 has no shared arrays; in versions 2 and 3 only the four pose arrays may be
    shared, and a length that is neither H hypotheses' nor one's is refused, naming the field."""
    rng = np.random.default_rng(9)
    snap = _shared(rng, 5, 3)
    doc = msgpack.unpackb(encode_estimate(EstimateMessage("r1", 3, {"local": snap})))
    assert doc["v"] == 3
    assert_same_estimate(decode_estimate(pack(_int64_classes(doc, 2))), decode_estimate(pack(doc)))
    old = _int64_classes(doc, 1)
    WIRE.assert_rejected(pack(old), MalformedMessage, "beliefs.local.robot_pose")
    for name, size in (("classes", 3), ("object_pose", 24 * 2)):  # (weights fix H)
        bad = copy.deepcopy(doc)
        bad["beliefs"]["local"][name] = bytes(size)
        WIRE.assert_rejected(pack(bad), MalformedMessage, f"beliefs.local.{name}")


@pytest.mark.parametrize(
    ("name", "index", "value", "why"),
    [
        ("object_cov", 5, math.nan, "non-finite"),
        ("object_pose", 2, math.inf, "non-finite"),
        ("robot_cov", 1, None, "not symmetric"),  # (0, 1) but not (1, 0)
        ("object_cov", 9 + 1, None, "not symmetric"),  # the second object's (0, 1)
    ],
)
def test_estimate_array_sent_once_obeys_the_value_rules(
    name: str, index: int, value: float | None, why: str
) -> None:
    """A pose array sent once for every hypothesis is checked once (not H times: 5 ms of a
    300-hypothesis estimate of 60 objects) but checked: a bad value in it is refused, named."""
    rng = np.random.default_rng(3)
    doc = msgpack.unpackb(encode_estimate(EstimateMessage("r1", 3, {"local": _shared(rng, 6, 4)})))
    raw = bytearray(doc["beliefs"]["local"][name])
    assert len(raw) < 6 * 8 * 9 * 4  # sent once
    if value is None:  # the largest |entry| with the sign opposite to (1, 0)'s: asymmetric
        matrix = np.frombuffer(bytes(raw), dtype="<f8")[index - 1 : index + 8]
        below = float(matrix[3])
        value = -math.copysign(float(np.abs(matrix).max()) or 1.0, below or -1.0)
    raw[8 * index : 8 * index + 8] = struct.pack("<d", value)
    doc["beliefs"]["local"][name] = bytes(raw)
    with pytest.raises(InvalidValue, match=why) as info:
        decode_estimate(pack(doc))
    assert info.value.field == f"beliefs.local.{name}"


@pytest.mark.parametrize("kind", ["stack", "frame", "Estimate", "", None, b"estimate"])
def test_estimate_unknown_message_type_is_unsupported(kind: Any) -> None:
    WIRE.assert_rejected(WIRE.with_(("type",), kind), UnsupportedVersion, "type")


@pytest.mark.parametrize(
    ("path", "field"),
    [((k,), "message") for k in REF_DOC]
    + [((*LOCAL, k), "beliefs.local") for k in get_at(REF_DOC, LOCAL)],
)
def test_estimate_missing_key_is_malformed(path: Path, field: str) -> None:
    WIRE.assert_rejected(WIRE.without(path), MalformedMessage, field)


@pytest.mark.parametrize("key", ["x", "V", "weight", ""])
@pytest.mark.parametrize(("path", "field"), [((), "message"), (LOCAL, "beliefs.local")])
def test_estimate_extra_key_is_malformed(path: Path, field: str, key: str) -> None:
    WIRE.assert_rejected(WIRE.with_((*path, key), 0), MalformedMessage, field)


@pytest.mark.parametrize(
    ("limits", "field"),
    [
        (EstimateLimits(max_hypotheses=2), "beliefs.distributed.weights"),
        (EstimateLimits(max_objects=3), "beliefs.distributed.objects"),
        (EstimateLimits(max_message_bytes=len(REF_BLOB) - 1), "message"),
    ],
)
def test_estimate_over_limits_is_rejected(limits: EstimateLimits, field: str) -> None:
    WIRE.assert_rejected(REF_BLOB, LimitExceeded, field, limits)
    with pytest.raises(LocalProtocolError) as caught:
        encode_estimate(REF, limits)
    assert caught.value.field == field


def test_estimate_exactly_at_limits_is_accepted() -> None:
    lim = EstimateLimits(
        num_classes=3, max_hypotheses=3, max_objects=4, max_message_bytes=len(REF_BLOB)
    )
    assert_same_estimate(decode_estimate(REF_BLOB, lim), REF)
    assert encode_estimate(REF, lim) == REF_BLOB


def test_estimate_default_limits_hold_a_large_belief() -> None:
    snap = make_snapshot(np.random.default_rng(7), h=200, n=60)
    msg = EstimateMessage("r1", 1, {"local": snap})
    assert_same_estimate(decode_estimate(encode_estimate(msg)), msg)


# --------------------------------------------------------------------------- structured fuzz

# Class indices at and past their edges, poked like the float64s (8 bytes: 8 one-byte classes of
# version 3, or one int64 class of versions 1 and 2).
EDGE_CLASSES = st.sampled_from(
    [struct.pack("<q", v) for v in (-1, 0, 2, 64, 2**63 - 1, -(2**63))]
    + [bytes([v] * 8) for v in (0, 1, 2, 63, 64, 255)]
)
MUTATOR = fuzz.Mutator(
    known_keys=(
        *("v", "type", "robot", "k", "beliefs", "counters", "local", "objects", *ARRAYS),
        *("num_classes", "class_probs", "fused", "r1"),
    ),
    strings=("estimate", "r1", "local", ""),
    edge_ints=(-1, 0, 1, 63, 64, 2**32 - 1, 2**32, 2**63 - 1, 2**63),
    numbers=fuzz.FLOAT64S | EDGE_CLASSES,
)


@settings(FUZZ, max_examples=1000)
@given(
    index=st.integers(0, len(BASE_DOCS) - 1),
    edits=st.integers(1, 3),
    limits=st.sampled_from([None, None, EstimateLimits(num_classes=2, max_hypotheses=2)]),
    data=st.data(),
)
def test_estimate_mutated_documents_raise_only_remote_errors(
    index: int, edits: int, limits: EstimateLimits | None, data: st.DataObject
) -> None:
    WIRE.decode_or_reject(pack(MUTATOR.mutated(BASE_DOCS[index], edits, data)), limits)


# --------------------------------------------------------------------------- encode


def _message(**changes: Any) -> EstimateMessage:
    """REF with fields changed, wrong types allowed."""
    return dataclasses.replace(REF, **changes)


def _with_local(**changes: Any) -> EstimateMessage:
    local = dataclasses.replace(REF.beliefs["local"], **changes)
    return dataclasses.replace(REF, beliefs={**REF.beliefs, "local": local})


def _poked(name: str, value: Any) -> np.ndarray:
    out = getattr(REF.beliefs["local"], name).copy()
    out.flat[-1] = value
    return out


L0 = REF.beliefs["local"]
ASYMMETRIC = L0.robot_cov.copy()
ASYMMETRIC[0, 0, 1] += 1e-3 * np.abs(ASYMMETRIC[0]).max()
ENCODE_REJECTS = [
    ("robot", _message(robot="r 2"), "robot"),
    ("robot-int", _message(robot=2), "robot"),
    ("k-negative", _message(k=-1), "k"),
    ("k-float", _message(k=1.0), "k"),
    ("no-beliefs", _message(beliefs={}), "beliefs"),
    ("belief-name", _message(beliefs={"Local": L0}), "beliefs"),
    (
        "beliefs-9",
        _message(beliefs={"b" + "_" * i: L0 for i in range(9)}),
        "beliefs",
    ),
    ("beliefs-list", _message(beliefs=[L0]), "beliefs"),
    ("counter-name", _message(counters={"Sent": 1}), "counters"),
    (
        "counters-129",
        _message(counters={"c" + "_" * i: 1 for i in range(MAX_COUNTERS + 1)}),
        "counters",
    ),
    ("counter-negative", _message(counters={"sent": -1}), "counters.sent"),
    ("counter-float", _message(counters={"sent": 1.0}), "counters.sent"),
    ("counter-bool", _message(counters={"sent": True}), "counters.sent"),
    ("counter-2**63", _message(counters={"sent": 2**63}), "counters.sent"),
    ("ids-duplicate", _with_local(object_ids=(1, 2, 1)), "beliefs.local.objects"),
    ("ids-negative", _with_local(object_ids=(1, 2, -1)), "beliefs.local.objects"),
    ("ids-float", _with_local(object_ids=(1, 2, 3.0)), "beliefs.local.objects"),
    ("ids-fewer", _with_local(object_ids=(1, 2)), "beliefs.local.classes"),
    ("weights-empty", _with_local(weights=np.zeros(0)), "beliefs.local.weights"),
    ("weights-2d", _with_local(weights=L0.weights[:, None]), "beliefs.local.weights"),
    ("weights-nan", _with_local(weights=_poked("weights", math.nan)), "beliefs.local.weights"),
    ("weights-sum", _with_local(weights=np.array([0.5, 0.4])), "beliefs.local.weights"),
    ("weights-negative", _with_local(weights=np.array([1.5, -0.5])), "beliefs.local.weights"),
    ("classes-float", _with_local(classes=L0.classes.astype(float)), "beliefs.local.classes"),
    ("classes-64", _with_local(classes=_poked("classes", 64)), "beliefs.local.classes"),
    ("classes-negative", _with_local(classes=_poked("classes", -1)), "beliefs.local.classes"),
    (
        "classes-uint64-huge",
        _with_local(classes=np.full((2, 3), 2**64 - 1, np.uint64)),
        "beliefs.local.classes",
    ),
    ("classes-shape", _with_local(classes=L0.classes[:1]), "beliefs.local.classes"),
    (
        "robot-pose-inf",
        _with_local(robot_pose=_poked("robot_pose", math.inf)),
        "beliefs.local.robot_pose",
    ),
    ("robot-pose-shape", _with_local(robot_pose=L0.robot_pose[:, :2]), "beliefs.local.robot_pose"),
    ("robot-cov-asymmetric", _with_local(robot_cov=ASYMMETRIC), "beliefs.local.robot_cov"),
    (
        "object-pose-nan",
        _with_local(object_pose=_poked("object_pose", math.nan)),
        "beliefs.local.object_pose",
    ),
    (
        "object-cov-nan",
        _with_local(object_cov=_poked("object_cov", math.nan)),
        "beliefs.local.object_cov",
    ),
    (
        "object-cov-shape",
        _with_local(object_cov=L0.object_cov[:, :, :2]),
        "beliefs.local.object_cov",
    ),
    ("object-cov-complex", _with_local(object_cov=L0.object_cov + 0j), "beliefs.local.object_cov"),
]


@pytest.mark.parametrize(
    ("msg", "field"), [pytest.param(m, f, id=name) for name, m, f in ENCODE_REJECTS]
)
def test_estimate_encode_rejects_what_decode_would_reject(msg: EstimateMessage, field: str) -> None:
    with pytest.raises(LocalProtocolError) as caught:
        encode_estimate(msg)
    assert caught.value.field == field


BAD_FLOATS = (math.nan, math.inf, -math.inf, -1.0, 2.0, 1e300)


@settings(FUZZ, max_examples=1000)
@given(
    seed=st.integers(0, 2**32 - 1),
    name=st.sampled_from(ARRAYS),
    index=st.integers(0, 2**20),
    value=st.sampled_from(BAD_FLOATS) | st.integers(-2, 70) | st.floats(),
    transpose=st.booleans(),
)
def test_estimate_encode_emits_only_what_decode_accepts(
    seed: int, name: str, index: int, value: float, transpose: bool
) -> None:
    """Snapshots with one entry replaced by a doubtful value (or a covariance transposed, which is
    harmless, after the entry changed): ``encode_estimate`` refuses them with a
    LocalProtocolError, or emits bytes that decode back to the same estimate."""
    snap = make_snapshot(np.random.default_rng(seed), n=int(seed % 3) + 1)
    array = getattr(snap, name).copy()
    if name == "classes":
        array.flat[index % array.size] = int(np.clip(value, -2, 70)) if math.isfinite(value) else 0
    else:
        array.flat[index % array.size] = value
        if transpose and name.endswith("cov"):
            array = np.swapaxes(array, -1, -2).copy()
    msg = EstimateMessage("r1", 1, {"local": dataclasses.replace(snap, **{name: array})})
    try:
        blob = encode_estimate(msg)
    except LocalProtocolError as exc:
        assert exc.field
        return
    assert_same_estimate(decode_estimate(blob), msg)


# --------------------------------------------------------------------------- the head alone


def _head_agrees(blob: bytes) -> None:
    """``decode_estimate_head`` refuses what ``decode_estimate`` refuses for any field but the
    beliefs' contents (same error, same field), and reads the same robot, step and counters."""
    try:
        full = decode_estimate(blob)
    except RemoteProtocolError as exc:
        full = exc
    try:
        head = decode_estimate_head(blob)
    except RemoteProtocolError as exc:
        assert isinstance(full, RemoteProtocolError)
        assert (type(exc), exc.field) == (type(full), full.field)
        return
    assert head.beliefs == {}
    if isinstance(full, RemoteProtocolError):
        assert full.field.startswith("beliefs."), full  # refused for a belief's contents alone
    else:
        assert (head.robot, head.k, head.counters) == (full.robot, full.k, full.counters)
        assert head.fused == full.fused


@pytest.mark.parametrize("index", range(len(BASE_BLOBS)))
def test_the_head_of_an_estimate_reads_what_the_whole_reads(index: int) -> None:
    _head_agrees(BASE_BLOBS[index])
    assert decode_estimate_head(BASE_BLOBS[index]).counters == BASE_MESSAGES[index].counters


def test_the_head_of_an_estimate_leaves_the_arrays_to_the_whole() -> None:
    blob = WIRE.poke((*LOCAL, "weights"), 1, math.nan)
    assert decode_estimate_head(blob).robot == REF.robot
    with pytest.raises(InvalidValue):
        decode_estimate(blob)
    for field, value in (("k", -1), ("robot", "no such id!"), ("counters", {"x": -1})):
        doc = copy.deepcopy(REF_DOC)
        doc[field] = value
        with pytest.raises(RemoteProtocolError) as err:
            decode_estimate_head(pack(doc))
        assert err.value.field.split(".")[0] == field


@settings(FUZZ, max_examples=500)
@given(index=st.integers(0, len(BASE_BLOBS) - 1), edits=fuzz.BYTE_EDITS)
def test_the_head_of_a_corrupted_estimate_agrees_with_the_whole(
    index: int, edits: list[tuple[int, int]]
) -> None:
    _head_agrees(fuzz.corrupt(BASE_BLOBS[index], edits))


# --------------------------------------------------------------------------- per-object classes

# Robot r4's ``local`` belief keeps per-object class marginals: 3 objects, M = 3.
PROBS_REF = EstimateMessage(
    "r4",
    5,
    {
        "local": make_per_object_snapshot(np.random.default_rng(21), n=3, num_classes=3),
        "distributed": REF.beliefs["distributed"],
    },
)
PROBS_BLOB = encode_estimate(PROBS_REF)
PROBS_DOC: dict[str, Any] = msgpack.unpackb(PROBS_BLOB, raw=False)
PROBS_WIRE = fuzz.Wire(decode_estimate, PROBS_DOC, EstimateLimits(), _check_valid)
PROBS_FIELD = "beliefs.local.class_probs"
M_FIELD = "beliefs.local.num_classes"


def test_estimate_class_probs_round_trip_bit_exact_with_their_m() -> None:
    """A belief's per-object class marginals travel as ``num_classes`` and ``class_probs``
    (float64, C order) after its arrays, and only for that belief; the version is unchanged."""
    local = PROBS_REF.beliefs["local"]
    assert local.class_probs is not None
    assert PROBS_DOC["v"] == 3
    raw = PROBS_DOC["beliefs"]["local"]
    assert list(raw) == ["objects", *ARRAYS, "num_classes", "class_probs"]
    assert raw["num_classes"] == 3
    assert raw["class_probs"] == local.class_probs.astype("<f8").tobytes()
    assert list(PROBS_DOC["beliefs"]["distributed"]) == ["objects", *ARRAYS]  # None: no keys
    got = decode_estimate(PROBS_BLOB)
    assert_same_estimate(got, PROBS_REF)
    assert got.beliefs["distributed"].class_probs is None
    assert encode_estimate(got) == PROBS_BLOB
    assert got.beliefs["local"].marginals(3).tobytes() == local.class_probs.tobytes()


def test_estimate_without_class_probs_is_byte_for_byte_as_before() -> None:
    """A snapshot whose ``class_probs`` is None writes neither key: the same bytes as the
    snapshot built without the field."""
    old = REF.beliefs["local"]
    rebuilt = BeliefSnapshot(
        old.object_ids,
        old.weights,
        old.classes,
        old.robot_pose,
        old.robot_cov,
        old.object_pose,
        old.object_cov,
    )
    assert rebuilt.class_probs is None
    msg = dataclasses.replace(REF, beliefs={**REF.beliefs, "local": rebuilt})
    assert encode_estimate(msg) == REF_BLOB
    assert "class_probs" not in REF_DOC["beliefs"]["local"]


@pytest.mark.parametrize("m", [1, 2, 64])
def test_estimate_class_probs_of_no_object_keep_their_m(m: int) -> None:
    snap = make_per_object_snapshot(np.random.default_rng(m), n=0, num_classes=m)
    msg = EstimateMessage("r1", 1, {"local": snap})
    blob = encode_estimate(msg)
    raw = msgpack.unpackb(blob)["beliefs"]["local"]
    assert (raw["num_classes"], raw["class_probs"]) == (m, b"")
    got = decode_estimate(blob).beliefs["local"]
    assert got.class_probs is not None and got.class_probs.shape == (0, m)
    assert_same_snapshot(got, snap)


def test_estimate_class_probs_one_integer_snapshot_decodes_as_float64() -> None:
    snap = make_per_object_snapshot(np.random.default_rng(2), n=2, num_classes=2)
    onehot = dataclasses.replace(snap, class_probs=np.array([[0, 1], [1, 0]], dtype=np.int64))
    got = decode_estimate(encode_estimate(EstimateMessage("r1", 1, {"local": onehot})))
    assert_same_snapshot(got.beliefs["local"], onehot)


@pytest.mark.parametrize("missing", ["num_classes", "class_probs"])
def test_estimate_class_probs_need_both_keys(missing: str) -> None:
    PROBS_WIRE.assert_rejected(
        PROBS_WIRE.without((*LOCAL, missing)), MalformedMessage, "beliefs.local"
    )
    doc = copy.deepcopy(REF_DOC)  # one key alone on a snapshot without them: as unknown
    doc["beliefs"]["local"][missing] = PROBS_DOC["beliefs"]["local"][missing]
    WIRE.assert_rejected(pack(doc), MalformedMessage, "beliefs.local")


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
@pytest.mark.parametrize("index", [0, 4, 8])
def test_estimate_non_finite_class_probability_is_invalid(value: float, index: int) -> None:
    PROBS_WIRE.assert_rejected(
        PROBS_WIRE.poke((*LOCAL, "class_probs"), index, value), InvalidValue, PROBS_FIELD
    )


@pytest.mark.parametrize(
    "row",
    [
        [1.5, -0.5, 0.0],  # negative
        [-1e-300, 1.0, 0.0],
        [1.0 + 2e-7, 0.0, 0.0],  # over 1, although within the sum's tolerance
        [0.5, 0.5 - 2e-6, 0.0],  # rows must sum to 1
        [0.5, 0.5 + 2e-6, 0.0],
        [0.0, 0.0, 0.0],
        [0.3, 0.3, 0.3],
    ],
)
def test_estimate_class_probs_off_the_simplex_are_invalid(row: list[float]) -> None:
    probs = np.array([[0.2, 0.3, 0.5], row, [1.0, 0.0, 0.0]])
    path = (*LOCAL, "class_probs")
    blob = PROBS_WIRE.with_(path, probs.astype("<f8").tobytes())
    PROBS_WIRE.assert_rejected(blob, InvalidValue, PROBS_FIELD)


@pytest.mark.parametrize("row", [[0.5, 0.5 - 5e-7, 0.0], [0.5, 0.5 + 5e-7, 0.0], [-0.0, 1.0, 0]])
def test_estimate_class_probs_within_tolerance_are_accepted(row: list[float]) -> None:
    probs = np.array([[0.2, 0.3, 0.5], row, [1.0, 0.0, 0.0]])
    blob = PROBS_WIRE.with_((*LOCAL, "class_probs"), probs.astype("<f8").tobytes())
    got = decode_estimate(blob).beliefs["local"].class_probs
    assert got is not None and got.tobytes() == probs.tobytes()


@pytest.mark.parametrize("change", [-8, 8, -1, 1, None])
def test_estimate_class_probs_of_the_wrong_length_are_malformed(change: int | None) -> None:
    path = (*LOCAL, "class_probs")
    blob = get_at(PROBS_DOC, path)
    new = b"" if change is None else blob[:change] if change < 0 else blob + bytes(change)
    PROBS_WIRE.assert_rejected(PROBS_WIRE.with_(path, new), MalformedMessage, PROBS_FIELD)


def test_estimate_num_classes_disagreeing_with_class_probs_is_malformed() -> None:
    for m in (2, 4):  # 3 × 3 float64 sent: 3 × 2 or 3 × 4 expected
        blob = PROBS_WIRE.with_((*LOCAL, "num_classes"), m)
        PROBS_WIRE.assert_rejected(blob, MalformedMessage, PROBS_FIELD)


@pytest.mark.parametrize("m", [0, -1, 65, 2**63])
def test_estimate_num_classes_out_of_range_is_invalid(m: int) -> None:
    PROBS_WIRE.assert_rejected(PROBS_WIRE.with_((*LOCAL, "num_classes"), m), InvalidValue, M_FIELD)


def test_estimate_num_classes_limit_follows_the_limits() -> None:
    PROBS_WIRE.assert_rejected(PROBS_BLOB, InvalidValue, M_FIELD, EstimateLimits(num_classes=2))
    assert_same_estimate(decode_estimate(PROBS_BLOB, EstimateLimits(num_classes=3)), PROBS_REF)
    with pytest.raises(LocalProtocolError) as caught:
        encode_estimate(PROBS_REF, EstimateLimits(num_classes=2))
    assert caught.value.field == M_FIELD


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("num_classes", 3.0),
        ("num_classes", True),
        ("num_classes", "3"),
        ("num_classes", None),
        ("class_probs", None),
        ("class_probs", [0.2, 0.3, 0.5]),
        ("class_probs", "ab"),
    ],
)
def test_estimate_class_probs_of_the_wrong_type_are_malformed(key: str, value: Any) -> None:
    PROBS_WIRE.assert_rejected(
        PROBS_WIRE.with_((*LOCAL, key), value), MalformedMessage, f"beliefs.local.{key}"
    )


P0 = PROBS_REF.beliefs["local"]
assert P0.class_probs is not None
P0_PROBS = P0.class_probs


def _with_probs(value: Any) -> EstimateMessage:
    local = dataclasses.replace(P0, class_probs=value)
    return dataclasses.replace(PROBS_REF, beliefs={**PROBS_REF.beliefs, "local": local})


def _probs_poked(row: int, values: list[float]) -> np.ndarray:
    out = P0_PROBS.copy()
    out[row] = values
    return out


ENCODE_PROBS_REJECTS = [
    ("1-d", _with_probs(P0_PROBS[0]), PROBS_FIELD),
    ("3-d", _with_probs(P0_PROBS[None]), PROBS_FIELD),
    ("rows-fewer", _with_probs(P0_PROBS[:2]), PROBS_FIELD),
    ("rows-more", _with_probs(np.vstack([P0_PROBS, P0_PROBS[:1]])), PROBS_FIELD),
    ("m-0", _with_probs(np.zeros((3, 0))), M_FIELD),
    ("m-65", _with_probs(np.full((3, 65), 1 / 65)), M_FIELD),
    ("nan", _with_probs(_probs_poked(1, [math.nan, 0.5, 0.5])), PROBS_FIELD),
    ("inf", _with_probs(_probs_poked(2, [math.inf, 0.0, 0.0])), PROBS_FIELD),
    ("negative", _with_probs(_probs_poked(0, [1.5, -0.5, 0.0])), PROBS_FIELD),
    ("over-1", _with_probs(_probs_poked(0, [1.0 + 2e-7, 0.0, 0.0])), PROBS_FIELD),
    ("row-sum", _with_probs(_probs_poked(2, [0.5, 0.5 - 2e-6, 0.0])), PROBS_FIELD),
    ("complex", _with_probs(P0_PROBS + 0j), PROBS_FIELD),
    ("strings", _with_probs(np.full((3, 3), "a")), PROBS_FIELD),
    ("bool", _with_probs(P0_PROBS > 0.5), PROBS_FIELD),
    ("ragged", _with_probs([[1.0], [0.5, 0.5], [1.0]]), PROBS_FIELD),
]


@pytest.mark.parametrize(
    ("msg", "field"), [pytest.param(m, f, id=name) for name, m, f in ENCODE_PROBS_REJECTS]
)
def test_estimate_encode_rejects_class_probs_decode_would_reject(
    msg: EstimateMessage, field: str
) -> None:
    with pytest.raises(LocalProtocolError) as caught:
        encode_estimate(msg)
    assert caught.value.field == field


@settings(FUZZ, max_examples=500)
@given(
    seed=st.integers(0, 2**32 - 1),
    m=st.integers(1, 66),
    index=st.integers(0, 2**20),
    value=st.sampled_from(BAD_FLOATS) | st.floats(),
    poke=st.booleans(),
)
def test_estimate_encode_class_probs_emits_only_what_decode_accepts(
    seed: int, m: int, index: int, value: float, poke: bool
) -> None:
    """Per-object marginals of any M, maybe with one entry replaced by a doubtful value:
    refused with a LocalProtocolError naming the field, or round-tripped bit for bit."""
    rng = np.random.default_rng(seed)
    snap = make_per_object_snapshot(rng, n=int(seed % 4), num_classes=m)
    probs = np.array(snap.class_probs)
    if poke and probs.size:
        probs.flat[index % probs.size] = value
    classes = np.minimum(snap.classes, 63)  # under the class limit: M and the values are tested
    msg = EstimateMessage(
        "r1", 1, {"local": dataclasses.replace(snap, classes=classes, class_probs=probs)}
    )
    try:
        blob = encode_estimate(msg)
    except LocalProtocolError as exc:
        assert exc.field in (PROBS_FIELD, M_FIELD), exc
        return
    assert m <= 64
    assert_same_estimate(decode_estimate(blob), msg)


@settings(FUZZ, max_examples=500)
@given(edits=fuzz.BYTE_EDITS)
def test_estimate_corrupted_class_probs_raise_only_remote_errors(
    edits: list[tuple[int, int]],
) -> None:
    PROBS_WIRE.decode_or_reject(fuzz.corrupt(PROBS_BLOB, edits))
    _head_agrees(fuzz.corrupt(PROBS_BLOB, edits))


def test_the_head_of_an_estimate_with_class_probs_reads_as_an_old_decoder_would() -> None:
    """``decode_estimate_head`` (what the conductor reads arriving estimates with) reads no
    snapshot key, so it reads an estimate with class marginals whatever it knows of them: this is
    why they came without a new version, which an older head decoder would refuse."""
    head = decode_estimate_head(PROBS_BLOB)
    assert (head.robot, head.k, head.beliefs) == ("r4", 5, {})


# --------------------------------------------------------------------------- fused versions

FUSED_REF = BASE_MESSAGES[4]
FUSED_BLOB = BASE_BLOBS[4]
FUSED_WIRE = fuzz.Wire(decode_estimate, BASE_DOCS[4], EstimateLimits(), _check_valid)


def test_estimate_fused_versions_travel_after_the_counters_sorted_by_owner() -> None:
    """``fused`` is written after ``counters``, owners sorted, the version unchanged; a message
    without it is byte for byte what it was (REF has none)."""
    doc = BASE_DOCS[4]
    assert list(doc) == ["v", "type", "robot", "k", "beliefs", "counters", "fused"]
    assert doc["v"] == 3
    assert list(doc["fused"].items()) == [("r1", 8), ("r2", 0), ("x" * 32, MAX_STEP)]
    assert "fused" not in REF_DOC and REF.fused is None
    got = decode_estimate(FUSED_BLOB)
    assert_same_estimate(got, FUSED_REF)
    assert encode_estimate(got) == FUSED_BLOB
    assert decode_estimate_head(FUSED_BLOB).fused == FUSED_REF.fused


def test_estimate_fused_may_be_empty() -> None:
    msg = dataclasses.replace(REF, fused={})
    got = decode_estimate(encode_estimate(msg))
    assert got.fused == {}
    assert decode_estimate(REF_BLOB).fused is None


@pytest.mark.parametrize(
    ("value", "error", "field"),
    [
        ([["r1", 1]], MalformedMessage, "fused"),
        ({"r 1": 1}, InvalidValue, "fused"),
        ({"": 1}, InvalidValue, "fused"),
        ({"r1": -1}, InvalidValue, "fused.r1"),
        ({"r1": MAX_STEP + 1}, InvalidValue, "fused.r1"),
        ({"r1": 1.0}, MalformedMessage, "fused.r1"),
        ({"r1": True}, MalformedMessage, "fused.r1"),
        ({"r1": None}, MalformedMessage, "fused.r1"),
        ({f"r{i}": 1 for i in range(1025)}, LimitExceeded, "fused"),
    ],
)
def test_estimate_malformed_fused_is_refused_naming_the_field(
    value: Any, error: type[RemoteProtocolError], field: str
) -> None:
    blob = FUSED_WIRE.with_(("fused",), value)
    FUSED_WIRE.assert_rejected(blob, error, field)
    with pytest.raises(error) as caught:
        decode_estimate_head(blob)
    assert caught.value.field == field


def test_estimate_fused_limit_follows_the_limits() -> None:
    lim = EstimateLimits(max_fused=3)
    assert decode_estimate(FUSED_BLOB, lim).fused == FUSED_REF.fused
    blob = FUSED_WIRE.with_(("fused",), {"a": 1, "b": 1, "c": 1, "d": 1})
    with pytest.raises(LimitExceeded) as caught:
        decode_estimate(blob, lim)
    assert caught.value.field == "fused"


@pytest.mark.parametrize(
    ("fused", "field"),
    [
        ([("r1", 1)], "fused"),
        ({"r 1": 1}, "fused"),
        ({1: 1}, "fused"),
        ({"r1": -1}, "fused.r1"),
        ({"r1": MAX_STEP + 1}, "fused.r1"),
        ({"r1": 1.0}, "fused.r1"),
        ({"r1": True}, "fused.r1"),
        ({f"r{i}": 1 for i in range(1025)}, "fused"),
    ],
)
def test_estimate_encode_rejects_the_fused_versions_decode_would(fused: Any, field: str) -> None:
    with pytest.raises(LocalProtocolError) as caught:
        encode_estimate(dataclasses.replace(REF, fused=fused))
    assert caught.value.field == field


@settings(FUZZ, max_examples=300)
@given(
    fused=st.dictionaries(
        st.from_regex(r"^[A-Za-z0-9_-]{1,32}$", fullmatch=True),
        st.integers(0, MAX_STEP),
        max_size=20,
    )
)
def test_estimate_fused_round_trips(fused: dict[str, int]) -> None:
    msg = dataclasses.replace(REF, fused=fused)
    assert_same_estimate(decode_estimate(encode_estimate(msg)), msg)


@settings(FUZZ, max_examples=300)
@given(edits=fuzz.BYTE_EDITS)
def test_estimate_corrupted_fused_raise_only_remote_errors(edits: list[tuple[int, int]]) -> None:
    FUSED_WIRE.decode_or_reject(fuzz.corrupt(FUSED_BLOB, edits))
    _head_agrees(fuzz.corrupt(FUSED_BLOB, edits))
