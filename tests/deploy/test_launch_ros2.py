"""`semfleet launch --ros2 --ros2-bag DIR` (issue 46, item 12): a real launch whose generated agent
configs carry a ``[ros2]`` table, seen from a ROS 2 side as rmw_zenoh has it — a Zenoh session
that dials the robot's router (`semfleet router` standing in for `rmw_zenohd`). Every agent's
node and publishers appear in the graph, and its Path, Detection3DArray, markers, odometry and
pose arrive; no `/tf` and no subscriptions, since a simulation's frames come from the conductor.
The run's rosbag2 recording, read back with rosbags, holds the same messages as the live ones
(stamps aside: the bag's are the run's start plus k periods)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import tomllib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import zenoh

from agents.ros2.messages import MARKERS, ODOMETRY, POSE, Ros2Types, types_for
from agents.ros2.outputs import OBJECTS, PATH
from agents.ros2.wire import topic_key
from agents.transport.zenoh_transport import ZenohSettings
from deploy.cli.main import main
from deploy.launch import free_ports
from tests.tolerance import assert_close

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
DOMAIN = 11
STEPS = 3
ROBOTS = ("r1", "r2", "r3")
TOPICS = {
    PATH: "semfleet/path",
    OBJECTS: "semfleet/detections",
    MARKERS: "semfleet/objects",
    ODOMETRY: "semfleet/odometry",
    POSE: "semfleet/pose",
}


def _semfleet(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "deploy.cli", *args],
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
        cwd=ROOT,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1", "COLUMNS": "200"},
    )


@pytest.mark.parametrize("secure", [False, True], ids=["plain", "secure"])
def test_launch_ros2_publishes_every_agents_belief_through_the_router(
    tmp_path: Path, secure: bool
) -> None:
    """Plain, with the bag; a throwaway secure fleet (mutual TLS among the agents, the ROS 2
    client session beside it), without."""
    with _router_and_ros2_side(tmp_path) as (router_at, session):
        samples, tokens = _listen(session)
        out = tmp_path / "out"
        launch = _semfleet(
            [
                "launch", "--scenario", "paper", "--steps", str(STEPS), "--out", str(out),
                "--ros2", "--ros2-domain", str(DOMAIN), "--ros2-router", router_at,
                *(["--secure"] if secure else ["--ros2-bag", str(tmp_path / "bag")]),
            ],
            tmp_path / "launch.log",
        )  # fmt: skip
        rc = launch.wait(180)
        printed = (tmp_path / "launch.log").read_text()
        assert rc == 0, printed[-3000:]
        _check(out, printed, samples, tokens)
        if not secure:
            _check_bag(tmp_path / "bag", printed, samples)
        else:
            assert "secure fleet: mutual TLS" in printed and "ROS 2 bag" not in printed


@contextlib.contextmanager
def _router_and_ros2_side(tmp_path: Path) -> Iterator[tuple[str, zenoh.Session]]:
    """A `semfleet router` standing in for `rmw_zenohd`, and a Zenoh session dialling it as a
    ROS 2 node's does: the router's endpoint and the session."""
    (port,) = free_ports(1)
    router_at = f"tcp/127.0.0.1:{port}"
    router = _semfleet(["router", "--listen", router_at], tmp_path / "router.log")
    session = None
    try:
        ros = ZenohSettings(connect=(router_at,), listen=("tcp/127.0.0.1:0",))
        session = zenoh.open(ros.config())
        yield router_at, session
    finally:
        if session is not None:
            session.close()
        router.send_signal(signal.SIGTERM)
        router.wait(10)


Samples = dict[str, list[bytes]]


def _listen(session: zenoh.Session) -> tuple[Samples, set[str]]:
    samples: Samples = {}
    tokens: set[str] = set()
    lock = threading.Lock()

    def on_sample(s: zenoh.Sample) -> None:
        with lock:
            samples.setdefault(str(s.key_expr), []).append(s.payload.to_bytes())

    def on_token(s: zenoh.Sample) -> None:
        if s.kind == zenoh.SampleKind.PUT:
            with lock:
                tokens.add(str(s.key_expr))

    session.declare_subscriber(f"{DOMAIN}/**", on_sample)
    session.liveliness().declare_subscriber(f"@ros2_lv/{DOMAIN}/**", on_token)
    return samples, tokens


def _check(out: Path, printed: str, samples: Samples, tokens: set[str]) -> None:
    assert f"ROS 2 (jazzy, domain {DOMAIN})" in printed
    for r in ROBOTS:
        ros2 = tomllib.loads((out / "agents" / f"{r}.toml").read_text())["ros2"]
        assert ros2 == {
            "enable": True, "domain_id": DOMAIN, "distro": "jazzy",
            "connect": [ros2["connect"][0]], "odometry_in": "", "detections_in": "",
        }  # fmt: skip
    # The graph: a node and five publishers per agent; no subscription, no /tf publisher
    # carries a sample (the agent declares it; a conductor's frames have no odom frame).
    kinds = sorted(t.split("/")[5] for t in tokens)
    assert kinds == ["MP"] * 18 + ["NN"] * 3, sorted(tokens)
    types = types_for("jazzy")
    keys = {
        (r, t): topic_key(DOMAIN, f"/{r}/{topic}", t, types.type_hash(t))
        for r in ROBOTS
        for t, topic in TOPICS.items()
    }
    assert set(samples) == set(keys.values()), sorted(samples)
    assert not any("tf2_msgs" in k for k in samples)
    results = json.loads((out / "results.json").read_text())
    for r in ROBOTS:
        path = types.store.deserialize_cdr(samples[keys[r, PATH]][-1], PATH)
        assert path.header.frame_id == "map"
        assert len(path.poses) == STEPS  # each step of the run, once
        stamps = [q.header.stamp.sec * 10**9 + q.header.stamp.nanosec for q in path.poses]
        assert stamps == sorted(set(stamps))
        odometry = types.store.deserialize_cdr(samples[keys[r, ODOMETRY]][-1], ODOMETRY)
        last = path.poses[-1].pose.position
        p = odometry.pose.pose.position
        assert_close([last.x, last.y], [p.x, p.y], atol=1e-12)
        objects = types.store.deserialize_cdr(samples[keys[r, OBJECTS]][-1], OBJECTS)
        assert objects.detections
        for d in objects.detections:
            scores = [h.hypothesis.score for h in d.results]
            assert [h.hypothesis.class_id for h in d.results] == ["0", "1"]
            assert_close(sum(scores), 1.0, atol=1e-9)
    robot_error = results["methods"]["distributed"]["mean"]["robot_error"]
    assert np.isfinite(robot_error[STEPS - 1])


def _check_bag(bag: Path, printed: str, samples: Samples) -> None:
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import Reader

    assert f"wrote the ROS 2 bag {bag} (MCAP): 15 topics, {15 * STEPS} messages" in printed
    assert sorted(p.name for p in bag.iterdir()) == ["bag.mcap", "metadata.yaml"]
    types = types_for("jazzy")
    assert (bag / "bag.mcap").read_bytes()[:8] == b"\x89MCAP0\r\n"  # what Foxglove opens
    assert "storage_identifier: mcap" in (bag / "metadata.yaml").read_text()
    with Reader(bag) as reader:
        got = {(c.topic, c.msgtype): c.msgcount for c in reader.connections}
        assert got == {(f"/{r}/{topic}", t): STEPS for r in ROBOTS for t, topic in TOPICS.items()}
        recorded: dict[str, list[tuple[int, bytes]]] = {}
        for c, t, raw in reader.messages():
            recorded.setdefault(c.topic, []).append((t, raw))
    for r in ROBOTS:
        for t, topic in TOPICS.items():
            key = topic_key(DOMAIN, f"/{r}/{topic}", t, types.type_hash(t))
            (log_ns, raw), live = recorded[f"/{r}/{topic}"][-1], samples[key][-1]
            msg = types.store.deserialize_cdr(raw, t)
            assert types.store.serialize_cdr(msg, t) == raw  # valid CDR of its type
            stamp = (msg.header if t != MARKERS else msg.markers[0].header).stamp
            assert stamp.sec * 10**9 + stamp.nanosec == log_ns
            assert _unstamped(types, msg, t) == _unstamped(
                types, types.store.deserialize_cdr(live, t), t
            ), (r, t)
        logged = [n for n, _ in recorded[f"/{r}/semfleet/path"]]
        assert np.diff(logged).tolist() == [500_000_000] * (STEPS - 1)  # the default period
    # A tool without vision_msgs (Foxglove, a ROS install without it) decodes by the bag's own
    # message definitions: rosbags' AnyReader builds its types from them alone.
    with AnyReader([bag]) as reader:
        (det,) = [c for c in reader.connections if c.topic == "/r3/semfleet/detections"]
        *_, (_, _, raw) = reader.messages(connections=[det])
        from_bag = reader.deserialize(raw, OBJECTS)
    ours = types.store.deserialize_cdr(raw, OBJECTS)
    assert [
        [(h.hypothesis.class_id, h.hypothesis.score) for h in d.results] for d in ours.detections
    ] == [
        [(h.hypothesis.class_id, h.hypothesis.score) for h in d.results]
        for d in from_bag.detections
    ]


def _unstamped(types: Ros2Types, msg: object, type_name: str) -> bytes:
    """``msg``'s CDR with every stamp zeroed (in place): the live samples carry the wall clock."""
    _zero_stamps(msg)
    return types.store.serialize_cdr(msg, type_name)


def _zero_stamps(value: object) -> None:
    if type(value).__name__ == "builtin_interfaces__msg__Time":
        value.sec = value.nanosec = 0  # type: ignore[attr-defined]
        return
    if isinstance(value, list):
        for v in value:
            _zero_stamps(v)
    for name in getattr(value, "__dataclass_fields__", ()):
        _zero_stamps(getattr(value, name))


@pytest.mark.parametrize(
    ("extra", "files", "error"),
    [
        ([], ["metadata.yaml"], "exists and is not empty (--force writes over"),
        (["--force"], ["metadata.yaml", "notes.txt"], "holds 'notes.txt', not a bag's file"),
        (["--ros2-domain", "3"], [], "--ros2-domain: only with --ros2"),
    ],
)
def test_launch_ros2_bag_refuses_before_starting(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], files: list[str],
    error: str,
) -> None:  # fmt: skip
    bag = tmp_path / "bag"
    bag.mkdir()
    for name in files:
        (bag / name).write_text("x")
    argv = ["launch", "--scenario", "paper", "--out", str(tmp_path / "out"), "--ros2-bag", str(bag)]
    assert main([*argv, *extra]) == 2
    assert error in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
    assert sorted(p.name for p in bag.iterdir()) == sorted(files)  # nothing removed


CHAOS_STEPS = 10


def test_chaos_ros2_shows_a_killed_robot_leave_the_ros2_graph_and_come_back(
    tmp_path: Path,
) -> None:
    """`semfleet chaos --ros2 --ros2-bag`: the ROS 2 side of a chaos run through a router. r3's
    node and publishers leave the graph when it is killed (liveliness tokens deleted) and come
    back when it restarts from its journal; every robot's Path reaches the last step; the bag
    holds each robot's steps, r3's without the ones it was dead for."""
    with _router_and_ros2_side(tmp_path) as (router_at, session):
        samples, _ = _listen(session)
        events: list[tuple[str, str]] = []
        session.liveliness().declare_subscriber(
            f"@ros2_lv/{DOMAIN}/**",
            lambda s: events.append((str(s.kind).rsplit(".", 1)[-1], str(s.key_expr))),
        )
        out, bag = tmp_path / "out", tmp_path / "bag"
        chaos = _semfleet(
            [
                "chaos", "--scenario", "paper", "--steps", str(CHAOS_STEPS), "--out", str(out),
                "--kill", "r3@3", "--restart", "r3@6", "--drop", "0.1", "--seed", "2",
                "--ros2", "--ros2-domain", str(DOMAIN), "--ros2-router", router_at,
                "--ros2-bag", str(bag),
            ],
            tmp_path / "chaos.log",
        )  # fmt: skip
        rc = chaos.wait(240)
        printed = (tmp_path / "chaos.log").read_text()
        assert rc == 0, printed[-3000:]
    assert f"ROS 2 (jazzy, domain {DOMAIN})" in printed
    assert "SIGKILL r3" in printed and "restarted r3" in printed
    # r3's node token: put, deleted by the kill, put again by the restart, deleted when the run
    # ends. The others' stay until the run ends, after r3 came back.
    nodes = {
        r: [(i, kind) for i, (kind, key) in enumerate(events) if "/NN/" in key and key.endswith(r)]
        for r in ROBOTS
    }
    assert [k for _, k in nodes["r3"]] == ["PUT", "DELETE", "PUT", "DELETE"], events
    back = nodes["r3"][2][0]
    for r in ("r1", "r2"):
        assert [k for _, k in nodes[r]] == ["PUT", "DELETE"], events
        assert nodes[r][1][0] > back
    types = types_for("jazzy")
    for r in ROBOTS:
        key = topic_key(DOMAIN, f"/{r}/semfleet/path", PATH, types.type_hash(PATH))
        path = types.store.deserialize_cdr(samples[key][-1], PATH)
        assert len(path.poses) >= 1
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
    for r in ("r1", "r2"):
        assert counts[f"/{r}/semfleet/path"] == CHAOS_STEPS
    # Dead from its kill at step 3 until its restart at 6: its estimates of those steps are
    # missing, and the bag does not invent them.
    assert 0 < counts["/r3/semfleet/path"] < CHAOS_STEPS


@pytest.mark.parametrize(
    ("extra", "error"),
    [
        (["--net", "netns"], "--ros2: not with --net netns (an agent's localhost"),
        (["--attack", "all"], "--ros2: not with --attack"),
        (["--ros2-domain", "300"], "expected a ROS_DOMAIN_ID in 0..232"),
    ],
)
def test_chaos_ros2_refuses_what_cannot_reach_rmw_zenohd(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], error: str
) -> None:
    argv = ["chaos", "--scenario", "paper", "--out", str(tmp_path / "out"), "--ros2", *extra]
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own refusal of a value
        code = exc.code
    assert code == 2
    assert error in capsys.readouterr().err
    assert not (tmp_path / "out").exists()
