"""ROS 2 messages as CDR bytes, through rosbags' typestore of the chosen distro, and the belief
out as ``nav_msgs/msg/Odometry``, ``geometry_msgs/msg/PoseWithCovarianceStamped`` and
``visualization_msgs/msg/MarkerArray`` (a robot's readings in: ``agents.ros2.readings``). rosbags
is the optional extra ``ros2``: imported on first use, its absence one :class:`Ros2Unavailable`
sentence.

Covariances: a snapshot's are body-frame tangent covariances of (x, y, θ); ROS wants them in the
header's frame, (x, y, z, roll, pitch, yaw) row-major 6×6: the position block is rotated
(R Σ_xy Rᵀ, cross terms R Σ_xθ), and z, roll and pitch — which a planar robot does not estimate —
get :data:`UNUSED_VARIANCE` on the diagonal.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agents.ros2.wire import DISTROS, NO_TYPE_HASH
from estimator.snapshot import BeliefSnapshot

Array = NDArray[np.float64]

ODOMETRY = "nav_msgs/msg/Odometry"
POSE = "geometry_msgs/msg/PoseWithCovarianceStamped"
MARKERS = "visualization_msgs/msg/MarkerArray"
DETECTIONS = "vision_msgs/msg/Detection2DArray"
UNUSED_VARIANCE = 1e6  # m², rad²: the axes a planar belief does not estimate
ELLIPSE_SIGMA = math.sqrt(5.991)  # the 95 % ellipse of a 2-D Gaussian (χ² with 2 dof)
ELLIPSE_POINTS = 33
INSTALL_HINT = "ROS 2 interop needs rosbags: pip install 'semfleet[ros2]'"

# vision_msgs (ros-perception/vision_msgs, branch ros2 at e77fa2d, comments left out): not in
# rosbags' stores, registered from these definitions (their RIHS01 hash is computed from them).
VISION_MSGS = {
    "vision_msgs/msg/Point2D": "float64 x\nfloat64 y\n",
    "vision_msgs/msg/Pose2D": "vision_msgs/Point2D position\nfloat64 theta\n",
    "vision_msgs/msg/BoundingBox2D": "vision_msgs/Pose2D center\nfloat64 size_x\nfloat64 size_y\n",
    "vision_msgs/msg/ObjectHypothesis": "string class_id\nfloat64 score\n",
    "vision_msgs/msg/ObjectHypothesisWithPose": (
        "vision_msgs/ObjectHypothesis hypothesis\ngeometry_msgs/PoseWithCovariance pose\n"
    ),
    "vision_msgs/msg/Detection2D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
        "vision_msgs/BoundingBox2D bbox\nstring id\n"
    ),
    "vision_msgs/msg/Detection2DArray": (
        "std_msgs/Header header\nvision_msgs/Detection2D[] detections\n"
    ),
    "vision_msgs/msg/BoundingBox3D": "geometry_msgs/Pose center\ngeometry_msgs/Vector3 size\n",
    "vision_msgs/msg/Detection3D": (
        "std_msgs/Header header\nvision_msgs/ObjectHypothesisWithPose[] results\n"
        "vision_msgs/BoundingBox3D bbox\nstring id\n"
    ),
    "vision_msgs/msg/Detection3DArray": (
        "std_msgs/Header header\nvision_msgs/Detection3D[] detections\n"
    ),
}
_DTYPES = {
    "bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
    "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
    "int64": np.int64, "uint64": np.uint64, "float32": np.float32, "float64": np.float64,
}  # fmt: skip


class Ros2Unavailable(RuntimeError):
    """rosbags is not installed."""


class Ros2MessageError(ValueError):
    """CDR bytes that are not the message they claim to be, or a message semfleet cannot use
    (names the field)."""


class Ros2Types:
    """One distro's typestore (rosbags) with vision_msgs registered."""

    def __init__(self, distro: str) -> None:
        if distro not in DISTROS:
            raise ValueError(f"ROS distro {distro!r} (known: {', '.join(DISTROS)})")
        try:
            from rosbags.typesys import Stores, get_types_from_msg, get_typestore
        except ImportError:
            raise Ros2Unavailable(INSTALL_HINT) from None
        store = {"humble": Stores.ROS2_HUMBLE, "jazzy": Stores.ROS2_JAZZY}[distro]
        self.distro = distro
        self.store = get_typestore(store)
        extra: dict[str, Any] = {}
        for name, text in VISION_MSGS.items():
            extra.update(get_types_from_msg(text, name))
        self.store.register(extra)

    def type_hash(self, type_name: str) -> str:
        """``RIHS01_<sha256 hex>``, or Humble's ``TypeHashNotSupported``."""
        if self.distro == "humble":
            return NO_TYPE_HASH
        return str(self.store.hash_rihs01(type_name))

    def build(self, type_name: str, **fields: Any) -> Any:
        """A message of ``type_name``: ``fields`` as given, every other field zero or empty."""
        _, defs = self.store.fielddefs[type_name]
        values = {name: self._default(spec) for name, spec in defs if name not in fields}
        return self.store.types[type_name](**values, **fields)

    def _default(self, spec: tuple[Any, Any]) -> Any:
        kind, detail = spec
        kind = int(kind)
        if kind == 1:  # a base type
            base = detail[0]
            if base == "string":
                return ""
            return _DTYPES[base](0).item()
        if kind == 2:  # a message
            return self.build(detail)
        (inner_kind, inner), length = detail
        if int(inner_kind) == 1 and inner[0] != "string":
            return np.zeros(length if int(kind) == 3 else 0, dtype=_DTYPES[inner[0]])
        if int(kind) == 3:
            return [self._default((inner_kind, inner)) for _ in range(length)]
        return []

    def serialize(self, message: Any, type_name: str) -> bytes:
        return bytes(self.store.serialize_cdr(message, type_name))

    def deserialize(self, data: bytes, type_name: str) -> Any:
        """The message in ``data``; every failure of the third-party decoder on untrusted bytes
        (struct, index, unicode, numpy errors alike) one :class:`Ros2MessageError`."""
        try:
            return self.store.deserialize_cdr(data, type_name)
        except Exception as exc:  # the boundary: any decoder error on these bytes is a bad input
            raise Ros2MessageError(f"{type_name}: not valid CDR ({type(exc).__name__})") from None


@functools.cache
def types_for(distro: str) -> Ros2Types:
    return Ros2Types(distro)


# --------------------------------------------------------------------------- belief out


def _stamp(types: Ros2Types, stamp_ns: int) -> Any:
    return types.build(
        "builtin_interfaces/msg/Time", sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9
    )


def header(types: Ros2Types, stamp_ns: int, frame_id: str) -> Any:
    return types.build("std_msgs/msg/Header", stamp=_stamp(types, stamp_ns), frame_id=frame_id)


def planar_pose(types: Ros2Types, x: float, y: float, theta: float) -> Any:
    point = types.build("geometry_msgs/msg/Point", x=float(x), y=float(y), z=0.0)
    q = types.build(
        "geometry_msgs/msg/Quaternion", x=0.0, y=0.0, z=math.sin(theta / 2), w=math.cos(theta / 2)
    )
    return types.build("geometry_msgs/msg/Pose", position=point, orientation=q)


def covariance_6x6(pose: Array, cov: Array) -> Array:
    """(36,) row-major (x, y, z, roll, pitch, yaw) covariance in the world frame of a planar pose
    (3,) with a body-frame tangent covariance (3, 3)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    jac = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    world = jac @ cov @ jac.T
    out = np.diag([0.0, 0.0, UNUSED_VARIANCE, UNUSED_VARIANCE, UNUSED_VARIANCE, 0.0])
    axes = [0, 1, 5]
    out[np.ix_(axes, axes)] = (world + world.T) / 2
    return out.reshape(36)


def best_hypothesis(snapshot: BeliefSnapshot) -> int:
    return int(np.argmax(snapshot.weights))


def odometry_message(
    types: Ros2Types, snapshot: BeliefSnapshot, stamp_ns: int, frame_id: str, child: str
) -> bytes:
    """The robot's pose in the most probable hypothesis, its covariance, zero twist of unknown
    (:data:`UNUSED_VARIANCE`) covariance."""
    h = best_hypothesis(snapshot)
    pose = snapshot.robot_pose[h]
    pwc = types.build(
        "geometry_msgs/msg/PoseWithCovariance",
        pose=planar_pose(types, *pose),
        covariance=covariance_6x6(pose, snapshot.robot_cov[h]),
    )
    twist = types.build(
        "geometry_msgs/msg/TwistWithCovariance", covariance=np.eye(6).reshape(36) * UNUSED_VARIANCE
    )
    msg = types.build(
        ODOMETRY,
        header=header(types, stamp_ns, frame_id),
        child_frame_id=child,
        pose=pwc,
        twist=twist,
    )
    return types.serialize(msg, ODOMETRY)


def pose_message(types: Ros2Types, snapshot: BeliefSnapshot, stamp_ns: int, frame_id: str) -> bytes:
    h = best_hypothesis(snapshot)
    pose = snapshot.robot_pose[h]
    pwc = types.build(
        "geometry_msgs/msg/PoseWithCovariance",
        pose=planar_pose(types, *pose),
        covariance=covariance_6x6(pose, snapshot.robot_cov[h]),
    )
    msg = types.build(POSE, header=header(types, stamp_ns, frame_id), pose=pwc)
    return types.serialize(msg, POSE)


def class_marginals(snapshot: BeliefSnapshot, num_classes: int) -> Array:
    """(n, M): p(class of object j = c) = Σ_h w_h [classes[h, j] = c], or the snapshot's
    per-object ``class_probs`` when it has them (:meth:`BeliefSnapshot.marginals`)."""
    return snapshot.marginals(num_classes)


def ellipse_points(mean: Array, cov_xy: Array) -> Array:
    """(ELLIPSE_POINTS, 2): the closed 95 % ellipse of a world-frame position covariance (2, 2)."""
    vals, vecs = np.linalg.eigh((cov_xy + cov_xy.T) / 2)
    radii = ELLIPSE_SIGMA * np.sqrt(np.clip(vals, 0.0, None))
    t = np.linspace(0.0, 2 * math.pi, ELLIPSE_POINTS)
    circle = np.stack([np.cos(t), np.sin(t)], axis=1)
    return np.asarray(mean[:2] + (circle * radii) @ vecs.T)


def markers_message(
    types: Ros2Types,
    snapshot: BeliefSnapshot,
    stamp_ns: int,
    frame_id: str,
    namespace: str,
    class_names: Sequence[str],
) -> bytes:
    """Per object of the most probable hypothesis: a LINE_STRIP, its 95 % position ellipse, and
    a TEXT_VIEW_FACING marker ``"<class> <p>"`` with the most likely class by the marginal over
    every hypothesis, both with the object's id in namespaces ``<namespace>/ellipse`` and
    ``<namespace>/class``."""
    h = best_hypothesis(snapshot)
    marginals = class_marginals(snapshot, len(class_names))
    head = header(types, stamp_ns, frame_id)
    markers = []
    for j, oid in enumerate(snapshot.object_ids):
        pose = snapshot.object_pose[h, j]
        c, s = math.cos(pose[2]), math.sin(pose[2])
        rot = np.array([[c, -s], [s, c]])
        cov_xy = rot @ snapshot.object_cov[h, j, :2, :2] @ rot.T
        points = [
            types.build("geometry_msgs/msg/Point", x=float(px), y=float(py), z=0.0)
            for px, py in ellipse_points(pose, cov_xy)
        ]
        best = int(np.argmax(marginals[j]))
        colour = types.build("std_msgs/msg/ColorRGBA", r=0.1, g=0.6, b=1.0, a=1.0)
        markers.append(
            _marker(
                types, head, f"{namespace}/ellipse", int(oid), 4,  # LINE_STRIP
                planar_pose(types, 0.0, 0.0, 0.0), (0.03, 0.0, 0.0), colour, points=points,
            )
        )  # fmt: skip
        markers.append(
            _marker(
                types, head, f"{namespace}/class", int(oid), 9,  # TEXT_VIEW_FACING
                planar_pose(types, pose[0], pose[1], 0.0), (0.0, 0.0, 0.25), colour,
                text=f"{class_names[best]} {marginals[j, best]:.2f}",
            )
        )  # fmt: skip
    return types.serialize(types.build(MARKERS, markers=markers), MARKERS)


def _marker(
    types: Ros2Types,
    head: Any,
    ns: str,
    marker_id: int,
    kind: int,
    pose: Any,
    scale: tuple[float, float, float],
    colour: Any,
    **fields: Any,
) -> Any:
    """One ADD ``visualization_msgs/msg/Marker`` of type ``kind``."""
    x, y, z = scale
    return types.build(
        "visualization_msgs/msg/Marker",
        header=head,
        ns=ns,
        id=marker_id,
        type=kind,
        action=0,  # ADD
        pose=pose,
        scale=types.build("geometry_msgs/msg/Vector3", x=x, y=y, z=z),
        color=colour,
        **fields,
    )
