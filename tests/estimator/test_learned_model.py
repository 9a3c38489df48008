"""The learned classifier model (estimator.models.learned): periodic GP maths, the likelihood of a
model built from the crafted one's values, and validation of a model file's arrays."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from estimator.hybrid import HybridBelief
from estimator.models import ClassifierModel, LearnedClassifier, paper_classifier
from estimator.models.classifier import all_log_likelihoods, gaussian_log_likelihood
from estimator.models.learned import LearnedModelError, PeriodicGP
from tests.estimator.exact_worlds import no_pruning
from tests.estimator.scenarios import tiny_scenario
from tests.tolerance import assert_close

GRID = np.linspace(-math.pi, math.pi, 24, endpoint=False)


def learned_copy(model: ClassifierModel, length_scale: float = 1.0) -> LearnedClassifier:
    """A learned model whose means interpolate ``model``'s on :data:`GRID` (noise-free GP),
    with ``model``'s covariance at ψ = 0 and a log scale of zero."""
    means = []
    for c in range(model.num_classes):
        h = model.mean(c, GRID)
        weights = [
            PeriodicGP.regression(GRID, h[:, i], GRID, length_scale, 1.0, 1e-12, 0.0).weights
            for i in range(model.dim)
        ]
        ls = np.full(model.dim, length_scale)
        means.append(PeriodicGP(GRID, np.concatenate(weights), ls, np.zeros(model.dim)))
    flat = PeriodicGP(GRID[:1], np.zeros((1, 1)), np.ones(1), np.zeros(1))
    covs = np.stack([model.cov(c, 0.0) for c in range(model.num_classes)])
    return LearnedClassifier(tuple(means), (flat,) * model.num_classes, covs)


def random_model(rng: np.random.Generator, m: int = 3, g: int = 9) -> LearnedClassifier:
    """A model with random means and a ψ-dependent covariance scale."""
    grid = np.sort(rng.uniform(-math.pi, math.pi, g))
    means = tuple(
        PeriodicGP(grid, rng.normal(0, 0.3, (m, g)), rng.uniform(0.5, 2.0, m), rng.normal(0, 1, m))
        for _ in range(m)
    )
    scales = tuple(
        PeriodicGP(
            grid, rng.normal(0, 0.2, (1, g)), rng.uniform(0.5, 2.0, 1), rng.normal(0, 0.3, 1)
        )
        for _ in range(m)
    )
    a = rng.normal(size=(m, m, m))
    covs = a @ np.swapaxes(a, 1, 2) + 0.5 * np.eye(m)
    return LearnedClassifier(means, scales, covs)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(2718)


def test_periodic_gp_is_periodic_in_psi(rng: np.random.Generator) -> None:
    model = random_model(rng)
    psi = rng.uniform(-math.pi, math.pi, 50)
    for c in range(3):
        for k in (-2, 1, 3):
            shifted = psi + 2 * math.pi * k
            assert_close(model.mean(c, shifted), model.mean(c, psi), atol=1e-12)
            assert_close(model.cov(c, shifted), model.cov(c, psi), rtol=1e-11)
            assert_close(model.mean_dpsi(c, shifted), model.mean_dpsi(c, psi), atol=1e-11)


def test_periodic_gp_dpsi_matches_finite_differences(rng: np.random.Generator) -> None:
    model = random_model(rng)
    psi, eps = rng.uniform(-4, 4, 20), 1e-6
    for c in range(3):
        numeric = (model.mean(c, psi + eps) - model.mean(c, psi - eps)) / (2 * eps)
        assert_close(model.mean_dpsi(c, psi), numeric, rtol=1e-6, atol=1e-7)


def test_mean_and_cov_broadcast_over_psi_shapes(rng: np.random.Generator) -> None:
    model = random_model(rng)
    assert model.mean(1, 0.3).shape == (3,) and model.mean_dpsi(1, 0.3).shape == (3,)
    assert model.mean(1, np.zeros((4, 5))).shape == (4, 5, 3)
    assert model.cov(2, np.zeros((4, 5))).shape == (4, 5, 3, 3)
    assert model.log_likelihood(np.zeros(3), 0, np.zeros((4, 5))).shape == (4, 5)
    assert model.log_likelihood(np.zeros((4, 5, 3)), 0, np.zeros((4, 5))).shape == (4, 5)


def test_log_likelihood_is_the_gaussian_of_mean_and_cov(rng: np.random.Generator) -> None:
    model = random_model(rng)
    psi = rng.uniform(-math.pi, math.pi, 40)
    z = rng.normal(size=(40, 3))
    for c in range(3):
        expected = gaussian_log_likelihood(z, model.mean(c, psi), model.cov(c, psi))
        assert_close(model.log_likelihood(z, c, psi), expected, rtol=1e-10)
    scale = model.scale(0, psi)
    assert np.ptp(scale) > 0.1, "the covariance should vary with ψ in this test"


def test_learned_copy_of_the_crafted_model_has_its_likelihood(rng: np.random.Generator) -> None:
    crafted = paper_classifier()
    learned = learned_copy(crafted)
    psi = rng.uniform(-math.pi, math.pi, (30, 4))
    z = rng.normal(0.5, 0.7, (4, 2))
    for c in range(2):
        assert_close(learned.mean(c, psi), crafted.mean(c, psi), atol=1e-9)
        assert_close(learned.mean_dpsi(c, psi), crafted.mean_dpsi(c, psi), atol=1e-8)
        assert_close(learned.cov(c, psi), crafted.cov(c, psi), rtol=1e-12)
    assert_close(
        all_log_likelihoods(learned, z, psi), all_log_likelihoods(crafted, z, psi), atol=1e-8
    )


def test_a_belief_with_the_learned_copy_matches_the_crafted_one() -> None:
    """The estimator uses a learned model through the same interface: the factor graph (Σ as a
    covariance instead of a square-root information) and the class weights agree."""
    from deploy.base.build import belief_model, belief_rng
    from sim.sensors import Simulator

    s = tiny_scenario([(2.0, 0.6, 60.0, 1), (3.0, -0.8, -100.0, 2)], steps=4)
    frames = Simulator(s, 5).frames("r1")
    crafted = belief_model(s)
    learned = dataclasses.replace(crafted, classifier=learned_copy(crafted.classifier))
    beliefs = []
    for model in (crafted, learned):
        belief = HybridBelief(model, {"r1": s.robot("r1").start}, no_pruning())
        rng = belief_rng(0, ["r1"])
        for f in frames:
            belief.step([f], rng)
        beliefs.append(belief)
    a, b = beliefs
    assert_close(b.class_marginals(), a.class_marginals(), atol=1e-6)
    assert a.class_marginals().min() < 0.45, "the evidence should move the marginals"


def test_regression_recovers_a_known_function_from_noisy_samples(
    rng: np.random.Generator,
) -> None:
    def h(psi: np.ndarray) -> np.ndarray:
        return 0.5 + 0.3 * np.cos(psi - 1.0) + 0.1 * np.sin(2 * psi)

    x = rng.uniform(-math.pi, math.pi, 300)
    y = h(x) + rng.normal(0, 0.1, x.size)
    grid = np.linspace(-math.pi, math.pi, 32, endpoint=False)
    gp = PeriodicGP.regression(x, y, grid, 1.0, 0.3, 0.01, float(np.mean(y)))
    psi = np.linspace(-math.pi, math.pi, 181)
    err = np.abs(gp(psi)[:, 0] - h(psi))
    assert err.max() < 0.05, err.max()  # measured 0.02 for this seed
    assert_close(gp(psi + 2 * math.pi), gp(psi), atol=1e-12)


def test_arrays_round_trip_to_an_equal_model(rng: np.random.Generator) -> None:
    model = random_model(rng)
    back = LearnedClassifier.from_arrays(model.to_arrays())
    psi = rng.uniform(-4, 4, 25)
    z = rng.normal(size=3)
    for c in range(3):
        assert_close(back.log_likelihood(z, c, psi), model.log_likelihood(z, c, psi), rtol=0)
        assert_close(back.mean_dpsi(c, psi), model.mean_dpsi(c, psi), rtol=0)


def _broken(arrays: dict[str, Any], name: str, value: Any) -> dict[str, Any]:
    out = dict(arrays)
    if value is None:
        del out[name]
    else:
        out[name] = value(out[name]) if callable(value) else value
    return out


def _nan_at_first(a: np.ndarray) -> np.ndarray:
    b = np.array(a, dtype=float)
    b.flat[0] = np.nan
    return b


def _asymmetric(a: np.ndarray) -> np.ndarray:
    b = np.array(a)
    b[1, 0, 1] += 0.5
    return b


def _indefinite(a: np.ndarray) -> np.ndarray:
    b = np.array(a)
    b[0] = -b[0]
    return b


BAD = [
    ("missing", "mean_weights", None, "missing"),
    ("unknown", "colour", np.array(1.0), "unknown field"),
    ("format", "format", np.array("something-else"), "expected the string"),
    ("version", "version", np.array(2), "unsupported version 2"),
    ("version-type", "version", np.array(1.5), "expected one integer"),
    ("nan", "mean_weights", _nan_at_first, "NaN"),
    ("inf", "mean_offset", lambda a: a + np.inf, "NaN or an infinity"),
    ("object-dtype", "mean_offset", lambda a: a.astype(object), "expected numbers"),
    ("wrong-shape", "noise_cov", lambda a: a[:, :2, :2], "expected shape (3, 3, 3)"),
    ("class-count", "scale_inducing", lambda a: a[:2], "2 classes, the model has 3"),
    ("one-class", "mean_inducing", lambda a: a[:1], "1 classes, expected 2..64"),
    ("asymmetric", "noise_cov", _asymmetric, "not symmetric"),
    ("indefinite", "noise_cov", _indefinite, "not positive definite"),
    ("length-scale", "mean_length_scale", lambda a: a * 0.0, "length scale must be in"),
    ("log-scale", "scale_weights", lambda a: a + 10.0, "beyond ±30"),
    ("dims", "mean_weights", lambda a: a[None], "expected 3 dimensions"),
    ("viewpoint", "viewpoint", np.array("camera"), "expected one of the strings"),
    ("viewpoint-type", "viewpoint", np.array(3.14), "expected one of the strings"),
]


@pytest.mark.parametrize(("name", "field", "value", "reason"), BAD, ids=[b[0] for b in BAD])
def test_from_arrays_refuses_bad_arrays_naming_the_field(
    rng: np.random.Generator, name: str, field: str, value: Any, reason: str
) -> None:
    arrays = _broken(random_model(rng).to_arrays(), field, value)
    with pytest.raises(LearnedModelError) as info:
        LearnedClassifier.from_arrays(arrays)
    message = str(info.value)
    where = "noise_cov[" if field == "noise_cov" and name != "wrong-shape" else field
    assert message.startswith(where), message
    assert reason in message, message
    assert "\n" not in message


@pytest.mark.parametrize("convention", ["object_to_camera", "camera_to_object"])
def test_a_learned_model_records_its_viewpoint_convention(
    rng: np.random.Generator, convention: str
) -> None:
    """The file keeps the convention; a file without the field (before it existed) reads as
    object → camera; a camera → object model at semfleet's ψ is the same GPs at ψ + π."""
    plain = random_model(rng)
    model = replace(plain, viewpoint=convention)
    arrays = model.to_arrays()
    assert str(arrays["viewpoint"]) == convention
    assert LearnedClassifier.from_arrays(arrays).viewpoint == convention
    del arrays["viewpoint"]
    assert LearnedClassifier.from_arrays(arrays).viewpoint == "object_to_camera"
    turn = math.pi if convention == "camera_to_object" else 0.0
    psi = rng.uniform(-4, 4, 25)
    z = rng.normal(size=3)
    for c in range(3):
        assert_close(model.mean(c, psi), plain.mean(c, psi + turn), atol=1e-12)
        assert_close(model.mean_dpsi(c, psi), plain.mean_dpsi(c, psi + turn), atol=1e-12)
        assert_close(model.cov(c, psi), plain.cov(c, psi + turn), atol=1e-12)
        assert_close(
            model.log_likelihood(z, c, psi), plain.log_likelihood(z, c, psi + turn), atol=1e-9
        )
