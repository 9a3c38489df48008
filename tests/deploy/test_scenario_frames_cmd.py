"""`semfleet scenario frames`: a robot's simulated frames as a frame log (docs/wire.md, "Frame
logs (JSON lines)"), one line per step after the header, and no ground truth anywhere in the file:
not the word, and none of the true poses' numbers."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from deploy.cli.main import main
from estimator.models import NO_ID
from protocol.framelog import read_frame_log
from sim.loader import load_scenario
from sim.sensors import Detector, Simulator
from tests.protocol.test_frames import assert_same_frame

PAPER = load_scenario("paper")


def _export(out: Path, *extra: str) -> int:
    return main(
        ["scenario", "frames", "paper", "--seed", "3", "--robot", "r2", "-o", str(out), *extra]
    )


def test_scenario_frames_writes_every_step_without_truth(tmp_path: Path) -> None:
    out = tmp_path / "logs" / "r2.jsonl"
    assert _export(out) == 0
    text = out.read_text(encoding="utf-8")
    lines = text.splitlines()
    assert len(lines) == 1 + PAPER.steps and text.endswith("\n")
    assert json.loads(lines[0]) == {"v": 1, "type": "frame_log"}
    assert "truth" not in text and "true" not in text
    simulated = Simulator(PAPER, 3).frames("r2")
    truth = {float(x) for f in simulated for x in f.true_pose}
    written: list[float] = []  # every float token of the file (integers are k, ids and v)
    for line in lines:
        json.loads(line, parse_float=lambda token: written.append(float(token)))
    assert not truth & set(written), sorted(truth & set(written))[:5]
    assert len(written) > 3 * PAPER.steps  # the numbers were found: odometry and detections
    frames = read_frame_log(lines)
    for got, want in zip(frames, simulated, strict=True):
        assert np.isnan(got.true_pose).all()
        assert_same_frame(got, dataclasses.replace(want, true_pose=np.full(3, np.nan)))


def test_scenario_frames_steps_and_overwrite(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "r2.jsonl"
    assert _export(out, "--steps", "5") == 0
    assert len(out.read_text().splitlines()) == 6
    assert _export(out) == 2  # never overwritten without --force
    assert "already exists (--force overwrites it)" in capsys.readouterr().err
    assert len(out.read_text().splitlines()) == 6
    assert _export(out, "--force", "--steps", "7") == 0
    assert [f.k for f in read_frame_log(out.read_text().splitlines())] == list(range(1, 8))


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--robot", "r9"], "--robot: 'r9' is not a robot of paper (r1, r2, r3)"),
        (["--steps", "61"], "--steps 61: outside 1..60"),
    ],
)
def test_scenario_frames_refuses_bad_arguments(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], says: str
) -> None:
    out = tmp_path / "x.jsonl"
    assert _export(out, *args) == 2
    assert says in capsys.readouterr().err
    assert not out.exists()


def test_scenario_frames_without_ids_writes_the_detector_frames(tmp_path: Path) -> None:
    out = tmp_path / "r2.jsonl"
    assert _export(out, "--ids", "none", "--clutter", "0.2", "--miss", "0.1") == 0
    with out.open(encoding="utf-8") as f:
        got = read_frame_log(f)
    sim = Simulator(PAPER, 3, detector=Detector("none", 0.2, 0.1))
    for g, want in zip(got, sim.frames("r2"), strict=True):
        assert g.ids == "none" and all(d.object_id == NO_ID for d in g.detections)
        assert_same_frame(g, dataclasses.replace(want, true_pose=np.full(3, np.nan)))
    given = sum(len(f.detections) for f in Simulator(PAPER, 3).frames("r2"))
    assert sum(len(f.detections) for f in got) != given  # misses and clutter changed them


@pytest.mark.parametrize(("option", "value"), [("--ids", "tracker"), ("--miss", "1.5")])
def test_scenario_frames_refuses_a_bad_detector_option(
    tmp_path: Path, option: str, value: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as caught:
        _export(tmp_path / "r2.jsonl", option, value)
    assert caught.value.code == 2 and option in capsys.readouterr().err
