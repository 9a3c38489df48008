"""What rmw_zenoh puts on Zenoh besides the CDR payload, per ROS distro (docs/ros2.md cites the
rmw_zenoh sources): data key expressions, the attachment of every sample and the liveliness
tokens of the ROS graph. Pure string and byte formatting: no rosbags, no Zenoh.
"""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass

DISTROS = ("humble", "jazzy")
NO_TYPE_HASH = "TypeHashNotSupported"  # Humble's type-hash chunk (no RIHS01 before Iron)
ADMIN_SPACE = "@ros2_lv"
GID_BYTES = 16
# rmw_zenoh's default QoS (rmw_zenoh_cpp/src/detail/qos.cpp): a token leaves out every value equal
# to it. rmw's enums: reliability RELIABLE 1, BEST_EFFORT 2; durability TRANSIENT_LOCAL 1,
# VOLATILE 2; history KEEP_LAST 1, KEEP_ALL 2; liveliness AUTOMATIC 1, MANUAL_BY_TOPIC 3.
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
RMW_ZENOH_DEFAULT_DEPTH = 42
MAX_TOPIC_LENGTH = 255 - 8  # RMW_TOPIC_MAX_NAME_LENGTH: DDS's limit less 8 reserved for prefixes
_ATTACHMENT = struct.Struct("<qqB16s")  # int64, int64, then the gid as a sequence: VLE length 16
_TYPE_NAME = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/msg/([A-Za-z][A-Za-z0-9_]*)$")
_NAME_CHARS = re.compile(r"^[A-Za-z0-9_/]*$")


class AttachmentError(ValueError):
    """An attachment that is not rmw_zenoh's 33 bytes."""


def ros_name_problem(name: str) -> str | None:
    """Why ``name`` is not a ROS 2 topic, namespace or node name, or None if it is one. The rules
    of ROS 2's naming design (ros2/design, "Topic and Service name mapping to DDS") that rcl and
    rmw check, and repeated underscores, which the design forbids in a name token; ``~`` and
    ``{}`` substitutions are not taken."""
    if not name:
        return "is empty"
    if not _NAME_CHARS.match(name):
        return "has characters other than letters, digits, '_' and '/'"
    if "//" in name:
        return "has repeated '/'"
    if name.endswith("/"):
        return "ends with '/'"
    if "__" in name:
        return "has repeated underscores ('__' is reserved by ROS 2)"
    if any(token[:1].isdigit() for token in name.lstrip("/").split("/")):
        return "has a token that starts with a digit"
    if len(name) > MAX_TOPIC_LENGTH:
        return f"is longer than {MAX_TOPIC_LENGTH} characters"
    return None


def valid_ros_name(name: str) -> bool:
    """A ROS 2 topic, namespace or node name (:func:`ros_name_problem`)."""
    return ros_name_problem(name) is None


def qos_chunk(
    reliability: int = RELIABLE,
    durability: int = VOLATILE,
    history: int = KEEP_LAST,
    depth: int = RMW_ZENOH_DEFAULT_DEPTH,
) -> str:
    """A token's QoS chunk as rmw_zenoh's ``qos_to_keyexpr`` writes it: ``reliability:durability:
    history,depth:deadline s,ns:lifespan s,ns:liveliness,lease s,lease ns``, every value equal
    to rmw_zenoh's default left out (deadline, lifespan and lease infinite, liveliness automatic:
    the defaults, always left out here)."""

    def chunk(value: int, default: int) -> str:
        return "" if value == default else str(value)

    return (
        f"{chunk(reliability, RELIABLE)}:{chunk(durability, VOLATILE)}:"
        f"{chunk(history, KEEP_LAST)},{chunk(depth, RMW_ZENOH_DEFAULT_DEPTH)}:,:,:,,"
    )


# rclcpp's and rclpy's default publisher and subscription QoS (a depth of 10, reliable, volatile).
DEFAULT_DEPTH = 10
DEFAULT_QOS = qos_chunk(depth=DEFAULT_DEPTH)
TF_DEPTH = 100  # tf2_ros' TransformBroadcaster's depth (reliable, volatile)
TF_QOS = qos_chunk(depth=TF_DEPTH)


def resolve_topic(namespace: str, topic: str) -> str:
    """The absolute topic name: ``topic`` if absolute, else under ``namespace``."""
    if topic.startswith("/"):
        return topic
    return f"{namespace.rstrip('/')}/{topic}"


def dds_type_name(type_name: str) -> str:
    """``nav_msgs/msg/Odometry`` → ``nav_msgs::msg::dds_::Odometry_`` (the name rmw_zenoh puts in
    keys and tokens)."""
    m = _TYPE_NAME.match(type_name)
    if m is None:
        raise ValueError(f"not a ROS 2 message type name: {type_name!r}")
    return f"{m.group(1)}::msg::dds_::{m.group(2)}_"


def topic_key(domain_id: int, topic: str, type_name: str, type_hash: str) -> str:
    """``<domain_id>/<topic without its outer slashes>/<dds type>/<type hash>``."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(type_name)}/{type_hash}"


def topic_key_any_hash(domain_id: int, topic: str, type_name: str) -> str:
    """The subscription expression of a topic whatever the publisher's type hash (a Humble
    publisher and one whose type description differs from ours are both heard)."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(type_name)}/*"


def mangle(name: str) -> str:
    """A name as one key chunk: every ``/`` replaced by ``%`` (so ``/`` alone becomes ``%``)."""
    return name.replace("/", "%")


@dataclass(frozen=True, slots=True)
class GraphNode:
    """The ROS node a token belongs to. ``zid``: the Zenoh session id as hex; ``nid``: the node's
    entity id within the session."""

    domain_id: int
    zid: str
    nid: int
    namespace: str
    name: str
    enclave: str = "/"

    def _head(self, eid: int, kind: str) -> str:
        chunks = (ADMIN_SPACE, str(self.domain_id), self.zid, str(self.nid), str(eid), kind)
        tail = (mangle(self.enclave), mangle(self.namespace), mangle(self.name))
        return "/".join((*chunks, *tail))

    def node_token(self) -> str:
        """``@ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>``."""
        return self._head(self.nid, "NN")

    def endpoint_token(
        self,
        eid: int,
        kind: str,
        topic: str,
        type_name: str,
        type_hash: str,
        qos: str = DEFAULT_QOS,
    ) -> str:
        """A publisher (``MP``) or subscription (``MS``) token: the node's chunks, then the mangled
        topic, the dds type, the type hash and the QoS."""
        if kind not in ("MP", "MS"):
            raise ValueError(f"entity kind {kind!r} (MP or MS)")
        topic_chunks = (mangle(topic), dds_type_name(type_name), type_hash, qos)
        return "/".join((self._head(eid, kind), *topic_chunks))


def endpoint_gid(token: str) -> bytes:
    """A publisher's 16-byte gid, a digest of its token. rmw_zenoh takes XXH3-128 of the token; the
    gid only has to be unique per publisher (subscribers read it as message info), so SHA-256's
    first 16 bytes do."""
    return hashlib.sha256(token.encode()).digest()[:GID_BYTES]


def encode_attachment(sequence_number: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """rmw_zenoh's attachment (zenoh-ext serialization): int64 sequence number, int64 source
    timestamp (ns since the Unix epoch), the 16-byte gid as a sequence (VLE length 16, bytes)."""
    if len(gid) != GID_BYTES:
        raise ValueError(f"gid has {len(gid)} bytes, expected {GID_BYTES}")
    return _ATTACHMENT.pack(sequence_number, source_timestamp_ns, GID_BYTES, gid)


def decode_attachment(data: bytes) -> tuple[int, int, bytes]:
    """(sequence number, source timestamp ns, gid) of an attachment; :class:`AttachmentError`
    for anything else than exactly that layout."""
    if len(data) != _ATTACHMENT.size:
        raise AttachmentError(f"attachment has {len(data)} bytes, expected {_ATTACHMENT.size}")
    seq, stamp, length, gid = _ATTACHMENT.unpack(data)
    if length != GID_BYTES:
        raise AttachmentError(f"gid length {length}, expected {GID_BYTES}")
    return seq, stamp, gid
