"""A secure fleet's agent (the files of `fleet init`: mutual TLS, access control, gossip scouting
off) with `[ros2]` on reaches a ROS 2 graph through a robot's router, as rmw_zenoh nodes do
(issue 46, item 11). Real processes: `semfleet router` stands in for the robot's `rmw_zenohd`,
`semfleet agent` runs from the robot's `fleet init` folder, and the ROS 2 side is a Zenoh session
configured as rmw_zenoh's default session (a peer dialling the router, gossip to the router,
autoconnect), which is what a ROS 2 node's is. The agent starts before the router, which a robot
booting its services in any order does.

The ROS 2 side dials only the router, and the agent's ROS 2 session is a client of it (which
the router forwards for), so every token and sample crosses the router. Before the fix the agent
put its ROS 2 traffic on its fleet session: a peer of the router with gossip off, for which a
router forwards nothing (and whose access control denied every ROS 2 key besides)."""

from __future__ import annotations

import json
import os
import queue
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
import zenoh

from agents.ros2.messages import DETECTIONS, MARKERS, ODOMETRY, types_for
from agents.ros2.outputs import OBJECTS, PATH, TF
from agents.ros2.wire import DEFAULT_QOS, decode_attachment, topic_key
from agents.transport.zenoh_transport import ZenohSettings
from deploy.cli.commands.scenario import model_text
from deploy.launch import free_ports
from deploy.operator.fleet_init import init_fleet, loopback_spec
from sim.loader import load_scenario
from sim.sensors import Simulator
from tests.deploy.test_ros2_agent import feed_ros2

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = load_scenario("paper")
DOMAIN = 7
STEPS = 6
S = 10**9
WAIT_S = 60.0
TOPICS = {
    MARKERS: "/r1/semfleet/objects",
    PATH: "/r1/semfleet/path",
    OBJECTS: "/r1/semfleet/detections",
    TF: "/tf",
}
# rmw_zenoh's DEFAULT_RMW_ZENOH_SESSION_CONFIG.json5 (ros2/rmw_zenoh, rolling): its scouting.
RMW_ZENOH_GOSSIP = {
    "enabled": True,
    "multihop": False,
    "target": {"router": ["router", "peer"], "peer": ["router"]},
    "autoconnect": {"router": [], "peer": ["router", "peer"]},
    "autoconnect_strategy": {"peer": {"to_router": "always", "to_peer": "greater-zid"}},
}


def _spawn(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    return subprocess.Popen(
        [sys.executable, "-m", "deploy.cli", *args],
        stdout=log.open("wb"),
        stderr=subprocess.STDOUT,
        cwd=ROOT,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )


def _stop(proc: subprocess.Popen[bytes]) -> None:
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def test_ros2_fleet_agent_reaches_a_router_based_ros2_graph(tmp_path: Path) -> None:
    fleet_port, router_port = free_ports(2)
    start = tuple(float(v) for v in SCENARIO.robot("r1").start)
    spec = loopback_spec("rosfleet", ["r1"], "op", {"r1": start}, model_text(SCENARIO), fleet_port)
    folder = init_fleet(spec, tmp_path / "fleet")["r1"]
    router = f"tcp/127.0.0.1:{router_port}"
    config = folder / "agent.toml"
    with config.open("a", encoding="utf-8") as f:
        f.write(f'\n[ros2]\nenable = true\ndomain_id = {DOMAIN}\nconnect = ["{router}"]\n')
    assert '"enabled": false' in (folder / "zenoh.json5").read_text()  # gossip off, as generated

    agent = _spawn(["agent", "--robot", "r1", "--config", str(config)], tmp_path / "agent.log")
    procs = [agent]
    session = None
    try:
        time.sleep(1.0)  # the agent is up before the robot's router
        procs.append(_spawn(["router", "--listen", router], tmp_path / "router.log"))
        ros = ZenohSettings(connect=(router,), listen=("tcp/127.0.0.1:0",))
        session = zenoh.open(_rmw_zenoh_like(ros))
        _exercise(session, tmp_path)
    finally:
        if session is not None:
            session.close()
        for proc in reversed(procs):
            _stop(proc)


def _rmw_zenoh_like(settings: ZenohSettings) -> zenoh.Config:
    """A ROS 2 node's session: ``settings`` with rmw_zenoh's gossip scouting."""
    doc = settings.document()
    doc["scouting"]["gossip"] = RMW_ZENOH_GOSSIP
    return zenoh.Config.from_json5(json.dumps(doc))


def _exercise(session: zenoh.Session, tmp: Path) -> None:
    types = types_for("jazzy")
    out: queue.Queue[tuple[str, bytes, bytes | None]] = queue.Queue()

    def on_ros(sample: zenoh.Sample) -> None:
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        out.put((str(sample.key_expr), sample.payload.to_bytes(), att))

    _subs = [
        session.declare_subscriber(f"{DOMAIN}/r1/semfleet/**", on_ros),
        session.declare_subscriber(f"{DOMAIN}/tf/**", on_ros),
    ]
    tokens = _wait_for_tokens(session, tmp)
    assert sorted(t.split("/")[5] for t in tokens) == ["MP"] * 6 + ["MS", "MS", "NN"]
    qos = sorted(t.rsplit("/", 1)[1] for t in tokens if t.split("/")[5] != "NN")
    assert qos == sorted([DEFAULT_QOS] * 7 + ["::,100:,:,:,,"])  # /tf: as tf2_ros declares it

    frames = Simulator(SCENARIO, 3).all_frames()["r1"][:STEPS]
    odom_pub = session.declare_publisher(
        topic_key(DOMAIN, "/r1/odom", ODOMETRY, types.type_hash(ODOMETRY))
    )
    det_pub = session.declare_publisher(
        topic_key(DOMAIN, "/r1/detections", DETECTIONS, types.type_hash(DETECTIONS))
    )
    gid = bytes(range(16))
    feed_ros2(types, odom_pub, det_pub, SCENARIO.robot("r1").start, frames, gid)

    wanted = {t: topic_key(DOMAIN, topic, t, types.type_hash(t)) for t, topic in TOPICS.items()}
    last: dict[str, object] = {}
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline and len(last) < len(wanted):
        try:
            key, payload, att = out.get(timeout=0.5)
        except queue.Empty:
            continue
        assert att is not None and decode_attachment(att)[0] >= 1, key
        for t, k in wanted.items():
            msg = types.store.deserialize_cdr(payload, t) if key == k else None
            if msg is not None and _stamp_of(t, msg) == STEPS:
                last[t] = msg  # the agent stepped on the ROS 2 frames and answered, via the router
    assert len(last) == len(wanted), f"not every topic of step {STEPS}: {_logs(tmp)}"
    (tf,) = last[TF].transforms  # type: ignore[attr-defined]
    assert (tf.header.frame_id, tf.child_frame_id) == ("map", "odom")  # the robot's odom frame
    # One pose per estimate heard (a realtime agent catching up publishes fewer), in order.
    stamps = [p.header.stamp.sec for p in last[PATH].poses]  # type: ignore[attr-defined]
    assert stamps[-1] == STEPS and stamps == sorted(set(stamps)), stamps
    assert len(last[OBJECTS].detections) > 0  # type: ignore[attr-defined]


def _stamp_of(type_name: str, msg: Any) -> int:
    if type_name == TF:
        return int(msg.transforms[0].header.stamp.sec)
    if type_name == MARKERS:
        return int(msg.markers[0].header.stamp.sec) if msg.markers else -1
    return int(msg.header.stamp.sec)


def _wait_for_tokens(session: zenoh.Session, tmp: Path) -> list[str]:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        replies = session.liveliness().get(f"@ros2_lv/{DOMAIN}/**", timeout=1.0)
        tokens = [str(r.ok.key_expr) for r in replies if r.ok is not None]
        if len(tokens) >= 9:
            return tokens
        time.sleep(0.2)
    raise AssertionError(f"no ROS 2 graph tokens through the router: {_logs(tmp)}")


def _logs(tmp: Path) -> str:
    return "\n".join(p.read_text()[-1500:] for p in sorted(tmp.glob("*.log")))
