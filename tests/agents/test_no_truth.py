"""Ground truth never enters an agent: no module under agents/ reads a frame's true pose (or any
field named like ground truth). The simulator keeps it for its metrics; the conductor strips it
from the frames it publishes (tested in tests/deploy/test_launch.py)."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np

from deploy.launch.conductor import without_truth
from estimator.models import SensorFrame
from protocol.frames import decode_frame, encode_frame

AGENTS = Path(__file__).resolve().parents[2] / "agents"
TRUTH_NAMES = {"true_pose", "truth", "true_poses", "ground_truth"}


def truth_reads(source: str) -> list[tuple[int, str]]:
    """(line, name) of every read of a ground-truth field: attribute, name or string key (a
    keyword argument that *sets* it, e.g. to strip it with ``replace(frame, true_pose=nan)``, is
    not a read)."""
    found = []
    for node in ast.walk(ast.parse(source)):
        name = None
        if isinstance(node, ast.Attribute):
            name = node.attr
        elif isinstance(node, ast.Name):
            name = node.id
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            name = node.value
        if name in TRUTH_NAMES:
            found.append((getattr(node, "lineno", 0), name))
    return found


def test_no_module_under_agents_reads_a_ground_truth_field() -> None:
    modules = sorted(AGENTS.rglob("*.py"))
    assert len(modules) >= 8
    offenders = {
        str(p.relative_to(AGENTS)): hits
        for p in modules
        if (hits := truth_reads(p.read_text(encoding="utf-8")))
    }
    assert offenders == {}


def test_the_check_sees_a_truth_read() -> None:
    assert truth_reads("x = frame.true_pose[0]\n") == [(1, "true_pose")]
    assert truth_reads("y = getattr(frame, 'true_pose')\n") == [(1, "true_pose")]
    assert truth_reads("z = doc['truth']\n") == [(1, "truth")]
    assert truth_reads("w = frame.odometry\n") == []


def test_frames_published_to_agents_carry_no_truth() -> None:
    frame = SensorFrame("r1", 3, np.array([1.0, 0.0, 0.1]), (), np.array([4.0, 5.0, 0.2]))
    sent = decode_frame(encode_frame(without_truth(frame)))
    assert np.isnan(sent.true_pose).all()
    np.testing.assert_array_equal(sent.odometry, frame.odometry)
