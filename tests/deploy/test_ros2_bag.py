"""A run's rosbag2 recording (`--ros2-bag`, issue 46 item 12) as the tools that open it read it:

- Foxglove, through its own MCAP reader and ROS 2 decoder (the PyPI packages ``mcap`` and
  ``mcap-ros2-support``): the ``ros2`` profile, every message decoded from the message
  definitions stored in the file alone (vision_msgs included, which no ROS install need have),
  to the fields rosbags' typestore reads from the same bytes;
- ``ros2 bag play`` of the distro asked for: Jazzy's rosbag2 writes and reads metadata version 9,
  whose topics' ``offered_qos_profiles`` are a YAML list with named enums; Humble's reads any
  version without checking it but parses ``offered_qos_profiles`` as a YAML *string* of QoS with
  integer enums, and its player builds each publisher from that (rosbag2 humble,
  ``metadata_io.cpp`` and ``rosbag2_transport/qos.cpp``). A Humble bag is therefore version 8.
  No ROS 2 with rosbag2 installs here (not on PyPI or Debian), so these are checked against
  those parsers' rules, not by running them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from agents.ros2.bridge import Ros2Settings
from agents.ros2.outputs import OBJECTS, PATH
from deploy.launch.ros2_bag import write_bag
from estimator.snapshot import BeliefSnapshot
from protocol.estimate import EstimateMessage

pytest.importorskip("rosbags")
STEPS = 4
START_NS = 1_700_000_000 * 10**9


def _estimates(robots: tuple[str, ...]) -> dict[tuple[str, int], EstimateMessage]:
    rng = np.random.default_rng(5)
    out = {}
    for r in robots:
        for k in range(1, STEPS + 1):
            p = rng.dirichlet(np.ones(3))
            snap = BeliefSnapshot(
                object_ids=(2, 7),
                weights=np.array([1.0]),
                classes=np.array([[0, 2]], dtype=np.int64),
                robot_pose=np.array([[0.5 * k, 0.1 * k, 0.2]]),
                robot_cov=np.eye(3)[None] * 0.01,
                object_pose=np.array([[[2.0, 2.0, 0.0], [3.0, -1.0, 1.0]]]),
                object_cov=np.eye(3)[None, None].repeat(2, axis=1) * 0.02,
                class_probs=np.array([p, p[::-1]]),
            )
            out[r, k] = EstimateMessage(r, k, {"distributed": snap})
    return out


def _bag(tmp_path: Path, distro: str) -> Path:
    robots = ("r1", "r2")
    settings = {
        r: Ros2Settings(namespace=f"/{r}", node=f"semfleet_{r}", distro=distro) for r in robots
    }
    path = tmp_path / "bag"
    counts = write_bag(path, settings, 3, _estimates(robots), START_NS, 0.5)
    assert set(counts.values()) == {STEPS}
    return path


@pytest.mark.parametrize(("distro", "version"), [("humble", 8), ("jazzy", 9)])
def test_bag_metadata_is_what_the_distros_ros2_bag_play_parses(
    tmp_path: Path, distro: str, version: int
) -> None:
    meta = yaml.safe_load((_bag(tmp_path, distro) / "metadata.yaml").read_text())
    info = meta["rosbag2_bagfile_information"]
    assert info["version"] == version
    assert info["storage_identifier"] == "mcap"
    topics = info["topics_with_message_count"]
    assert len(topics) == 10
    for t in topics:
        qos = t["topic_metadata"]["offered_qos_profiles"]
        if distro == "humble":
            # Humble: `node["offered_qos_profiles"].as<std::string>()`, then YAML::Load of it
            # as a list of profiles whose history, reliability and durability are integers.
            assert isinstance(qos, str)
            (profile,) = yaml.safe_load(qos)
            assert (profile["history"], profile["reliability"], profile["durability"]) == (1, 1, 2)
        else:
            # Jazzy, version ≥ 9: a YAML list with the enums by name.
            (profile,) = qos
            assert (profile["history"], profile["reliability"], profile["durability"]) == (
                "keep_last", "reliable", "volatile",
            )  # fmt: skip
        # What every robot's publisher offers live (rclcpp's default QoS: depth 10).
        assert profile["depth"] == 10
        assert profile["liveliness"] in (1, "automatic")


@pytest.mark.parametrize("distro", ["humble", "jazzy"])
def test_foxglove_reads_every_message_of_the_bag_from_its_own_definitions(
    tmp_path: Path, distro: str
) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    bag = _bag(tmp_path, distro)
    (mcap,) = bag.glob("*.mcap")
    with mcap.open("rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        foxglove = [
            (channel.topic, message.log_time, decoded)
            for _, channel, message, decoded in reader.iter_decoded_messages()
        ]
    assert len(foxglove) == 10 * STEPS
    store = get_typestore(Stores.ROS2_HUMBLE if distro == "humble" else Stores.ROS2_JAZZY)
    with Reader(bag) as r:
        ours = {(c.topic, t): (c.msgtype, raw) for c, t, raw in r.messages()}
    detections = paths = 0
    for topic, log_time, msg in foxglove:
        type_name, raw = ours[topic, log_time]
        if type_name == OBJECTS:
            want = _detections_store(bag, raw)
            got = [
                [(h.hypothesis.class_id, h.hypothesis.score) for h in d.results]
                for d in msg.detections
            ]
            assert got == want
            cov = np.array(msg.detections[0].results[0].pose.covariance)
            assert cov.shape == (36,) and cov[0] > 0
            detections += 1
        elif type_name == PATH:
            path = store.deserialize_cdr(raw, PATH)
            assert [p.pose.position.x for p in msg.poses] == [p.pose.position.x for p in path.poses]
            k = (log_time - START_NS) // 500_000_000
            assert len(msg.poses) == k  # one pose per step so far
            paths += 1
    assert detections == paths == 2 * STEPS


def _detections_store(bag: Path, raw: bytes) -> list[list[tuple[str, float]]]:
    """The class scores of a Detection3DArray as rosbags reads them, from the bag's own
    definitions (AnyReader: no vision_msgs in rosbags' stores)."""
    from rosbags.highlevel import AnyReader

    with AnyReader([bag]) as reader:
        msg = reader.deserialize(raw, OBJECTS)
    return [
        [(h.hypothesis.class_id, h.hypothesis.score) for h in d.results] for d in msg.detections
    ]
