"""Learned classifier model files in scenarios and robot models: `model = "learned"` with a file
relative to the TOML's folder, `[classifier.estimator]`, hostile files refused in one line."""

from __future__ import annotations

import dataclasses
import io
import zipfile
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from deploy.base.build import belief_model
from estimator.models import LearnedClassifier, paper_classifier
from sim.generate import dump_scenario
from sim.learned_file import LearnedFileError, load_learned, save_learned
from sim.loader import load_scenario, parse_scenario
from sim.robot_model import dump_robot_model, load_robot_model, parse_robot_model
from sim.scenario import ScenarioError
from sim.sensors import Simulator
from tests.estimator.test_learned_model import learned_copy
from tests.tolerance import assert_close

MODEL = """\
format = 1

[classes]
count = 2

[classifier]
model = "learned"
file = "models/paper.npz"

[noise]
odometry_var = [0.003, 0.003, 0.001]
geometric_var = [0.1, 0.1, 0.01]

[sensor]
half_angle_deg = 50.0
range = 3.5
"""


@pytest.fixture
def npz(tmp_path: Path) -> Path:
    return save_learned(learned_copy(paper_classifier()), tmp_path / "models" / "paper.npz")


def _paper_with_estimator(folder: Path, file: str) -> Path:
    """The bundled paper world with a learned ``[classifier.estimator]``, in ``folder/world``."""
    paper = (resources.files("sim") / "scenarios" / "paper.toml").read_text(encoding="utf-8")
    estimator = f'[classifier.estimator]\nmodel = "learned"\nfile = "{file}"\n'
    text = paper.replace("\n[noise]\n", f"\n{estimator}\n[noise]\n")  # after [classifier]
    assert text != paper
    path = folder / "world" / "paper-learned.toml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def test_robot_model_reads_a_learned_file_relative_to_its_folder(
    npz: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(MODEL, encoding="utf-8")
    monkeypatch.chdir(tmp_path.parent)  # not the model's folder
    model = load_robot_model(path)
    assert model.classifier.model == "learned"
    assert Path(model.classifier.file) == npz.resolve()
    classifier = belief_model(model).classifier
    assert isinstance(classifier, LearnedClassifier)
    assert_close(classifier.cov(1, 0.3), paper_classifier().cov(1, 0.3))
    # written with the absolute path: read back anywhere, the same model
    again = parse_robot_model(dump_robot_model(model), "elsewhere.toml", tmp_path / "x")
    assert again == model


def test_scenario_estimator_classifier_is_the_robots_model_and_not_the_simulators(
    npz: Path, tmp_path: Path
) -> None:
    s = load_scenario(_paper_with_estimator(tmp_path, "../models/paper.npz"))
    assert s.classifier.model == "paper"
    assert s.robot_model().classifier.model == "learned"
    assert isinstance(belief_model(s).classifier, LearnedClassifier)
    plain = load_scenario("paper")
    frame, plain_frame = Simulator(s, 3).frame("r1", 5), Simulator(plain, 3).frame("r1", 5)
    for d, e in zip(frame.detections, plain_frame.detections, strict=True):
        assert_close(d.z_sem, e.z_sem, rtol=0)  # the crafted model still draws the scores
    again = parse_scenario(dump_scenario(s), "copy.toml")
    assert dataclasses.replace(again, source=s.source) == s


def test_override_sets_the_estimator_classifier_relative_to_the_current_folder(
    npz: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(npz.parent)
    value = {"model": "learned", "file": "paper.npz"}
    s = load_scenario("paper", overrides={"classifier.estimator": value})
    assert s.estimator_classifier is not None
    assert Path(s.estimator_classifier.file) == npz.resolve()


@pytest.mark.parametrize(
    ("change", "field", "reason"),
    [
        (('file = "models/paper.npz"', 'file = "models/none.npz"'), "classifier.file", "no such"),
        (('file = "models/paper.npz"', 'file = ""'), "classifier.file", "must name"),
        (('file = "models/paper.npz"\n', ""), "classifier.file", "missing required field"),
        (
            ('file = "models/paper.npz"', 'file = "models/paper.npz"\nalias = [2, 1]'),
            "classifier.alias",
            "unknown key",
        ),
        (
            ("count = 2", "count = 3"),
            "classifier.file",
            "holds a model of 2 classes, the model has 3",
        ),
        (
            ('file = "models/paper.npz"', 'file = "models/paper.npz"\n[classifier.estimator]'),
            "classifier.estimator",
            "only in a scenario",
        ),
    ],
)
def test_robot_model_errors_name_the_field(
    npz: Path, tmp_path: Path, change: tuple[str, str], field: str, reason: str
) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(MODEL.replace(*change), encoding="utf-8")
    with pytest.raises(ScenarioError) as info:
        load_robot_model(path)
    message = str(info.value)
    assert message.startswith(f"{path}: {field}: "), message
    assert reason in message and "\n" not in message, message


def _rewrite(path: Path, **changes: object) -> None:
    with np.load(path, allow_pickle=False) as f:
        arrays = {k: f[k] for k in f.files}
    arrays.update(changes)  # type: ignore[arg-type]
    np.savez(path, **arrays)  # type: ignore[arg-type]


def test_hostile_files_are_refused_in_one_line_naming_the_field(npz: Path) -> None:
    good = npz.read_bytes()
    cases: list[tuple[bytes | None, dict[str, object], str]] = [
        (b"not a zip at all", {}, "not a readable .npz file"),
        (None, {"mean_weights": np.full((2, 2, 24), np.nan)}, "mean_weights: contains a NaN"),
        (None, {"noise_cov": np.ones((2, 2, 2))}, "noise_cov[0]: not positive definite"),
        (None, {"mean_offset": np.zeros((3, 2))}, "mean_offset: expected shape (2, 2)"),
        (None, {"version": np.array(7)}, "version: unsupported version 7"),
        (None, {"mean_offset": np.array([None, 1], dtype=object)}, "not a readable .npz"),
    ]
    for data, changes, reason in cases:
        npz.write_bytes(good)
        if data is not None:
            npz.write_bytes(data)
        else:
            _rewrite(npz, **changes)
        with pytest.raises(LearnedFileError) as info:
            load_learned(npz)
        message = str(info.value)
        assert message.startswith(f"{npz}: ") and reason in message, message
        assert "\n" not in message


def test_a_zip_bomb_is_refused_before_it_is_inflated(npz: Path) -> None:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("mean_weights.npy", b"\0" * (80 * 2**20))
    npz.write_bytes(buffer.getvalue())
    assert npz.stat().st_size < 2**20
    with pytest.raises(LearnedFileError, match="inflates to"):
        load_learned(npz)


def test_a_file_replaced_after_loading_is_refused_at_build(npz: Path, tmp_path: Path) -> None:
    path = tmp_path / "robot.toml"
    path.write_text(MODEL, encoding="utf-8")
    model = load_robot_model(path)
    other = learned_copy(paper_classifier(), length_scale=0.8)
    save_learned(other, npz)
    with pytest.raises(ScenarioError, match="changed since the scenario was loaded"):
        model.classifier.build()
