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
# reliability RELIABLE (1), durability VOLATILE (2), history KEEP_LAST (1) with depth 10; deadline,
# lifespan and liveliness left empty (the defaults) — every rmw_zenoh release parses this form.
DEFAULT_QOS = "1:2:1,10:,:,:,,"
_ATTACHMENT = struct.Struct("<qqB16s")  # int64, int64, then the gid as a sequence: VLE length 16
_TYPE_NAME = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/msg/([A-Za-z][A-Za-z0-9_]*)$")
_ROS_NAME = re.compile(r"^/?[A-Za-z_][A-Za-z0-9_]*(/[A-Za-z_][A-Za-z0-9_]*)*$")


class AttachmentError(ValueError):
    """An attachment that is not rmw_zenoh's 33 bytes."""


def valid_ros_name(name: str) -> bool:
    """A ROS 2 topic, namespace or node name (no ``~``, no substitutions)."""
    return bool(_ROS_NAME.match(name))


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
