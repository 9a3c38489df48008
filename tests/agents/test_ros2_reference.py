"""semfleet's ROS 2 messages read by ROS 2 itself: rclpy's serialisation (rmw_fastrtps' CDR) of
the PyPI ``ros-*`` wheels, in their own virtual environment (`make ros2-env`, which `make test`
runs), through tests/agents/ros2_reference.py. rmw_zenoh sends the same CDR bytes (docs/ros2.md);
its own transport is not among those wheels and is not exercised here.

- ROS 2 reads each of semfleet's belief messages (Odometry, PoseWithCovarianceStamped,
  MarkerArray, Path; tf2_msgs and vision_msgs are not among the wheels) to the same fields as
  semfleet's own decoder, and re-serialises it to the bytes semfleet sent;
- the type hashes semfleet puts in its keys are the ones the message packages install;
- an Odometry built and serialised by ROS 2 is read by semfleet to the pose it holds, and is the
  bytes semfleet's own builder makes of it.

"The bytes" up to alignment padding: Fast-CDR leaves the padding before an 8-byte field
unwritten (it held 0x7f and 0x08 in our runs), and CDR does not specify its value; semfleet (like
rosbags) writes zeros. So ROS 2's bytes are compared after a rosbags round trip, which zeroes the
padding and nothing else, and their lengths are compared as they are.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from agents.ros2.messages import (
    MARKERS,
    ODOMETRY,
    POSE,
    markers_message,
    odometry_message,
    pose_message,
    types_for,
)
from agents.ros2.outputs import PATH, path_message
from agents.ros2.readings import odometry_reading_message, read_odometry
from tests.agents.test_ros2_messages import _snapshot
from tests.tolerance import assert_angles_close, assert_close

REPO = Path(__file__).resolve().parents[2]
SCRIPT = Path(__file__).with_name("ros2_reference.py")
ENV_VAR = "SEMFLEET_ROS2_PYTHON"


def ros2_python() -> Path | None:
    """The Python with ROS 2: ``$SEMFLEET_ROS2_PYTHON``, else ``make ros2-env``'s."""
    given = os.environ.get(ENV_VAR)
    path = Path(given) if given else REPO / ".venv-ros2" / "bin" / "python"
    return path if path.exists() else None


def ask_ros2(request: dict[str, Any]) -> dict[str, Any]:
    python = ros2_python()
    if python is None:
        pytest.skip(f"no ROS 2 Python: `make ros2-env` installs one (or set {ENV_VAR})")
    lib = python.parent.parent / "lib"  # the wheels' shared libraries (librcl, librmw_...)
    env = {
        "PATH": "/usr/bin:/bin",
        "LD_LIBRARY_PATH": str(lib),
        "AMENT_PREFIX_PATH": str(lib.parent),
    }
    done = subprocess.run(
        [str(python), str(SCRIPT)],
        input=json.dumps(request),
        capture_output=True,
        text=True,
        timeout=120,  # a guard against hangs
        env=env,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    answer: dict[str, Any] = json.loads(done.stdout)
    return answer


def plain(value: Any) -> Any:
    """A rosbags message as nested dicts and lists (as the script makes of ROS 2's): its fields,
    not its ``__msgtype__`` nor its constants (upper case in ROS 2, fields never are)."""
    if dataclasses.is_dataclass(value):
        names = (f.name for f in dataclasses.fields(value))
        fields = (n for n in names if not n.startswith("__") and not n.isupper())
        return {name: plain(getattr(value, name)) for name in fields}
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, list | tuple):
        return [plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def zero_padding(types: Any, data: bytes, type_name: str) -> bytes:
    """``data`` with its alignment padding zeroed (a rosbags round trip)."""
    return bytes(types.store.serialize_cdr(types.store.deserialize_cdr(data, type_name), type_name))


@pytest.fixture(scope="module")
def exchange() -> tuple[dict[str, bytes], dict[str, Any]]:
    types, snap = types_for("jazzy"), _snapshot()
    stamp = 1_700_000_000_123_456_789
    ours = {
        ODOMETRY: odometry_message(types, snap, stamp, "map", "r1/base_link"),
        POSE: pose_message(types, snap, stamp, "map"),
        MARKERS: markers_message(types, snap, stamp, "map", "semfleet/r1", ("chair", "table")),
        PATH: path_message(types, [(stamp - 5, snap.robot_pose[1]), (stamp, snap.robot_pose[0])],
                           stamp, "map"),
    }  # fmt: skip
    theta = 2.5  # beyond ±π/2: the quaternion's sign conventions matter
    request = {
        "read": [{"type": t, "hex": data.hex()} for t, data in ours.items()],
        "hashes": list(ours),
        "odometry": {
            "stamp_ns": stamp, "frame_id": "odom", "child_frame_id": "r2/base_link",
            "x": -3.25, "y": 7.5, "qz": float(np.sin(theta / 2)), "qw": float(np.cos(theta / 2)),
        },
    }  # fmt: skip
    return ours, ask_ros2(request)


def test_ros2_reads_semfleets_belief_messages_as_semfleet_means_them(
    exchange: tuple[dict[str, bytes], dict[str, Any]],
) -> None:
    ours, ros2 = exchange
    types = types_for("jazzy")
    for (type_name, data), read in zip(ours.items(), ros2["read"], strict=True):
        mine = plain(types.store.deserialize_cdr(data, type_name))
        assert read["fields"] == mine, type_name
        again = bytes.fromhex(read["hex"])
        assert len(again) == len(data) and zero_padding(types, again, type_name) == data, (
            f"{type_name}: rclpy re-serialises other bytes"
        )
    # Not vacuous: the markers carry the class text and the odometry the best hypothesis.
    texts = [m["text"] for m in ros2["read"][2]["fields"]["markers"] if m["text"]]
    assert texts and all("chair" in t or "table" in t for t in texts)
    assert_close(ros2["read"][0]["fields"]["pose"]["pose"]["position"]["x"], 1.0)


def test_ros2_type_hashes_are_the_installed_packages_ones(
    exchange: tuple[dict[str, bytes], dict[str, Any]],
) -> None:
    ours, ros2 = exchange
    types = types_for("jazzy")
    assert ros2["hashes"] == {t: types.type_hash(t) for t in ours}


def test_semfleet_reads_an_odometry_ros2_serialised(
    exchange: tuple[dict[str, bytes], dict[str, Any]],
) -> None:
    _, ros2 = exchange
    data = bytes.fromhex(ros2["odometry"])
    for distro in ("humble", "jazzy"):  # Odometry's layout is the same in both
        types = types_for(distro)
        reading = read_odometry(types, data)
        assert reading.stamp_ns == 1_700_000_000_123_456_789
        assert_close(reading.pose[:2], [-3.25, 7.5])
        assert_angles_close(reading.pose[2], 2.5)
        pose = np.array([-3.25, 7.5, 2.5])
        mine = odometry_reading_message(types, reading.stamp_ns, "odom", "r2/base_link", pose)
        assert len(mine) == len(data) and zero_padding(types, data, ODOMETRY) == mine, distro
