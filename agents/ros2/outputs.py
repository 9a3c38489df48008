"""The belief out as what ROS 2's tools read besides poses and markers (docs/ros2.md, "The belief
out"): the map → odom correction on ``/tf`` (``tf2_msgs/msg/TFMessage``, REP 105), the estimated
trajectory (``nav_msgs/msg/Path``) and the object map machine-readable
(``vision_msgs/msg/Detection3DArray``: every class's probability, the pose with its covariance).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from agents.ros2.messages import (
    Array,
    Ros2Types,
    best_hypothesis,
    class_marginals,
    covariance_6x6,
    header,
    planar_pose,
)
from estimator.models.se2 import compose, inverse
from estimator.snapshot import BeliefSnapshot

TF = "tf2_msgs/msg/TFMessage"
PATH = "nav_msgs/msg/Path"
OBJECTS = "vision_msgs/msg/Detection3DArray"


def map_to_odom(map_pose: Array, odom_pose: Array) -> Array:
    """(3,): the pose of the robot's odom frame in the map, ``T_map_base ∘ T_odom_base⁻¹``: the
    correction that, composed with the robot's own odom → base_link, puts base_link where the
    belief has it (REP 105: a localiser publishes map → odom, never map → base_link)."""
    return compose(np.asarray(map_pose, dtype=float), inverse(np.asarray(odom_pose, dtype=float)))


def tf_message(
    types: Ros2Types, stamp_ns: int, map_frame: str, odom_frame: str, correction: Array
) -> bytes:
    """One ``geometry_msgs/TransformStamped``, ``map_frame`` → ``odom_frame``: ``correction``
    (3,) as a planar transform (z 0, a rotation about z)."""
    x, y, theta = (float(v) for v in correction)
    transform = types.build(
        "geometry_msgs/msg/Transform",
        translation=types.build("geometry_msgs/msg/Vector3", x=x, y=y, z=0.0),
        rotation=types.build(
            "geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(theta / 2),
            w=math.cos(theta / 2),
        ),
    )  # fmt: skip
    stamped = types.build(
        "geometry_msgs/msg/TransformStamped",
        header=header(types, stamp_ns, map_frame),
        child_frame_id=odom_frame,
        transform=transform,
    )
    return types.serialize(types.build(TF, transforms=[stamped]), TF)


def path_message(
    types: Ros2Types, poses: Sequence[tuple[int, Array]], stamp_ns: int, frame_id: str
) -> bytes:
    """The trajectory ``poses`` — (stamp ns, pose (3,)) per step, oldest first — as a Path in
    ``frame_id`` stamped ``stamp_ns``."""
    stamped = [
        types.build(
            "geometry_msgs/msg/PoseStamped",
            header=header(types, t, frame_id),
            pose=planar_pose(types, *pose),
        )
        for t, pose in poses
    ]
    msg = types.build(PATH, header=header(types, stamp_ns, frame_id), poses=stamped)
    return types.serialize(msg, PATH)


def objects_message(
    types: Ros2Types,
    snapshot: BeliefSnapshot,
    stamp_ns: int,
    frame_id: str,
    class_names: Sequence[str],
) -> bytes:
    """Per object of the most probable hypothesis a Detection3D: ``id`` the object id; one
    result per class, in the model's order, ``class_id`` its name and ``score`` its marginal
    probability over every hypothesis (they sum to 1), each with the object's pose and its
    covariance in the header's frame (as the robot pose's, ``covariance_6x6``); ``bbox`` centred
    on the object with size 0 (a planar belief estimates no extent)."""
    h = best_hypothesis(snapshot)
    marginals = class_marginals(snapshot, len(class_names))
    head = header(types, stamp_ns, frame_id)
    detections = []
    for j, oid in enumerate(snapshot.object_ids):
        pose = snapshot.object_pose[h, j]
        pwc = types.build(
            "geometry_msgs/msg/PoseWithCovariance",
            pose=planar_pose(types, *pose),
            covariance=covariance_6x6(pose, snapshot.object_cov[h, j]),
        )
        results = [
            types.build(
                "vision_msgs/msg/ObjectHypothesisWithPose",
                hypothesis=types.build(
                    "vision_msgs/msg/ObjectHypothesis", class_id=name, score=float(p)
                ),
                pose=pwc,
            )
            for name, p in zip(class_names, marginals[j], strict=True)
        ]
        bbox = types.build("vision_msgs/msg/BoundingBox3D", center=planar_pose(types, *pose))
        detections.append(
            types.build(
                "vision_msgs/msg/Detection3D", header=head, results=results, bbox=bbox,
                id=str(int(oid)),
            )
        )  # fmt: skip
    return types.serialize(types.build(OBJECTS, header=head, detections=detections), OBJECTS)
