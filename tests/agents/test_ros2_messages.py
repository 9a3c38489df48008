"""CDR round trips through rosbags, byte for byte: the belief out (Odometry,
PoseWithCovarianceStamped, MarkerArray, Path, Detection3DArray, TFMessage) and a robot's
readings in (Odometry, Detection2DArray), per distro; malformed CDR is one Ros2MessageError,
never another exception."""

from __future__ import annotations

import contextlib
import math

import numpy as np
import pytest

from agents.ros2.messages import (
    DETECTIONS,
    MARKERS,
    ODOMETRY,
    POSE,
    UNUSED_VARIANCE,
    Ros2MessageError,
    class_marginals,
    covariance_6x6,
    markers_message,
    odometry_message,
    pose_message,
    types_for,
)
from agents.ros2.outputs import (
    OBJECTS,
    PATH,
    TF,
    objects_message,
    path_message,
    tf_message,
)
from agents.ros2.readings import (
    detections_message,
    odometry_reading_message,
    read_detections,
    read_odometry,
)
from estimator.models import Detection
from estimator.snapshot import BeliefSnapshot
from tests.tolerance import assert_angles_close, assert_close

DISTROS = ("humble", "jazzy")
CDR_LE = b"\x00\x01\x00\x00"  # the encapsulation header: CDR, little-endian


def _snapshot() -> BeliefSnapshot:
    """Two hypotheses over objects 4 and 9, the first the more probable."""
    rng = np.random.default_rng(3)
    a = rng.normal(size=(2, 3, 3))
    robot_cov = a @ np.swapaxes(a, 1, 2) * 0.01 + 0.01 * np.eye(3)
    b = rng.normal(size=(2, 2, 3, 3))
    object_cov = b @ np.swapaxes(b, -1, -2) * 0.01 + 0.01 * np.eye(3)
    return BeliefSnapshot(
        object_ids=(4, 9),
        weights=np.array([0.75, 0.25]),
        classes=np.array([[1, 0], [1, 1]], dtype=np.int64),
        robot_pose=np.array([[1.0, 2.0, 0.5], [1.1, 2.1, 0.4]]),
        robot_cov=robot_cov,
        object_pose=np.array([[[3.0, 1.0, 0.2], [0.0, -2.0, 1.0]]] * 2),
        object_cov=object_cov,
    )


def test_ros2_markers_show_per_object_class_marginals() -> None:
    """A belief with per-object class marginals is labelled from them, not from its one
    hypothesis' classes (here (table, chair), said otherwise on purpose)."""
    snap = _snapshot()
    one = BeliefSnapshot(
        snap.object_ids,
        np.array([1.0]),
        snap.classes[:1],
        snap.robot_pose[:1],
        snap.robot_cov[:1],
        snap.object_pose[:1],
        snap.object_cov[:1],
        class_probs=np.array([[0.6, 0.4], [0.2, 0.8]]),
    )
    types = types_for("humble")
    data = markers_message(types, one, 1, "map", "semfleet/r1", ("chair", "table"))
    markers = types.store.deserialize_cdr(data, MARKERS).markers
    assert [markers[1].text, markers[3].text] == ["chair 0.60", "table 0.80"]
    assert_close(class_marginals(one, 2), [[0.6, 0.4], [0.2, 0.8]])


@pytest.mark.parametrize("distro", DISTROS)
def test_ros2_belief_messages_round_trip_byte_for_byte(distro: str) -> None:
    types, snap = types_for(distro), _snapshot()
    stamp = 1_700_000_000_123_456_789
    for type_name, data in (
        (ODOMETRY, odometry_message(types, snap, stamp, "map", "r1/base_link")),
        (POSE, pose_message(types, snap, stamp, "map")),
        (MARKERS, markers_message(types, snap, stamp, "map", "semfleet/r1", ("chair", "table"))),
        (
            PATH,
            path_message(types, [(stamp - 10, snap.robot_pose[0]), (stamp, [1, 2, 3])], 7, "map"),
        ),
        (OBJECTS, objects_message(types, snap, stamp, "map", ("chair", "table"))),
        (TF, tf_message(types, stamp, "map", "r1/odom", np.array([0.5, -1.0, 2.5]))),
    ):
        assert data[:4] == CDR_LE
        msg = types.store.deserialize_cdr(data, type_name)
        assert bytes(types.store.serialize_cdr(msg, type_name)) == data, type_name


def test_ros2_odometry_carries_the_best_hypothesis_in_world_covariance() -> None:
    types, snap = types_for("jazzy"), _snapshot()
    data = odometry_message(types, snap, 5_000_000_001, "map", "base_link")
    msg = types.store.deserialize_cdr(data, ODOMETRY)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (5, 1)
    assert (msg.header.frame_id, msg.child_frame_id) == ("map", "base_link")
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    assert_close([p.x, p.y, p.z], [1.0, 2.0, 0.0])
    assert_angles_close(2 * math.atan2(q.z, q.w), 0.5)
    cov = msg.pose.covariance.reshape(6, 6)
    c, s = math.cos(0.5), math.sin(0.5)
    rot = np.array([[c, -s], [s, c]])
    assert_close(cov[:2, :2], rot @ snap.robot_cov[0][:2, :2] @ rot.T)
    assert_close(cov[5, 5], snap.robot_cov[0][2, 2])
    assert_close(np.diag(cov)[2:5], [UNUSED_VARIANCE] * 3)
    assert_close(cov, cov.T)


def test_ros2_covariance_6x6_of_a_pose_facing_x_is_the_tangent_one() -> None:
    cov = np.array([[0.1, 0.02, 0.01], [0.02, 0.2, 0.03], [0.01, 0.03, 0.3]])
    out = covariance_6x6(np.zeros(3), cov).reshape(6, 6)
    assert_close(out[np.ix_([0, 1, 5], [0, 1, 5])], cov)


def test_ros2_markers_show_ellipses_and_the_most_likely_class() -> None:
    types, snap = types_for("humble"), _snapshot()
    data = markers_message(types, snap, 1, "map", "semfleet/r1", ("chair", "table"))
    markers = types.store.deserialize_cdr(data, MARKERS).markers
    assert [(m.ns, m.id, m.type) for m in markers] == [
        ("semfleet/r1/ellipse", 4, 4),
        ("semfleet/r1/class", 4, 9),
        ("semfleet/r1/ellipse", 9, 4),
        ("semfleet/r1/class", 9, 9),
    ]
    # object 4 is class 1 in both hypotheses; object 9 class 0 with 0.75
    assert [markers[1].text, markers[3].text] == ["table 1.00", "chair 0.75"]
    assert_close(class_marginals(snap, 2), [[0.0, 1.0], [0.75, 0.25]])
    ring = np.array([[pt.x, pt.y] for pt in markers[0].points])
    assert_close(ring[0], ring[-1], atol=1e-12)
    assert_close(ring.mean(axis=0), [3.0, 1.0], atol=0.05)


@pytest.mark.parametrize("distro", DISTROS)
def test_ros2_odometry_reading_round_trips(distro: str) -> None:
    types = types_for(distro)
    pose = np.array([-3.5, 0.25, -2.0])
    data = odometry_reading_message(types, 42_000_000_007, "odom", "base_link", pose)
    reading = read_odometry(types, data)
    assert reading.stamp_ns == 42_000_000_007
    assert_close(reading.pose, pose)
    again = odometry_reading_message(types, reading.stamp_ns, "odom", "base_link", reading.pose)
    assert again == data


@pytest.mark.parametrize("distro", DISTROS)
def test_ros2_detections_round_trip_byte_for_byte(distro: str) -> None:
    types = types_for(distro)
    names = ("chair", "table", "door")
    dets = (
        Detection(7, np.array([1.5, -0.5, 0.3]), np.array([0.2, -1.0, 3.5])),
        Detection(0, np.array([0.0, 2.0, -3.0]), np.array([1.0, 2.0, 3.0])),
    )
    data = detections_message(types, 9_000_000_000, "camera", dets, names)
    assert data[:4] == CDR_LE
    reading = read_detections(types, data, {n: c for c, n in enumerate(names)})
    assert reading.stamp_ns == 9_000_000_000 and reading.dropped == 0
    for got, want in zip(reading.detections, dets, strict=True):
        assert got.object_id == want.object_id
        assert_close(got.z_geo, want.z_geo)
        assert_close(got.z_sem, want.z_sem)
    assert detections_message(types, 9_000_000_000, "camera", reading.detections, names) == data


def test_ros2_detections_unusable_ones_are_dropped_and_counted() -> None:
    types = types_for("jazzy")
    good = Detection(1, np.array([1.0, 0.0, 0.0]), np.array([0.5, 0.5]))
    dup = Detection(1, np.array([2.0, 0.0, 0.0]), np.array([0.1, 0.9]))
    data = detections_message(types, 1, "cam", (good, dup), ("a", "b"))
    reading = read_detections(types, data, {"a": 0, "b": 1})
    assert [d.object_id for d in reading.detections] == [1] and reading.dropped == 1
    unknown = read_detections(types, data, {"a": 0, "c": 1})  # a class name we do not know
    assert unknown.detections == () and unknown.dropped == 2
    msg = types.store.deserialize_cdr(data, DETECTIONS)
    msg.detections[0].id = "chair-1"
    bad_id = bytes(types.store.serialize_cdr(msg, DETECTIONS))
    renamed = read_detections(types, bad_id, {"a": 0, "b": 1})  # and no longer a duplicate
    assert [d.object_id for d in renamed.detections] == [1] and renamed.dropped == 1
    assert_close(renamed.detections[0].z_geo, [2.0, 0.0, 0.0])


def test_ros2_malformed_cdr_is_one_error_type() -> None:
    types = types_for("jazzy")
    good = odometry_reading_message(types, 1, "odom", "base_link", np.zeros(3))
    dets = detections_message(types, 1, "cam", (Detection(3, np.zeros(3), np.ones(2)),), ("a", "b"))
    rng = np.random.default_rng(0)
    bad = [b"", CDR_LE, good[:40], dets[:-3], b"\x00\x01\x00\x00" + b"\xff" * 64]
    bad += [rng.bytes(int(rng.integers(0, 300))) for _ in range(200)]
    for blob in (
        *bad,
        *(_flip(good, rng) for _ in range(100)),
        *(_flip(dets, rng) for _ in range(100)),
    ):
        for read in (
            lambda b: read_odometry(types, b),
            lambda b: read_detections(types, b, {"a": 0, "b": 1}),
        ):
            with contextlib.suppress(Ros2MessageError):
                read(blob)


def _flip(data: bytes, rng: np.random.Generator) -> bytes:
    out = bytearray(data)
    for i in rng.integers(0, len(out), 4):
        out[i] = int(rng.integers(0, 256))
    return bytes(out)


def test_ros2_objects_score_every_class_by_its_marginal() -> None:
    types, snap = types_for("jazzy"), _snapshot()
    msg = types.store.deserialize_cdr(
        objects_message(types, snap, 3, "map", ("chair", "table")), OBJECTS
    )
    marginals = class_marginals(snap, 2)
    assert [d.id for d in msg.detections] == ["4", "9"]
    for j, det in enumerate(msg.detections):
        assert_close([r.hypothesis.score for r in det.results], marginals[j])
        pose = snap.object_pose[0, j]  # the most probable hypothesis
        wanted = covariance_6x6(pose, snap.object_cov[0, j])
        for r in det.results:
            assert_close(r.pose.covariance, wanted)
            assert_close([r.pose.pose.position.x, r.pose.pose.position.y], pose[:2])
    assert_close(marginals[1], [0.75, 0.25])  # not a one-hot: the hypotheses disagree
