"""The ``[ros2]`` section of an agent config (docs/ros2.md), read and validated into
:class:`~agents.ros2.bridge.Ros2Settings`; every mistake a failure of the section's field
reader, which names the file and the field."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from agents.ros2.bridge import ROS2_ROUTER, Ros2Settings
from agents.ros2.messages import Ros2Unavailable, types_for
from agents.ros2.wire import DISTROS, resolve_topic, ros_name_problem
from agents.transport.zenoh_transport import ZenohSettings
from sim.loader import FieldReader

_ROS2_TOPICS = (
    "odometry_topic", "pose_topic", "markers_topic", "path_topic", "objects_topic", "tf_topic",
    "odometry_in", "detections_in",
)  # fmt: skip
_ROS2_KEYS = {
    "enable", "domain_id", "distro", "namespace", "node", "frame_id", "child_frame_id",
    "class_names", "connect", *_ROS2_TOPICS,
}  # fmt: skip
MAX_DOMAIN_ID = 232  # the highest ROS 2 domain id


def read_ros2(r: FieldReader, robot: str, num_classes: int, insecure: bool) -> Ros2Settings | None:
    """``[ros2]`` (docs/ros2.md): None unless ``enable = true``; the ``rosbags`` extra must then
    be installed. Names follow ROS 2's naming rules (:func:`ros_name_problem`), the default
    namespace and node made of the robot id included; ``connect`` (the robot's rmw_zenohd) stays
    on loopback unless the agent's ``[zenoh] insecure = true``."""
    r.check_keys(_ROS2_KEYS)
    if not (r.boolean("enable") if r.has("enable") else False):
        return None
    distro = r.string("distro") if r.has("distro") else "jazzy"
    if distro not in DISTROS:
        raise r.fail("distro", f"{distro!r} (known: {', '.join(DISTROS)})")
    names = {"namespace": f"/{robot}", "node": f"semfleet_{robot}"}
    given = set()
    for name in ("namespace", "node", *_ROS2_TOPICS):
        if r.has(name):
            names[name] = r.string(name)
            given.add(name)
    for name, value in names.items():
        if (name in ("odometry_in", "detections_in") and value == "") or (
            name == "namespace" and value == "/"
        ):
            continue
        problem = ros_name_problem(value)
        if problem is None and name == "node" and "/" in value:
            problem = "has a '/' (a node name is one token)"
        if problem is not None:
            where = "" if name in given else f" (the default, from the robot id {robot!r})"
            raise r.fail(name, f"{value!r}{where} is not a ROS 2 name: it {problem}")
    classes: tuple[str, ...] = ()
    if r.has("class_names"):
        field = r.array("class_names")
        classes = tuple(field.string(i) for i in range(len(field.raw)))
        if len(classes) != num_classes or len(set(classes)) != num_classes:
            raise r.fail(
                "class_names", f"expected {num_classes} distinct names (the model's classes)"
            )
    connect: tuple[str, ...] = (ROS2_ROUTER,)
    if r.has("connect"):
        field = r.array("connect")
        connect = tuple(field.string(i) for i in range(len(field.raw)))
        for e in connect:
            if "/" not in e:
                raise r.fail("connect", f"bad endpoint {e!r} (e.g. {ROS2_ROUTER})")
    exposed = ZenohSettings(connect=connect).off_loopback()
    if exposed and not insecure:
        raise r.fail(
            "connect",
            f"{', '.join(exposed)} is not on loopback: the ROS 2 session has no TLS (run it "
            "against the robot's own rmw_zenohd, or set [zenoh] insecure = true)",
        )
    try:
        types_for(distro)
    except Ros2Unavailable as exc:
        raise r.fail("enable", str(exc)) from None
    settings = Ros2Settings(
        domain_id=r.integer("domain_id", 0, MAX_DOMAIN_ID) if r.has("domain_id") else 0,
        distro=distro,
        frame_id=r.string("frame_id") if r.has("frame_id") else "map",
        child_frame_id=r.string("child_frame_id") if r.has("child_frame_id") else "base_link",
        class_names=classes,
        connect=connect,
        **names,
    )
    for name in _ROS2_TOPICS:  # each topic resolved under the namespace (its length)
        full = resolve_topic(settings.namespace, getattr(settings, name))
        problem = ros_name_problem(full) if getattr(settings, name) else None
        if problem is not None:
            raise r.fail(name, f"{full!r} is not a ROS 2 topic name: it {problem}")
    return settings


def simulation_table(domain_id: int, distro: str, connect: str) -> dict[str, Any]:
    """The ``[ros2]`` table ``launch --ros2`` writes into every agent config: the belief out on
    ``domain_id`` through the router ``connect``; frames from ROS 2 off (``odometry_in`` and
    ``detections_in`` empty), since a simulation's frames come from its conductor."""
    return {
        "enable": True,
        "domain_id": domain_id,
        "distro": distro,
        "connect": [connect],
        "odometry_in": "",
        "detections_in": "",
    }


def check_table(table: Mapping[str, Any], label: str, robot: str, num_classes: int) -> Ros2Settings:
    """``table`` read as ``robot``'s agent will read it (:func:`read_ros2`, its loopback rule
    included): a :class:`~sim.scenario.ScenarioError` naming ``label`` and the field, before any
    agent starts."""
    settings = read_ros2(FieldReader(label, dict(table), "ros2"), robot, num_classes, False)
    assert settings is not None  # enable = true
    return settings
