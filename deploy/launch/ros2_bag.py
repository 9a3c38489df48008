"""A launch's rosbag2 recording (``--ros2-bag DIR``, docs/ros2.md, "A recording of a run"): every
robot's belief out as the ROS 2 messages its agent publishes with ``[ros2]`` on — the same
bridge (:class:`~agents.ros2.bridge.Ros2Bridge`) run over the estimates the conductor kept, so
the CDR bytes are the agents' up to the stamps — written with rosbags as a rosbag2 folder of one
MCAP file (``metadata.yaml`` for ``ros2 bag play``, ``DIR/<DIR's name>.mcap`` for Foxglove).

Time: the estimates carry no clock, so step k is logged and stamped at ``start_ns + k · period``
(the run's start, its step period), the order a replay of the run needs."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from agents.ros2.bridge import Ros2Bridge, Ros2Settings
from agents.ros2.outputs import TF
from agents.ros2.wire import DEFAULT_DEPTH, TF_DEPTH
from protocol.estimate import EstimateMessage

if TYPE_CHECKING:
    from rosbags.interfaces import Qos

BAG_METADATA = "metadata.yaml"  # what rosbag2 writes next to the storage files
# rosbag2's metadata version for a distro's `ros2 bag play` (rosbags writes 8 or 9). Jazzy's
# rosbag2 writes 9, whose topics' offered_qos_profiles are a YAML list with names for the enums;
# Humble's (which writes 5) reads any version without checking it, takes the keys it knows and
# reads offered_qos_profiles as a string of QoS with integer enums: version 8's form. A
# version-9 bag fails in Humble with "Exception on parsing info file: ... bad conversion"
# (ros2/rosbag2 humble, rosbag2_storage/src/rosbag2_storage/metadata_io.cpp).
BAG_VERSIONS: dict[str, Literal[8, 9]] = {"humble": 8, "jazzy": 9}
SESSION_ID = "0" * 32  # a recording has no Zenoh session: the bridge's tokens are not used


def bag_topic(key: str) -> str:
    """The ROS 2 topic of an rmw_zenoh data key ``<domain>/<topic>/<type>/<hash>``: neither the
    type nor the hash chunk holds a ``/``."""
    return "/" + "/".join(key.split("/")[1:-2])


def offered_qos(depth: int) -> Qos:
    """The QoS a robot's publisher offers (reliable, volatile, keep last ``depth``; deadline,
    lifespan and lease left at rmw's default 0 s, liveliness automatic), as ``ros2 bag play``
    reads it back to publish the topic again, as rosbag2 records what a publisher offered
    (rosbags writes an empty string unless given one)."""
    from rosbags.interfaces import (
        Qos,
        QosDurability,
        QosHistory,
        QosLiveliness,
        QosReliability,
        QosTime,
    )

    zero = QosTime(0, 0)
    return Qos(
        QosHistory.KEEP_LAST, depth, QosReliability.RELIABLE, QosDurability.VOLATILE, zero, zero,
        QosLiveliness.AUTOMATIC, zero, False,
    )  # fmt: skip


def write_bag(
    path: Path,
    settings: Mapping[str, Ros2Settings],
    num_classes: int,
    estimates: Mapping[tuple[str, int], EstimateMessage],
    start_ns: int,
    period_s: float,
) -> dict[str, int]:
    """Write the bag folder ``path`` (it must not exist): per robot of ``settings`` the samples
    its bridge makes of its ``estimates``, step by step. Returns the messages per topic."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    bridges = {r: Ros2Bridge(s, r, num_classes, SESSION_ID) for r, s in settings.items()}
    (distro,) = {s.distro for s in settings.values()} or {"jazzy"}
    counts: dict[str, int] = {}
    version = BAG_VERSIONS[distro]
    with Writer(path, version=version, storage_plugin=StoragePlugin.MCAP) as writer:
        connections = {}
        for (robot, k), estimate in sorted(estimates.items(), key=lambda e: (e[0][1], e[0][0])):
            if robot not in bridges:
                continue
            bridge = bridges[robot]
            stamp = start_ns + round(k * period_s * 1e9)
            for sample in bridge.samples_of(estimate, stamp):
                if sample.key not in connections:
                    p = next(p for p in bridge.publications.values() if p.key == sample.key)
                    depth = TF_DEPTH if p.type_name == TF else DEFAULT_DEPTH  # as published
                    connections[sample.key] = writer.add_connection(
                        bag_topic(sample.key),
                        p.type_name,
                        typestore=bridge.types.store,
                        offered_qos_profiles=[offered_qos(depth)],
                    )
                writer.write(connections[sample.key], stamp, sample.payload)
                topic = bag_topic(sample.key)
                counts[topic] = counts.get(topic, 0) + 1
    return counts
