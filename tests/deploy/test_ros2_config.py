"""The ``[ros2]`` section of an agent config (docs/ros2.md): defaults, every field, and each
mistake one AgentConfigError naming the field."""

from __future__ import annotations

from pathlib import Path

import pytest

from agents.ros2.bridge import Ros2Settings
from deploy.operator.agent_config import AgentConfigError, load_agent_config
from sim.loader import load_scenario
from sim.robot_model import dump_robot_model

BASE = """\
[agent]
model = "model.toml"
start = [0.0, 0.0, 0.0]
roster = ["r1", "r2"]

[ros2]
"""


def _load(tmp_path: Path, ros2: str) -> Ros2Settings | None:
    (tmp_path / "model.toml").write_text(
        dump_robot_model(load_scenario("paper").robot_model()), encoding="utf-8"
    )
    path = tmp_path / "agent.toml"
    path.write_text(BASE + ros2, encoding="utf-8")
    return load_agent_config(path, "r1").ros2


def test_ros2_config_off_unless_enabled(tmp_path: Path) -> None:
    assert _load(tmp_path, "") is None
    assert _load(tmp_path, "enable = false\ndistro = 'jazzy'\n") is None


def test_ros2_config_defaults(tmp_path: Path) -> None:
    s = _load(tmp_path, "enable = true\n")
    assert s is not None
    assert (s.namespace, s.node, s.domain_id, s.distro) == ("/r1", "semfleet_r1", 0, "jazzy")
    assert (s.odometry_in, s.detections_in, s.class_names) == ("odom", "detections", ())
    assert s.connect == ("tcp/localhost:7447",)  # the robot's rmw_zenohd, as rmw_zenoh's nodes


def test_ros2_config_every_field(tmp_path: Path) -> None:
    s = _load(
        tmp_path,
        'enable = true\ndomain_id = 7\ndistro = "humble"\nnamespace = "/"\nnode = "slam"\n'
        'frame_id = "world"\nchild_frame_id = "r1/base"\nodometry_topic = "/fleet/r1/odom"\n'
        'pose_topic = "pose"\nmarkers_topic = "objects"\nodometry_in = ""\n'
        'detections_in = "det"\nclass_names = ["chair", "table"]\n',
    )
    assert s is not None
    assert s.domain_id == 7 and s.distro == "humble" and s.namespace == "/"
    assert s.odometry_topic == "/fleet/r1/odom" and s.class_names == ("chair", "table")
    assert not s.frames_in


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ('enable = true\ndistro = "iron"\n', "ros2.distro"),
        ("enable = true\ndomain_id = 300\n", "ros2.domain_id"),
        ('enable = true\nodometry_topic = "bad topic"\n', "ros2.odometry_topic"),
        ('enable = true\nnode = "a/b"\n', "ros2.node"),
        ('enable = true\nclass_names = ["only one"]\n', "ros2.class_names"),
        ('enable = true\nclass_names = ["a", "a"]\n', "ros2.class_names"),
        ("enable = true\ntopic = 1\n", "ros2"),
        ('enable = true\nmarkers_topic = "semfleet__objects"\n', "ros2.markers_topic"),
        ('enable = true\nnamespace = "/fleet/"\n', "ros2.namespace"),
        ('enable = true\npose_topic = "2d/pose"\n', "ros2.pose_topic"),
        ('enable = true\nnamespace = "/a__b"\n', "ros2.namespace"),
        ('enable = true\nconnect = ["tcp/10.0.0.5:7447"]\n', "ros2.connect"),
        ('enable = true\nconnect = ["localhost"]\n', "ros2.connect"),
    ],
)
def test_ros2_config_mistakes_name_the_field(tmp_path: Path, text: str, field: str) -> None:
    with pytest.raises(AgentConfigError) as err:
        _load(tmp_path, text)
    assert err.value.field.startswith(field), str(err.value)


def test_ros2_config_names_the_rule_a_name_breaks(tmp_path: Path) -> None:
    with pytest.raises(AgentConfigError, match="repeated underscores"):
        _load(tmp_path, 'enable = true\nmarkers_topic = "semfleet__objects"\n')
    with pytest.raises(AgentConfigError, match="longer than 247"):
        long = "n" * 240  # a valid namespace, whose topics are too long
        _load(tmp_path, f'enable = true\nnamespace = "/{long}"\n')


def test_ros2_config_default_names_from_a_robot_id_ros_refuses(tmp_path: Path) -> None:
    (tmp_path / "model.toml").write_text(
        dump_robot_model(load_scenario("paper").robot_model()), encoding="utf-8"
    )
    path = tmp_path / "agent.toml"
    path.write_text(BASE.replace('"r2"', '"r-2"') + "enable = true\n", encoding="utf-8")
    with pytest.raises(AgentConfigError, match=r"ros2.namespace: '/r-2' \(the default"):
        load_agent_config(path, "r-2")
    path.write_text(
        BASE.replace('"r2"', '"r-2"') + 'enable = true\nnamespace = "/r2"\n', encoding="utf-8"
    )
    with pytest.raises(AgentConfigError, match=r"ros2.node: .semfleet_r-2. \(the default"):
        load_agent_config(path, "r-2")


def test_ros2_config_connect_off_loopback_needs_insecure(tmp_path: Path) -> None:
    text = 'enable = true\nconnect = ["tcp/10.0.0.5:7447"]\n'
    (tmp_path / "model.toml").write_text(
        dump_robot_model(load_scenario("paper").robot_model()), encoding="utf-8"
    )
    path = tmp_path / "agent.toml"
    path.write_text(BASE.replace("[ros2]", "[zenoh]\ninsecure = true\n\n[ros2]") + text, "utf-8")
    s = load_agent_config(path, "r1").ros2
    assert s is not None and s.connect == ("tcp/10.0.0.5:7447",)
    path.write_text(BASE + "enable = true\nconnect = []\n", "utf-8")
    s = load_agent_config(path, "r1").ros2
    assert s is not None and s.connect == ()  # the agent's own session
