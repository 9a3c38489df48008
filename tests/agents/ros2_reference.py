"""ROS 2's own reading of semfleet's messages, run by a Python that has ROS 2 (rclpy and the
message packages; `make ros2-env` installs them from PyPI's ``ros-*`` wheels) — never by
semfleet's own environment, and without semfleet's imports.

stdin (JSON): ``{"read": [{"type": "nav_msgs/msg/Odometry", "hex": "..."}, ...],
"hashes": ["nav_msgs/msg/Odometry", ...], "odometry": {"stamp_ns": ..., "frame_id": ...,
"child_frame_id": ..., "x": ..., "y": ..., "qz": ..., "qw": ...}}``.

stdout (JSON): for each message read, ``rclpy.serialization``'s re-serialisation of it and its
fields as plain values; each type's ``RIHS01`` hash from the type description the message
package installs (``share/<pkg>/msg/<Name>.json``); and an Odometry built and serialised by ROS 2
from the given fields, for semfleet to read.
"""

from __future__ import annotations

import importlib
import json
import sys
from importlib.metadata import version
from pathlib import Path
from typing import Any

from ament_index_python.packages import get_package_share_directory
from rclpy.serialization import deserialize_message, serialize_message


def message_class(type_name: str) -> Any:
    package, kind, name = type_name.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)


def plain(value: Any) -> Any:
    """A message as nested dicts and lists of numbers and strings."""
    if hasattr(value, "get_fields_and_field_types"):
        return {name: plain(getattr(value, name)) for name in value.get_fields_and_field_types()}
    if isinstance(value, str | bytes):
        return value if isinstance(value, str) else list(value)
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, list | tuple) or type(value).__name__ == "array":
        return [plain(v) for v in value]
    return value


def type_hash(type_name: str) -> str:
    package, kind, name = type_name.split("/")
    path = Path(get_package_share_directory(package)) / kind / f"{name}.json"
    description = json.loads(path.read_text(encoding="utf-8"))
    (found,) = [h for h in description["type_hashes"] if h["type_name"] == type_name]
    return str(found["hash_string"])


def odometry(fields: dict[str, Any]) -> bytes:
    msg = message_class("nav_msgs/msg/Odometry")()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(fields["stamp_ns"]), 10**9)
    msg.header.frame_id = fields["frame_id"]
    msg.child_frame_id = fields["child_frame_id"]
    msg.pose.pose.position.x = float(fields["x"])
    msg.pose.pose.position.y = float(fields["y"])
    msg.pose.pose.orientation.z = float(fields["qz"])
    msg.pose.pose.orientation.w = float(fields["qw"])
    return bytes(serialize_message(msg))


def main() -> None:
    request = json.load(sys.stdin)
    read = []
    for item in request["read"]:
        msg = deserialize_message(bytes.fromhex(item["hex"]), message_class(item["type"]))
        read.append({"hex": bytes(serialize_message(msg)).hex(), "fields": plain(msg)})
    json.dump(
        {
            "rclpy": version("ros-rclpy"),
            "read": read,
            "hashes": {t: type_hash(t) for t in request["hashes"]},
            "odometry": odometry(request["odometry"]).hex(),
        },
        sys.stdout,
    )


if __name__ == "__main__":
    main()
