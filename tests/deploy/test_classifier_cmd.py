"""`semfleet classifier sample | fit`: score samples as CSV, the GP fit (against scikit-learn and
against the model that drew the samples), and the one-line errors. Run in this process."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from deploy.base.errors import UsageError
from deploy.cli.main import main
from deploy.study.classifier_fit import fit_classifier, truth_gap
from deploy.study.classifier_samples import ScoreSamples, draw_samples, read_samples, write_samples
from estimator.models import AliasedClassifier, paper_classifier
from estimator.models.learned import PeriodicGP
from sim.learned_file import load_learned
from tests.tolerance import assert_close

# A sharp two-class model (σ = 0.1): 300 samples pin its means down to a few hundredths.
SHARP = AliasedClassifier((1, 0), (math.pi / 2, -math.pi / 3), np.eye(2) / 0.1)


def test_draw_samples_follow_the_models_gaussian() -> None:
    model = paper_classifier()
    s = draw_samples(model, 4000, np.random.default_rng(1))
    assert np.bincount(s.classes).tolist() == [2000, 2000]
    assert s.psi.min() >= -math.pi and s.psi.max() < math.pi
    for c in range(2):
        psi, z = s.of_class(c)
        r = z - model.mean(c, psi)
        assert_close(r.mean(axis=0), [0, 0], atol=0.05)
        assert_close(np.cov(r.T), model.cov(c, 0.0), atol=0.03)


def test_samples_round_trip_through_csv_exactly(tmp_path: Path) -> None:
    s = draw_samples(SHARP, 30, np.random.default_rng(2))
    write_samples(s, tmp_path / "s.csv")
    back = read_samples(tmp_path / "s.csv")
    assert back.classes.tolist() == s.classes.tolist()
    assert_close(back.psi, s.psi, rtol=0, atol=0)
    assert_close(back.z, s.z, rtol=0, atol=0)


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("", "empty"),
        ("class,psi,z1\n1,0.0,0.5\n", "line 1: expected the header"),
        ("class,psi,z1,z2\n1,0.0,0.5\n", "line 2: 3 fields, the header has 4"),
        ("class,psi,z1,z2\n1,0.0,0.5,0.5\n3,0.0,0.5,0.5\n", "line 3: class: 3 is out of range"),
        ("class,psi,z1,z2\none,0.0,0.5,0.5\n", "line 2: class: 'one' is not an integer"),
        ("class,psi,z1,z2\n1,north,0.5,0.5\n", "line 2: psi: 'north' is not a number"),
        ("class,psi,z1,z2\n1,0.0,0.5,nan\n", "line 2: z2: nan is not a finite number"),
    ],
)
def test_read_samples_names_the_line_and_field(tmp_path: Path, text: str, reason: str) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(UsageError) as info:
        read_samples(path)
    assert str(info.value).startswith(f"{path}: ") and reason in str(info.value), info.value


def test_periodic_gp_mean_is_scikit_learns_posterior_mean() -> None:
    """With the training inputs as inducing points the projected mean is the exact GP mean."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import ConstantKernel, ExpSineSquared, WhiteKernel

    rng = np.random.default_rng(3)
    x = rng.uniform(-math.pi, math.pi, 40)
    y = np.sin(x) + 0.3 * np.cos(2 * x) + rng.normal(0, 0.2, 40)
    length, amp, noise = 0.8, 0.9, 0.2
    kernel = ConstantKernel(amp**2) * ExpSineSquared(length, 2 * math.pi) + WhiteKernel(noise**2)
    gp = GaussianProcessRegressor(kernel, optimizer=None).fit(x[:, None], y)
    psi = np.linspace(-4, 4, 50)
    ours = PeriodicGP.regression(x, y, x, length, amp, noise**2, 0.0)(psi)[:, 0]
    assert_close(ours, gp.predict(psi[:, None]), atol=1e-6)


def test_fit_recovers_the_model_that_drew_the_samples() -> None:
    samples = draw_samples(SHARP, 300, np.random.default_rng(4))
    fit = fit_classifier(samples, seed=0)
    gaps = truth_gap(fit.model, SHARP)
    # Measured on sample seeds 4..7: max |Δh| ≤ 0.051, mean KL ≤ 0.060 nats, score variances
    # averaged over ψ within 15 % of 0.01, 93–95 % of LOO residuals inside the 95 % ellipse.
    assert all(g.max_mean_error < 0.08 for g in gaps), gaps
    assert all(g.mean_kl < 0.1 for g in gaps), gaps
    psi = np.linspace(-math.pi, math.pi, 90, endpoint=False)
    for c, cf in enumerate(fit.classes):
        assert cf.count == 150
        assert 0.88 <= cf.coverage95 <= 1.0, cf
        variances = np.diagonal(fit.model.cov(c, psi), axis1=1, axis2=2).mean(axis=0)
        assert_close(variances, [0.01, 0.01], rtol=0.3)
    # the mean follows ψ: class 1 is sharpest at its best view (90°), class 2 at −60°
    assert fit.model.mean(0, math.pi / 2)[0] > fit.model.mean(0, -math.pi / 2)[0] + 0.3
    assert fit.model.mean(1, -math.pi / 3)[1] > fit.model.mean(1, 2 * math.pi / 3)[1] + 0.3


def test_fit_refuses_a_class_with_too_few_samples() -> None:
    s = draw_samples(SHARP, 40, np.random.default_rng(5))
    few = ScoreSamples(np.where(np.arange(40) < 35, 0, 1), s.psi, s.z)
    with pytest.raises(UsageError, match="class 2 has 5 samples"):
        fit_classifier(few)


def test_sample_and_fit_commands_write_a_model_a_scenario_can_use(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["classifier", "sample", "paper", "-n", "60", "--seed", "3", "-o", "s.csv"]) == 0
    assert main(["classifier", "fit", "s.csv", "-o", "m.npz", "--truth", "paper"]) == 0
    printed = capsys.readouterr().out
    assert "wrote s.csv: 60 samples of the paper model" in printed
    assert "fit quality per score" in printed and "max |h − h_true|" in printed
    assert (tmp_path / "m.png").stat().st_size > 10_000
    model, _ = load_learned(tmp_path / "m.npz")
    assert model.num_classes == 2
    study = ["--set", 'classifier.estimator={model="learned", file="m.npz"}']
    assert main(["scenario", "show", "paper", *study]) == 0
    # an existing file is not replaced without --force
    assert main(["classifier", "sample", "paper", "-n", "5", "-o", "s.csv"]) == 2
    assert "already exists (--force overwrites it)" in capsys.readouterr().err


def test_fit_without_scikit_learn_names_the_extra(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    write_samples(draw_samples(SHARP, 30, np.random.default_rng(6)), tmp_path / "s.csv")
    monkeypatch.setitem(sys.modules, "sklearn.gaussian_process", None)  # import fails
    assert main(["classifier", "fit", str(tmp_path / "s.csv"), "-o", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (
        "semfleet: error: classifier fit needs scikit-learn: pip install 'semfleet[learn]'"
    )
    assert not (tmp_path / "m").exists()


def test_samples_stated_camera_to_object_learn_a_model_of_that_convention() -> None:
    """Samples written in the camera → object convention (ψ + π of semfleet's), learned and
    saved with that convention, reproduce the camera → object model at semfleet's ψ; read as
    object → camera they do not."""
    from dataclasses import replace

    truth = AliasedClassifier(SHARP.alias, SHARP.best_view, SHARP.sqrt_info, "camera_to_object")
    samples = draw_samples(truth, 300, np.random.default_rng(4), "camera_to_object")
    # class 1's best view is 90° in the samples' own ψ
    best = np.abs(samples.psi - math.pi / 2) < 0.3
    worst = np.abs(samples.psi + math.pi / 2) < 0.3
    ones = samples.classes == 0
    assert samples.z[best & ones, 0].mean() > samples.z[worst & ones, 0].mean() + 0.3
    fit = fit_classifier(samples, seed=0)
    right = truth_gap(replace(fit.model, viewpoint="camera_to_object"), truth)
    wrong = truth_gap(fit.model, truth)
    assert all(g.max_mean_error < 0.08 for g in right), right
    assert all(g.max_mean_error > 0.3 for g in wrong), wrong


def test_the_fit_command_records_the_samples_convention(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    view = ["--viewpoint", "camera_to_object"]
    assert main(["classifier", "sample", "paper", "-n", "60", "-o", "s.csv", *view]) == 0
    assert main(["classifier", "fit", "s.csv", "-o", "m.npz", "--truth", "paper", *view]) == 0
    assert "ψ camera_to_object" in " ".join(capsys.readouterr().out.split())
    model, _ = load_learned(tmp_path / "m.npz")
    assert model.viewpoint == "camera_to_object"
