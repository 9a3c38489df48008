"""The agent's ROS 2 side without any I/O: tokens and keys from the settings, the samples of an
estimate, and frames from odometry + detections (one step per detections message, odometry
matched by stamp and integrated between steps)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from agents.ros2.bridge import Ros2Bridge, Ros2Settings
from agents.ros2.messages import MARKERS, ODOMETRY, POSE
from agents.ros2.outputs import OBJECTS, PATH, TF
from agents.ros2.readings import detections_message, odometry_reading_message
from agents.ros2.wire import DEFAULT_QOS, dds_type_name, decode_attachment
from estimator.models import Detection
from estimator.models.se2 import between, compose
from estimator.snapshot import BeliefSnapshot
from protocol.estimate import EstimateMessage, encode_estimate
from protocol.frames import decode_frame
from tests.tolerance import assert_close

ODOM_KEY = f"0/r1/odom/{dds_type_name(ODOMETRY)}/TypeHashNotSupported"
DET_KEY = "0/r1/detections/vision_msgs::msg::dds_::Detection2DArray_/RIHS01_" + "0" * 64
S = 10**9


def _bridge(distro: str = "jazzy", **kw: Any) -> Ros2Bridge:
    settings = Ros2Settings(namespace="/r1", node="semfleet_r1", distro=distro, **kw)
    return Ros2Bridge(settings, "r1", 2, "00ff")


def _odom(b: Ros2Bridge, t: float, pose: list[float]) -> list[bytes]:
    data = odometry_reading_message(b.types, int(t * S), "odom", "base_link", np.array(pose))
    return b.on_input(ODOM_KEY, data)


def _dets(b: Ros2Bridge, t: float, oids: tuple[int, ...] = (3,)) -> list[bytes]:
    dets = [Detection(o, np.array([1.0, 0.5, 0.1]), np.array([0.3, 0.7])) for o in oids]
    data = detections_message(b.types, int(t * S), "cam", dets, b.class_names)
    return b.on_input(DET_KEY, data)


def test_ros2_bridge_tokens_and_inputs_follow_the_settings() -> None:
    b = _bridge()
    tokens = b.tokens()
    assert tokens[0] == "@ros2_lv/0/00ff/0/0/NN/%/%r1/semfleet_r1"
    kinds = [t.split("/")[5] for t in tokens]
    assert kinds == ["NN", "MP", "MP", "MP", "MP", "MP", "MP", "MS", "MS"]
    assert [t.split("/")[9] for t in tokens[1:]] == [
        "%r1%semfleet%odometry", "%r1%semfleet%pose", "%r1%semfleet%objects",
        "%r1%semfleet%path", "%r1%semfleet%detections", "%tf", "%r1%odom", "%r1%detections",
    ]  # fmt: skip
    # /tf as tf2_ros' broadcaster declares it (depth 100), the others as rclcpp's QoS(10).
    assert [t.rsplit("/", 1)[1] for t in tokens[1:]] == [DEFAULT_QOS] * 5 + ["::,100:,:,:,,"] + [
        DEFAULT_QOS
    ] * 2
    assert b.input_type(ODOM_KEY) == ODOMETRY
    assert b.input_type("0/r1/odom/std_msgs::msg::dds_::String_/x") is None
    off = _bridge(detections_in="")
    assert off.inputs == {} and len(off.tokens()) == 7


def test_ros2_bridge_refuses_class_names_of_another_length() -> None:
    with pytest.raises(ValueError, match="3 class names for 2"):
        _bridge(class_names=("a", "b", "c"))


def test_ros2_bridge_frames_one_step_per_detections_message() -> None:
    b = _bridge()
    b.next_step = 4  # after a journal replay to step 3
    assert _odom(b, 1.0, [0.0, 0.0, 0.0]) == []
    assert _dets(b, 1.5) == []  # waits: no odometry at or after 1.5 yet
    assert _odom(b, 1.4, [0.4, 0.0, 0.1]) == []
    (f1,) = _odom(b, 2.0, [1.0, 0.2, 0.3])  # now 1.5 is covered: odometry 1.4 is its pose
    frame = decode_frame(f1)
    assert (frame.robot, frame.k) == ("r1", 4)
    assert_close(frame.odometry, between(np.zeros(3), [0.4, 0.0, 0.1]))
    assert np.isnan(frame.true_pose).all()
    assert [d.object_id for d in frame.detections] == [3]
    assert_close(frame.detections[0].z_sem, [0.3, 0.7])
    (f2,) = _dets(b, 2.0, (3, 5))  # odometry 2.0 already there
    frame = decode_frame(f2)
    assert frame.k == 5 and len(frame.detections) == 2
    assert_close(frame.odometry, between([0.4, 0.0, 0.1], [1.0, 0.2, 0.3]))
    (f3,) = _dets(b, 2.0, ())  # an empty detections message is still a step: no motion
    assert decode_frame(f3).k == 6 and decode_frame(f3).detections == ()
    assert_close(decode_frame(f3).odometry, np.zeros(3))
    assert b.counter_values()["ros_frames_built"] == 3


def test_ros2_bridge_counts_and_drops_malformed_samples() -> None:
    b = _bridge()
    assert b.on_input(ODOM_KEY, b"\x00\x01\x00\x00garbage") == []
    assert b.on_input(DET_KEY, b"") == []
    assert b.on_input("0/elsewhere/x/y", b"whatever") == []  # not an input: ignored
    assert b.counter_values()["ros_malformed"] == 2


def _estimate(k: int, pose: tuple[float, float, float] = (1.0, 2.0, 0.3)) -> bytes:
    snap = BeliefSnapshot(
        object_ids=(2,),
        weights=np.array([1.0]),
        classes=np.array([[1]], dtype=np.int64),
        robot_pose=np.array([pose]),
        robot_cov=np.eye(3)[None] * 0.01,
        object_pose=np.array([[[2.0, 2.0, 0.0]]]),
        object_cov=np.eye(3)[None, None] * 0.02,
    )
    return encode_estimate(EstimateMessage("r1", k, {"distributed": snap}))


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_ros2_bridge_publishes_each_estimate_with_attachments(distro: str) -> None:
    b = _bridge(distro)
    first = b.on_estimate(_estimate(0), 77)
    second = b.on_estimate(_estimate(0), 78)
    hashes = {t: b.types.type_hash(t) for t in (ODOMETRY, POSE, MARKERS, PATH, OBJECTS)}
    assert [s.key for s in first] == [
        f"0/r1/semfleet/odometry/{dds_type_name(ODOMETRY)}/{hashes[ODOMETRY]}",
        f"0/r1/semfleet/pose/{dds_type_name(POSE)}/{hashes[POSE]}",
        f"0/r1/semfleet/objects/{dds_type_name(MARKERS)}/{hashes[MARKERS]}",
        f"0/r1/semfleet/path/{dds_type_name(PATH)}/{hashes[PATH]}",
        f"0/r1/semfleet/detections/{dds_type_name(OBJECTS)}/{hashes[OBJECTS]}",
    ]  # no /tf: these steps did not come from the robot's odometry
    gids = set()
    for s1, s2 in zip(first, second, strict=True):
        seq1, t1, gid1 = decode_attachment(s1.attachment)
        seq2, t2, gid2 = decode_attachment(s2.attachment)
        assert (seq1, seq2, t1, t2) == (1, 2, 77, 78) and gid1 == gid2
        gids.add(gid1)
    assert len(gids) == 5  # one gid per publisher
    msg = b.types.store.deserialize_cdr(first[0].payload, ODOMETRY)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (0, 77)


def test_ros2_bridge_stamps_an_estimate_with_its_steps_detections() -> None:
    b = _bridge()
    _odom(b, 10.0, [0.0, 0.0, 0.0])
    _odom(b, 11.0, [0.0, 0.0, 0.0])
    assert len(_dets(b, 10.5)) == 1
    (odom, *_) = b.on_estimate(_estimate(1), 99 * S)
    msg = b.types.store.deserialize_cdr(odom.payload, ODOMETRY)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (10, S // 2)


def _by_type(samples: list[Any], b: Ros2Bridge) -> dict[str, Any]:
    types = {}
    for t in (ODOMETRY, POSE, MARKERS, PATH, OBJECTS, TF):
        types[dds_type_name(t)] = t
    out = {}
    for sample in samples:
        t = types[sample.key.split("/")[-2]]
        out[t] = b.types.store.deserialize_cdr(sample.payload, t)
    return out


def test_ros2_bridge_tf_is_the_map_to_odom_correction_of_ros2_steps() -> None:
    b = _bridge()
    odom_pose = np.array([0.7, -0.2, 0.4])
    data = odometry_reading_message(b.types, 10 * S, "r1/odom", "r1/base_link", odom_pose)
    assert b.on_input(ODOM_KEY, data) == []
    data = odometry_reading_message(b.types, 11 * S, "r1/odom", "r1/base_link", odom_pose)
    b.on_input(ODOM_KEY, data)
    assert len(_dets(b, 10.5)) == 1  # step 1 takes the odometry pose stamped 10 s
    estimated = (3.0, 1.0, 1.2)
    msgs = _by_type(b.on_estimate(_estimate(1, estimated), 99 * S), b)
    (tf,) = msgs[TF].transforms
    assert (tf.header.frame_id, tf.child_frame_id) == ("map", "r1/odom")  # the robot's odom frame
    assert (tf.header.stamp.sec, tf.header.stamp.nanosec) == (10, S // 2)
    t, q = tf.transform.translation, tf.transform.rotation
    correction = np.array([t.x, t.y, 2 * np.arctan2(q.z, q.w)])
    # map → odom → base_link is where the belief has the robot (REP 105).
    assert_close(compose(correction, odom_pose), estimated, atol=1e-12)
    assert t.z == 0.0 and q.x == q.y == 0.0


def test_ros2_bridge_path_holds_every_steps_estimate_once() -> None:
    b = _bridge()
    for k, x in ((0, 0.0), (1, 1.0), (1, 1.5), (2, 2.0)):  # step 1 re-published: replaced
        msgs = _by_type(b.on_estimate(_estimate(k, (x, 0.0, 0.0)), (10 + k) * S), b)
    poses = msgs[PATH].poses
    assert [p.pose.position.x for p in poses] == [0.0, 1.5, 2.0]
    assert [p.header.stamp.sec for p in poses] == [10, 11, 12]
    assert msgs[PATH].header.frame_id == "map" and poses[0].header.frame_id == "map"


def test_ros2_bridge_detections_carry_every_class_and_the_covariance() -> None:
    b = _bridge(class_names=("chair", "table"))
    msgs = _by_type(b.on_estimate(_estimate(0), 5), b)
    (det,) = msgs[OBJECTS].detections
    assert det.id == "2"
    assert [r.hypothesis.class_id for r in det.results] == ["chair", "table"]
    scores = [r.hypothesis.score for r in det.results]
    assert_close(scores, [0.0, 1.0])  # the one hypothesis holds class 1
    cov = det.results[0].pose.covariance.reshape(6, 6)
    assert_close(cov[:2, :2], np.eye(2) * 0.02, atol=1e-15)
    assert cov[2, 2] == 1e6 and det.bbox.center.position.x == 2.0
