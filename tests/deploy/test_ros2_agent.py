"""A real agent process whose frames come from simulated ROS 2 topics over Zenoh, as a robot with
rmw_zenoh would publish them (nav_msgs/Odometry + vision_msgs/Detection2DArray, rmw_zenoh keys
and attachments), and whose belief comes back as ROS 2 topics with rmw_zenoh's keys, attachments
and graph tokens — no ROS installed, no code on the robot's side."""

from __future__ import annotations

import os
import queue
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import tomli_w
import zenoh

from agents.ros2.messages import DETECTIONS, MARKERS, ODOMETRY, POSE, Ros2Types, types_for
from agents.ros2.outputs import OBJECTS, PATH
from agents.ros2.readings import detections_message, odometry_reading_message
from agents.ros2.wire import decode_attachment, encode_attachment, topic_key
from agents.transport.zenoh_transport import ZenohSettings, loopback_endpoint
from deploy.launch import free_ports
from estimator.models import SensorFrame
from estimator.models.se2 import compose
from protocol.estimate import EstimateMessage, decode_estimate
from sim.loader import load_scenario
from sim.robot_model import dump_robot_model
from sim.sensors import Simulator
from tests.tolerance import assert_close

ROOT = Path(__file__).resolve().parents[2]
SCENARIO = load_scenario("paper")
STEPS = 8
DOMAIN = 4
S = 10**9
WAIT_S = 60.0


def _config(tmp: Path, port: int) -> Path:
    (tmp / "model.toml").write_text(dump_robot_model(SCENARIO.robot_model()), "utf-8")
    doc = {
        "agent": {
            "fleet": "rosfleet",
            "model": "model.toml",
            "start": [float(v) for v in SCENARIO.robot("r1").start],
            "roster": ["r1"],
            "seed": 5,
            "mode": "realtime",
            "gossip_period": 0.2,
        },
        "zenoh": {"listen": [loopback_endpoint(port)], "gossip": False},
        # On the agent's own session (no router): the listener below dials the agent.
        "ros2": {"enable": True, "domain_id": DOMAIN, "distro": "jazzy", "connect": []},
    }
    path = tmp / "r1.toml"
    path.write_text(tomli_w.dumps(doc), "utf-8")
    return path


def test_ros2_agent_steps_on_ros2_topics_and_publishes_its_belief_as_ros2(tmp_path: Path) -> None:
    port = free_ports(1)[0]
    config = _config(tmp_path, port)
    log = open(tmp_path / "agent.log", "wb")  # noqa: SIM115 — outlives the with-less Popen
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}
    cmd = [sys.executable, "-m", "deploy.cli", "agent", "--robot", "r1", "--config", str(config)]
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=ROOT, env=env)
    settings = ZenohSettings(connect=(loopback_endpoint(port),), gossip=False)
    session = zenoh.open(settings.config())
    try:
        _run(session, tmp_path)
    finally:
        session.close()
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()


def _run(session: zenoh.Session, tmp: Path) -> None:
    types = types_for("jazzy")
    out: queue.Queue[tuple[str, bytes, bytes | None]] = queue.Queue()
    estimates: queue.Queue[bytes] = queue.Queue()

    def on_ros(sample: zenoh.Sample) -> None:
        att = sample.attachment.to_bytes() if sample.attachment is not None else None
        out.put((str(sample.key_expr), sample.payload.to_bytes(), att))

    _subs = [
        session.declare_subscriber(f"{DOMAIN}/r1/semfleet/**", on_ros),
        session.declare_subscriber(
            "semfleet/rosfleet/estimate/r1", lambda s: estimates.put(s.payload.to_bytes())
        ),
    ]
    tokens = _wait_for_tokens(session, tmp)
    kinds = sorted(t.split("/")[5] for t in tokens)
    assert kinds == ["MP"] * 6 + ["MS", "MS", "NN"], tokens

    # The robot's side: its driver's odometry and its detector's detections, rmw_zenoh style.
    frames = Simulator(SCENARIO, 5).all_frames()["r1"][:STEPS]
    odom_key = topic_key(DOMAIN, "/r1/odom", ODOMETRY, types.type_hash(ODOMETRY))
    det_key = topic_key(DOMAIN, "/r1/detections", DETECTIONS, types.type_hash(DETECTIONS))
    odom_pub = session.declare_publisher(odom_key)
    det_pub = session.declare_publisher(det_key)
    gid = bytes(16)
    feed_ros2(types, odom_pub, det_pub, SCENARIO.robot("r1").start, frames, gid)

    last = _wait_for_step(estimates, STEPS, tmp)
    assert last.counters["ros_frames_built"] == STEPS
    assert last.counters["ros_malformed"] == 0
    snap = last.beliefs["distributed"]
    best = int(np.argmax(snap.weights))
    truth = frames[-1].true_pose
    assert np.hypot(*(snap.robot_pose[best, :2] - truth[:2])) < 1.0

    # The belief as ROS 2: every sample has rmw_zenoh's key and attachment; the step's stamp.
    keys = {
        t: topic_key(DOMAIN, f"/r1/semfleet/{topic}", t, types.type_hash(t))
        for t, topic in ((ODOMETRY, "odometry"), (POSE, "pose"), (MARKERS, "objects"))
    }
    samples = _collect(out, keys[MARKERS], types, tmp)
    # The trajectory and the machine-readable map come on their own topics too; whether some of
    # theirs arrive before the last markers depends on timing, so they may be here or not.
    also = {
        topic_key(DOMAIN, f"/r1/semfleet/{topic}", t, types.type_hash(t))
        for t, topic in ((PATH, "path"), (OBJECTS, "detections"))
    }
    assert set(keys.values()) <= set(samples) <= set(keys.values()) | also
    for key in keys.values():
        seqs = [decode_attachment(att)[0] for _, att in samples[key] if att is not None]
        assert len(seqs) == len(samples[key]) and seqs == sorted(seqs) and seqs[0] >= 1
    odom_msg = types.store.deserialize_cdr(samples[keys[ODOMETRY]][-1][0], ODOMETRY)
    assert odom_msg.header.stamp.sec == STEPS
    p = odom_msg.pose.pose.position
    assert_close([p.x, p.y], snap.robot_pose[best, :2], atol=1e-12)
    markers = types.store.deserialize_cdr(samples[keys[MARKERS]][-1][0], MARKERS).markers
    texts = [m.text for m in markers if m.type == 9]
    assert len(texts) == len(snap.object_ids) > 0
    assert all(t.split()[0] in ("0", "1") for t in texts)


def feed_ros2(  # type: ignore[no-untyped-def]
    types: Ros2Types, odom_pub, det_pub, start, frames: list[SensorFrame], gid: bytes
) -> None:
    """Publish what a ROS 2 robot would: its odometry (integrated from ``start``, one reading
    ahead of each frame's detections) and each frame's detections, stamped k s, with rmw_zenoh's
    attachments."""
    pose = np.asarray(start, dtype=float)
    odom_pub.put(
        odometry_reading_message(types, 0, "odom", "base_link", pose),
        attachment=encode_attachment(1, 0, gid),
    )
    for f in frames:
        pose = compose(pose, f.odometry)
        stamp = f.k * S
        odom = odometry_reading_message(types, stamp, "odom", "base_link", pose)
        odom_pub.put(odom, attachment=encode_attachment(f.k + 1, stamp, gid))
        dets = detections_message(types, stamp, "camera", f.detections, ("0", "1"))
        det_pub.put(dets, attachment=encode_attachment(f.k, stamp, gid))


def _collect(
    out: queue.Queue[tuple[str, bytes, bytes | None]], last_key: str, types: Ros2Types, tmp: Path
) -> dict[str, list[tuple[bytes, bytes | None]]]:
    """Every ROS 2 sample received, by key, up to the markers of the last step (the agent puts
    a step's odometry, pose and markers in that order, after its estimate)."""
    samples: dict[str, list[tuple[bytes, bytes | None]]] = {}
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        try:
            key, payload, att = out.get(timeout=0.5)
        except queue.Empty:
            continue
        samples.setdefault(key, []).append((payload, att))
        if key == last_key:
            msg = types.store.deserialize_cdr(payload, MARKERS)
            if msg.markers and msg.markers[0].header.stamp.sec == STEPS:
                return samples
    raise AssertionError(
        f"no ROS 2 markers of step {STEPS}: {(tmp / 'agent.log').read_text()[-2000:]}"
    )


def _wait_for_tokens(session: zenoh.Session, tmp: Path) -> list[str]:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        replies = session.liveliness().get(f"@ros2_lv/{DOMAIN}/**", timeout=1.0)
        tokens = [str(r.ok.key_expr) for r in replies if r.ok is not None]
        if len(tokens) >= 9:
            return tokens
        time.sleep(0.2)
    raise AssertionError(f"no ROS 2 graph tokens: {(tmp / 'agent.log').read_text()[-2000:]}")


def _wait_for_step(estimates: queue.Queue[bytes], k: int, tmp: Path) -> EstimateMessage:
    deadline = time.monotonic() + WAIT_S
    while time.monotonic() < deadline:
        try:
            est = decode_estimate(estimates.get(timeout=0.5))
        except queue.Empty:
            continue
        if est.k >= k:
            return est
    raise AssertionError(f"no estimate of step {k}: {(tmp / 'agent.log').read_text()[-2000:]}")
