"""A robot's ROS 2 readings, in and out of CDR: its odometry (``nav_msgs/msg/Odometry``, the pose
only) and its detections (``vision_msgs/msg/Detection2DArray``; docs/ros2.md, "Frames in"). The
writers are what a robot's driver and detector publish: for tests and the docs' example."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from agents.ros2.messages import (
    DETECTIONS,
    ODOMETRY,
    Array,
    Ros2MessageError,
    Ros2Types,
    header,
    planar_pose,
)
from estimator.models import Detection


def _stamp_ns(head: Any) -> int:
    return int(head.stamp.sec) * 10**9 + int(head.stamp.nanosec)


def _planar(pose: Any, field: str) -> Array:
    """(x, y, yaw) of a geometry_msgs/Pose; yaw from the quaternion (roll and pitch ignored)."""
    p, q = pose.position, pose.orientation
    quat = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    xy = np.array([p.x, p.y], dtype=np.float64)
    if not (np.isfinite(xy).all() and np.isfinite(quat).all()):
        raise Ros2MessageError(f"{field}: non-finite number")
    if np.abs(quat).max() > 1.5 or not 0.5 < float(np.linalg.norm(quat)) < 1.5:
        raise Ros2MessageError(f"{field}: not a unit quaternion")
    x, y, z, w = quat
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.array([xy[0], xy[1], yaw])


@dataclass(frozen=True, slots=True)
class OdometryReading:
    """A robot's odometry pose (3,) in its odom frame ``frame_id`` at ``stamp_ns``."""

    stamp_ns: int
    pose: Array
    frame_id: str = "odom"


def read_odometry(types: Ros2Types, data: bytes) -> OdometryReading:
    msg = types.deserialize(data, ODOMETRY)
    pose = _planar(msg.pose.pose, "pose.pose")
    return OdometryReading(_stamp_ns(msg.header), pose, msg.header.frame_id)


@dataclass(frozen=True, slots=True)
class DetectionsReading:
    """The detections of one message at ``stamp_ns``, and how many of its detections were
    unusable (bad id, duplicate id, scores not one per class, bad pose)."""

    stamp_ns: int
    detections: tuple[Detection, ...]
    dropped: int


def read_detections(
    types: Ros2Types, data: bytes, class_index: Mapping[str, int]
) -> DetectionsReading:
    """A ``vision_msgs/msg/Detection2DArray`` as detections (docs/ros2.md, "Frames in"): per
    Detection2D, ``id`` the object id (decimal), one result per class whose ``class_id`` is a key
    of ``class_index`` and whose ``score`` is that class' entry of z_sem, the first result's pose
    the object's pose in the robot's body frame (z_geo)."""
    msg = types.deserialize(data, DETECTIONS)
    m = len(class_index)
    dets: list[Detection] = []
    seen: set[int] = set()
    dropped = 0
    for i, d in enumerate(msg.detections):
        try:
            dets.append(_detection(d, class_index, m, f"detections[{i}]", seen))
        except Ros2MessageError:
            dropped += 1
    return DetectionsReading(_stamp_ns(msg.header), tuple(dets), dropped)


def _detection(
    d: Any, class_index: Mapping[str, int], m: int, where: str, seen: set[int]
) -> Detection:
    if not (d.id.isascii() and d.id.isdigit()) or int(d.id) > 2**32 - 1:
        raise Ros2MessageError(f"{where}.id: {d.id!r} is not an object id 0..2³²−1")
    oid = int(d.id)
    if oid in seen:
        raise Ros2MessageError(f"{where}.id: duplicate object id {oid}")
    scores = np.full(m, np.nan)
    for r in d.results:
        c = class_index.get(r.hypothesis.class_id)
        if c is None or not np.isnan(scores[c]):
            raise Ros2MessageError(f"{where}.results: unknown or repeated class_id")
        scores[c] = r.hypothesis.score
    if len(d.results) != m or not np.isfinite(scores).all():
        raise Ros2MessageError(f"{where}.results: expected {m} finite scores, one per class")
    z_geo = _planar(d.results[0].pose.pose, f"{where}.results[0].pose")
    seen.add(oid)
    return Detection(oid, z_geo, scores)


def detections_message(
    types: Ros2Types,
    stamp_ns: int,
    frame_id: str,
    detections: Sequence[Detection],
    class_names: Sequence[str],
) -> bytes:
    """The inverse of :func:`read_detections` (what a robot's detector would publish): for tests,
    the docs' example and ``replay``-like tools."""
    head = header(types, stamp_ns, frame_id)
    out = []
    for d in detections:
        pose = types.build(
            "geometry_msgs/msg/PoseWithCovariance", pose=planar_pose(types, *d.z_geo)
        )
        results = [
            types.build(
                "vision_msgs/msg/ObjectHypothesisWithPose",
                hypothesis=types.build(
                    "vision_msgs/msg/ObjectHypothesis", class_id=name, score=float(score)
                ),
                pose=pose,
            )
            for name, score in zip(class_names, d.z_sem, strict=True)
        ]
        out.append(
            types.build(
                "vision_msgs/msg/Detection2D", header=head, results=results, id=str(d.object_id)
            )
        )
    return types.serialize(types.build(DETECTIONS, header=head, detections=out), DETECTIONS)


def odometry_reading_message(
    types: Ros2Types, stamp_ns: int, frame_id: str, child: str, pose: Array
) -> bytes:
    """A robot's own odometry message (pose only), as its driver would publish it."""
    pwc = types.build("geometry_msgs/msg/PoseWithCovariance", pose=planar_pose(types, *pose))
    msg = types.build(
        ODOMETRY, header=header(types, stamp_ns, frame_id), child_frame_id=child, pose=pwc
    )
    return types.serialize(msg, ODOMETRY)
