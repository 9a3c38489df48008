"""The agent's ROS 2 side, sans-I/O: what to publish for an estimate (keys, CDR payloads,
attachments), which tokens to hold and keys to hear, and the frames a robot's ROS 2 odometry and
detections make. The asyncio shell (``agents.runtime.Agent``) does the I/O.

Frames in (docs/ros2.md): one step per detections message. A detections message stamped t waits
until odometry stamped ≥ t has arrived, then takes the newest odometry pose stamped ≤ t (the
oldest held if none is); the frame's odometry is the SE(2) motion from the pose the previous step
took to that one (step 1: from the first odometry pose heard, the robot's configured start).
"""

from __future__ import annotations

import collections
import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from agents.ros2 import messages as msgs
from agents.ros2 import outputs, readings
from agents.ros2.wire import (
    DEFAULT_QOS,
    DISTROS,
    TF_QOS,
    GraphNode,
    encode_attachment,
    endpoint_gid,
    resolve_topic,
    topic_key,
    topic_key_any_hash,
)
from agents.transport.base import Transport
from estimator.models import SensorFrame
from estimator.models.se2 import between
from protocol.errors import LocalProtocolError, ProtocolError
from protocol.estimate import EstimateMessage, decode_estimate
from protocol.frames import FrameLimits, encode_frame

log = logging.getLogger(__name__)

MAX_PENDING = 64  # detections messages waiting for odometry
MAX_ODOMETRY = 1024  # odometry readings held
MAX_STAMPS = 256  # steps whose detections stamp is remembered (to stamp their estimate)
MAX_PATH = 1000  # steps of the estimated trajectory in each Path message
# Where a ROS 2 node with rmw_zenoh finds its router (rmw_zenoh's default session config).
ROS2_ROUTER = "tcp/localhost:7447"


@dataclass(frozen=True, slots=True)
class Ros2Settings:
    """The ``[ros2]`` section of an agent config (docs/agents.md). Relative topic names resolve
    under ``namespace``; an empty ``odometry_in`` or ``detections_in`` turns frames from ROS 2
    off. ``class_names``: the M names detections use as ``class_id`` and markers show (default
    ``"0"`` … ``"M-1"``). ``connect``: the robot's router (``rmw_zenohd``) that the ROS 2 side
    dials as a Zenoh client, in a session of its own; empty: the ROS 2 side shares the agent's
    session (a ROS graph that session reaches directly)."""

    namespace: str
    node: str
    domain_id: int = 0
    distro: str = "jazzy"
    frame_id: str = "map"
    child_frame_id: str = "base_link"
    odometry_topic: str = "semfleet/odometry"
    pose_topic: str = "semfleet/pose"
    markers_topic: str = "semfleet/objects"
    path_topic: str = "semfleet/path"
    objects_topic: str = "semfleet/detections"
    tf_topic: str = "/tf"
    odometry_in: str = "odom"
    detections_in: str = "detections"
    class_names: tuple[str, ...] = ()
    connect: tuple[str, ...] = (ROS2_ROUTER,)

    def __post_init__(self) -> None:
        if self.distro not in DISTROS:
            raise ValueError(f"ROS distro {self.distro!r} (known: {', '.join(DISTROS)})")

    @property
    def frames_in(self) -> bool:
        return bool(self.odometry_in and self.detections_in)


@dataclass(frozen=True, slots=True)
class Sample:
    """One Zenoh put as rmw_zenoh makes it."""

    key: str
    payload: bytes
    attachment: bytes


@dataclass(slots=True)
class _Publication:
    type_name: str
    key: str
    token: str
    gid: bytes
    sequence: int = 0


@dataclass(slots=True)
class Ros2Counters:
    samples_sent: int = 0
    frames_built: int = 0
    malformed: int = 0
    detections_dropped: int = 0


@dataclass(slots=True)
class _Inbound:
    odometry: collections.deque[readings.OdometryReading] = field(
        default_factory=lambda: collections.deque(maxlen=MAX_ODOMETRY)
    )
    pending: collections.deque[readings.DetectionsReading] = field(
        default_factory=collections.deque
    )
    previous: np.ndarray | None = None


@dataclass(frozen=True, slots=True)
class Ros2Link:
    """A bridge, how its samples are put on Zenoh (``publish(key, payload, attachment)``) and the
    transport its tokens and subscriptions go on; ``own_session``: that transport is the ROS 2
    side's own (``Ros2Settings.connect``), which the runtime opens — retrying until the robot's
    router answers — and closes, rather than the agent's."""

    bridge: Ros2Bridge
    publish: Callable[[str, bytes, bytes], None]
    transport: Transport
    own_session: bool = False


class Ros2Bridge:
    """``robot``'s ROS 2 graph presence (node ``settings.node`` in Zenoh session ``zid``), its
    publications and, if on, its frames from ROS 2 starting at step ``next_step``."""

    def __init__(self, settings: Ros2Settings, robot: str, num_classes: int, zid: str) -> None:
        self.settings = settings
        self.robot = robot
        self.types = msgs.types_for(settings.distro)
        names = settings.class_names or tuple(str(c) for c in range(num_classes))
        if len(names) != num_classes:
            raise ValueError(f"{len(names)} class names for {num_classes} classes")
        self.class_names = names
        self.class_index = {n: c for c, n in enumerate(names)}
        self.counters = Ros2Counters()
        self.next_step = 1
        self._inbound = _Inbound()
        self._stamps: dict[int, int] = {}
        self._odometry_at: dict[int, readings.OdometryReading] = {}  # the pose each step took
        self._path: dict[int, tuple[int, np.ndarray]] = {}  # step → (stamp, estimated pose)
        s = settings
        self.graph = GraphNode(s.domain_id, zid, 0, s.namespace, s.node)
        self._tokens = [self.graph.node_token()]
        self.publications: dict[str, _Publication] = {}
        eid = 1
        for name, topic, type_name, qos in (
            ("odometry", s.odometry_topic, msgs.ODOMETRY, DEFAULT_QOS),
            ("pose", s.pose_topic, msgs.POSE, DEFAULT_QOS),
            ("markers", s.markers_topic, msgs.MARKERS, DEFAULT_QOS),
            ("path", s.path_topic, outputs.PATH, DEFAULT_QOS),
            ("objects", s.objects_topic, outputs.OBJECTS, DEFAULT_QOS),
            ("tf", s.tf_topic, outputs.TF, TF_QOS),
        ):
            full = resolve_topic(s.namespace, topic)
            th = self.types.type_hash(type_name)
            token = self.graph.endpoint_token(eid, "MP", full, type_name, th, qos)
            key = topic_key(s.domain_id, full, type_name, th)
            self.publications[name] = _Publication(type_name, key, token, endpoint_gid(token))
            self._tokens.append(token)
            eid += 1
        self.inputs: dict[str, str] = {}  # subscription expression → message type
        if s.frames_in:
            for topic, type_name in (
                (s.odometry_in, msgs.ODOMETRY),
                (s.detections_in, msgs.DETECTIONS),
            ):
                full = resolve_topic(s.namespace, topic)
                th = self.types.type_hash(type_name)
                self._tokens.append(self.graph.endpoint_token(eid, "MS", full, type_name, th))
                self.inputs[topic_key_any_hash(s.domain_id, full, type_name)] = type_name
                eid += 1

    def tokens(self) -> list[str]:
        """The liveliness tokens to hold: the node, each publisher, each subscription."""
        return list(self._tokens)

    def counter_values(self) -> dict[str, int]:
        return {f"ros_{name}": n for name, n in dataclasses.asdict(self.counters).items()}

    # -- out --------------------------------------------------------------------------------

    def on_estimate(self, payload: bytes, now_ns: int) -> list[Sample]:
        """The samples of an estimate's distributed belief, stamped with the detections stamp of
        its step when that step came from ROS 2, else ``now_ns``. ``/tf`` (map → the robot's
        odom frame) only for a step built from the robot's ROS 2 odometry, which owns
        odom → base_link; the path holds the last ``MAX_PATH`` steps' estimated poses."""
        try:
            estimate = decode_estimate(payload)
        except ProtocolError as exc:  # our own bytes: a bug, not an input
            raise AssertionError(f"own estimate does not decode: {exc}") from exc
        return self.samples_of(estimate, now_ns)

    def samples_of(self, estimate: EstimateMessage, now_ns: int) -> list[Sample]:
        """:meth:`on_estimate` of an estimate already decoded (a recording of a run)."""
        snap = estimate.beliefs["distributed"]
        stamp = self._stamps.get(estimate.k, now_ns)
        s, t = self.settings, self.types
        pose = snap.robot_pose[msgs.best_hypothesis(snap)]
        self._path[estimate.k] = (stamp, pose)
        while len(self._path) > MAX_PATH:
            del self._path[min(self._path)]
        path = [self._path[k] for k in sorted(self._path)]
        payloads = {
            "odometry": msgs.odometry_message(t, snap, stamp, s.frame_id, s.child_frame_id),
            "pose": msgs.pose_message(t, snap, stamp, s.frame_id),
            "markers": msgs.markers_message(
                t, snap, stamp, s.frame_id, f"semfleet/{self.robot}", self.class_names
            ),
            "path": outputs.path_message(t, path, stamp, s.frame_id),
            "objects": outputs.objects_message(t, snap, stamp, s.frame_id, self.class_names),
        }
        odom = self._odometry_at.get(estimate.k)
        if odom is not None:
            correction = outputs.map_to_odom(pose, odom.pose)
            payloads["tf"] = outputs.tf_message(t, stamp, s.frame_id, odom.frame_id, correction)
        out = []
        for name, data in payloads.items():
            pub = self.publications[name]
            pub.sequence += 1
            out.append(Sample(pub.key, data, encode_attachment(pub.sequence, now_ns, pub.gid)))
        self.counters.samples_sent += len(out)
        return out

    # -- in ---------------------------------------------------------------------------------

    def input_type(self, key: str) -> str | None:
        """The message type a received key carries, or None if it is not one of our inputs."""
        parts = key.split("/")
        if len(parts) < 3:
            return None
        wanted = "/".join(parts[:-1]) + "/*"
        return self.inputs.get(wanted)

    def on_input(self, key: str, payload: bytes) -> list[bytes]:
        """The encoded frames a received odometry or detections sample completes (usually none
        or one); a malformed sample is counted and dropped, and so is a frame the frame codec
        refuses (e.g. more detections than it carries)."""
        type_name = self.input_type(key)
        if type_name is None:
            return []
        try:
            if type_name == msgs.ODOMETRY:
                self._inbound.odometry.append(readings.read_odometry(self.types, payload))
            else:
                reading = readings.read_detections(self.types, payload, self.class_index)
                self.counters.detections_dropped += reading.dropped
                if len(self._inbound.pending) >= MAX_PENDING:
                    self._inbound.pending.popleft()
                    self.counters.detections_dropped += 1
                self._inbound.pending.append(reading)
        except msgs.Ros2MessageError as exc:
            self.counters.malformed += 1
            log.debug("%s: dropped a ROS 2 sample on %s: %s", self.robot, key, exc)
            return []
        out = []
        for frame in self._assemble():
            try:
                out.append(encode_frame(frame, FrameLimits(num_classes=len(self.class_names))))
            except LocalProtocolError as exc:
                self.counters.malformed += 1
                log.debug("%s: frame %d from ROS 2 refused: %s", self.robot, frame.k, exc)
        return out

    def _assemble(self) -> list[SensorFrame]:
        inbound, frames = self._inbound, []
        while inbound.pending and inbound.odometry:
            det = inbound.pending[0]
            if max(o.stamp_ns for o in inbound.odometry) < det.stamp_ns:
                break  # the odometry of its time has not arrived yet
            inbound.pending.popleft()
            before = [o for o in inbound.odometry if o.stamp_ns <= det.stamp_ns]
            odo = before[-1] if before else inbound.odometry[0]
            previous = inbound.odometry[0].pose if inbound.previous is None else inbound.previous
            inbound.previous = odo.pose
            k = self.next_step
            self.next_step += 1
            self._stamps[k] = det.stamp_ns
            self._stamps.pop(k - MAX_STAMPS, None)
            self._odometry_at[k] = odo
            self._odometry_at.pop(k - MAX_STAMPS, None)
            motion = between(previous, odo.pose)
            # A robot knows no true pose: all NaN, which the frame codec sends as nil.
            frames.append(SensorFrame(self.robot, k, motion, det.detections, np.full(3, np.nan)))
            self.counters.frames_built += 1
        return frames
