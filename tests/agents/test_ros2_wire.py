"""rmw_zenoh's key expressions, type hashes, attachments and liveliness tokens, per distro, against
values captured from rmw_zenoh's sources and docs (docs/ros2.md cites them)."""

from __future__ import annotations

import pytest
import zenoh.ext

from agents.ros2.messages import DETECTIONS, MARKERS, ODOMETRY, POSE, types_for
from agents.ros2.outputs import TF
from agents.ros2.wire import (
    DEFAULT_QOS,
    KEEP_ALL,
    TRANSIENT_LOCAL,
    AttachmentError,
    GraphNode,
    dds_type_name,
    decode_attachment,
    encode_attachment,
    mangle,
    qos_chunk,
    resolve_topic,
    ros_name_problem,
    topic_key,
    topic_key_any_hash,
)

# rmw_zenoh docs/design.md: the key of /chatter (std_msgs/msg/String) in domain 0 on Jazzy.
CHATTER_KEY = (
    "0/chatter/std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"
)
# A Jazzy talker's publisher token as rmw_zenoh declares it (liveliness_utils.cpp layout).
TALKER_TOKEN = (
    "@ros2_lv/0/aac3178e146ba6f1fc6e6a4085e77f21/0/11/MP/%/%/talker/%chatter/"
    "std_msgs::msg::dds_::String_/"
    "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18/::,7:,:,:,,"
)
# zenoh-ext serialization of (int64 7, int64 1234567890123, [u8; 16] 0..15): rmw_zenoh's
# AttachmentData::serialize_to_zbytes, 33 bytes.
ATTACHMENT = bytes.fromhex("0700000000000000cb04fb711f01000010000102030405060708090a0b0c0d0e0f")


def test_ros2_dds_type_name_follows_rmw_zenoh() -> None:
    assert dds_type_name("nav_msgs/msg/Odometry") == "nav_msgs::msg::dds_::Odometry_"
    with pytest.raises(ValueError):
        dds_type_name("nav_msgs/Odometry")


def test_ros2_jazzy_key_of_chatter_is_the_design_docs() -> None:
    h = types_for("jazzy").type_hash("std_msgs/msg/String")
    assert topic_key(0, "/chatter", "std_msgs/msg/String", h) == CHATTER_KEY


def test_ros2_humble_key_has_no_type_hash() -> None:
    h = types_for("humble").type_hash(ODOMETRY)
    assert h == "TypeHashNotSupported"
    key = topic_key(3, "/r1/semfleet/odometry", ODOMETRY, h)
    assert key == "3/r1/semfleet/odometry/nav_msgs::msg::dds_::Odometry_/TypeHashNotSupported"


def test_ros2_jazzy_hashes_are_rihs01_of_each_type() -> None:
    types = types_for("jazzy")
    hashes = {t: types.type_hash(t) for t in (ODOMETRY, POSE, MARKERS, DETECTIONS)}
    for h in hashes.values():
        assert h.startswith("RIHS01_") and len(h) == 7 + 64
        int(h[7:], 16)
    assert len(set(hashes.values())) == 4
    # tf2_msgs/msg/TFMessage as a Jazzy /tf publisher's token carries it (a third-party
    # rmw_zenoh client's test, from the public code index).
    assert types.type_hash(TF) == (
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"
    )
    # nav_msgs/msg/Odometry as ROS 2 Jazzy computes it (its type description is unchanged).
    assert hashes[ODOMETRY] == (
        "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0"
    )


def test_ros2_subscription_expression_hears_any_hash() -> None:
    expr = topic_key_any_hash(0, "/r1/odom", ODOMETRY)
    assert expr == "0/r1/odom/nav_msgs::msg::dds_::Odometry_/*"


def test_ros2_topics_resolve_under_the_namespace() -> None:
    assert resolve_topic("/r1", "odom") == "/r1/odom"
    assert resolve_topic("/r1/", "a/b") == "/r1/a/b"
    assert resolve_topic("/r1", "/odom") == "/odom"
    assert mangle("/r1/odom") == "%r1%odom"
    assert mangle("/") == "%"


def test_ros2_publisher_token_is_byte_for_byte_rmw_zenohs() -> None:
    node = GraphNode(0, "aac3178e146ba6f1fc6e6a4085e77f21", 0, "/", "talker")
    h = types_for("jazzy").type_hash("std_msgs/msg/String")
    token = node.endpoint_token(11, "MP", "/chatter", "std_msgs/msg/String", h, "::,7:,:,:,,")
    assert token == TALKER_TOKEN


# robot_state_publisher's /robot_description publisher (transient local, depth 1), as another
# project that reads rmw_zenoh's graph records it from a live Jazzy system (a Rust token parser's
# test, found in the public code index; type hash shortened there).
ROBOT_DESCRIPTION_QOS = ":1:,1:,:,:,,"


def test_ros2_qos_chunk_leaves_rmw_zenohs_defaults_out() -> None:
    assert qos_chunk(depth=7) == TALKER_TOKEN.rsplit("/", 1)[1]
    assert DEFAULT_QOS == "::,10:,:,:,,"  # rclcpp's QoS(10): only the depth differs from 42
    assert qos_chunk(durability=TRANSIENT_LOCAL, depth=1) == ROBOT_DESCRIPTION_QOS
    assert qos_chunk() == "::,:,:,:,,"  # every value rmw_zenoh's default
    assert qos_chunk(2, 1, KEEP_ALL, 5) == "2:1:2,5:,:,:,,"


@pytest.mark.parametrize(
    ("name", "problem"),
    [
        ("/r1/semfleet__odometry", "repeated underscores"),
        ("/r1/__objects", "repeated underscores"),
        ("r1//odom", "repeated '/'"),
        ("/r1/odom/", "ends with '/'"),
        ("/r1/2d", "starts with a digit"),
        ("3d", "starts with a digit"),
        ("/r-1/odom", "characters other than"),
        ("~/odom", "characters other than"),
        ("", "is empty"),
        ("/" + "a" * 247, "longer than 247"),
    ],
)
def test_ros2_names_the_ros2_rules_forbid_are_refused(name: str, problem: str) -> None:
    found = ros_name_problem(name)
    assert found is not None and problem in found


@pytest.mark.parametrize("name", ["/r1/odom", "odom", "_hidden/x", "/a" * 10, "a_b/c_d", "A9"])
def test_ros2_names_the_ros2_rules_allow_are_taken(name: str) -> None:
    assert ros_name_problem(name) is None


def test_ros2_tokens_have_rmw_zenohs_13_non_empty_chunks() -> None:
    node = GraphNode(5, "0123abcd", 0, "/r1", "semfleet_r1")
    assert node.node_token() == "@ros2_lv/5/0123abcd/0/0/NN/%/%r1/semfleet_r1"
    token = node.endpoint_token(2, "MS", "/r1/odom", ODOMETRY, "TypeHashNotSupported")
    chunks = token.split("/")
    assert len(chunks) == 13 and all(chunks)
    assert chunks[5:] == [
        "MS", "%", "%r1", "semfleet_r1", "%r1%odom",
        "nav_msgs::msg::dds_::Odometry_", "TypeHashNotSupported", DEFAULT_QOS,
    ]  # fmt: skip
    with pytest.raises(ValueError):
        node.endpoint_token(2, "SS", "/x", ODOMETRY, "TypeHashNotSupported")


def test_ros2_attachment_is_zenoh_ext_serialization() -> None:
    gid = bytes(range(16))
    assert encode_attachment(7, 1234567890123, gid) == ATTACHMENT
    assert decode_attachment(ATTACHMENT) == (7, 1234567890123, gid)


def test_ros2_attachment_matches_zenoh_python_serializer() -> None:
    gid = bytes(range(100, 116))
    expected = zenoh.ext.z_serialize((zenoh.ext.Int64(-5), zenoh.ext.Int64(2**62), gid))
    assert encode_attachment(-5, 2**62, gid) == expected.to_bytes()


def test_ros2_attachment_refuses_other_layouts() -> None:
    with pytest.raises(AttachmentError):
        decode_attachment(ATTACHMENT[:-1])
    with pytest.raises(AttachmentError):
        decode_attachment(ATTACHMENT[:16] + b"\x0f" + ATTACHMENT[17:])
    with pytest.raises(ValueError):
        encode_attachment(1, 1, b"short")
