"""Classifier models (Eq. 1): the paper model, the aliased family, the M−1 marginal and ψ."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from scipy.stats import multivariate_normal

from estimator.models import (
    AliasedClassifier,
    ClassifierModel,
    FirstComponents,
    paper_classifier,
    viewpoint,
)
from estimator.models.classifier import PAPER_SQRT_INFO, gaussian_log_likelihood
from tests.tolerance import assert_angles_close, assert_close

PSI_SHAPES = [(50,), (4, 5)]


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(314159)


@pytest.fixture
def paper() -> AliasedClassifier:
    return paper_classifier()


def _separation(model: ClassifierModel, psi: float) -> float:
    """½ ΔhᵀΣ⁻¹Δh between the means of classes 0 and 1 at ψ (nats)."""
    dh = model.mean(0, psi) - model.mean(1, psi)
    return float(0.5 * dh @ np.linalg.solve(model.cov(0, psi), dh))


def _scipy_log_likelihood(
    model: ClassifierModel, z: np.ndarray, c: int, psi: np.ndarray
) -> np.ndarray:
    """Per-sample scipy reference: z (..., d) and ψ (...) of the same leading shape → (...)."""
    out = np.empty(psi.shape)
    for idx in np.ndindex(*psi.shape):
        p = float(psi[idx])
        out[idx] = multivariate_normal.logpdf(z[idx], model.mean(c, p), model.cov(c, p))
    return out


def test_paper_classifier_means_at_best_and_worst_view(paper: AliasedClassifier) -> None:
    up, down = math.radians(90.0), math.radians(-90.0)
    assert_close(paper.mean(0, up), [1.0, 0.0], atol=1e-12, what="h_1(90°)")
    assert_close(paper.mean(1, up), [0.0, 1.0], atol=1e-12, what="h_2(90°)")
    assert_close(paper.mean(0, down), [0.5, 0.5], atol=1e-12, what="h_1(−90°)")
    assert_close(paper.mean(1, down), [0.5, 0.5], atol=1e-12, what="h_2(−90°)")


def test_paper_classifier_means_follow_design_formula(
    paper: AliasedClassifier, rng: np.random.Generator
) -> None:
    psi = rng.uniform(-np.pi, np.pi, 100)
    s = np.sin(psi)
    h1 = np.column_stack([0.25 * s + 0.75, 0.25 * (1.0 - s)])
    h2 = np.column_stack([0.25 * (1.0 - s), 0.25 * s + 0.75])
    assert_close(paper.mean(0, psi), h1, what="h_1(ψ)")
    assert_close(paper.mean(1, psi), h2, what="h_2(ψ)")


@pytest.mark.parametrize(
    ("psi_deg", "nats"), [(-90.0, 0.0), (-45.0, 0.08), (0.0, 0.91), (45.0, 2.66), (90.0, 3.66)]
)
def test_paper_classifier_separation_matches_design_doc(
    paper: AliasedClassifier, psi_deg: float, nats: float
) -> None:
    assert round(_separation(paper, math.radians(psi_deg)), 2) == nats


def test_paper_classifier_covariance_is_paper_sqrt_info(paper: AliasedClassifier) -> None:
    r = np.array([[1.5, -0.75], [0.0, 1.5]])
    assert_close(paper.sqrt_info, r, what="R")
    assert_close(PAPER_SQRT_INFO, r, what="PAPER_SQRT_INFO")
    assert paper.alias == (1, 0)
    assert paper.num_classes == 2
    assert paper.dim == 2


@pytest.mark.parametrize("shape", [(), *PSI_SHAPES])
def test_cov_equals_inverse_information(
    paper: AliasedClassifier, rng: np.random.Generator, shape: tuple[int, ...]
) -> None:
    psi = rng.uniform(-np.pi, np.pi, shape)
    expected = np.linalg.inv(paper.sqrt_info.T @ paper.sqrt_info)
    for c in range(2):
        cov = paper.cov(c, psi)
        assert cov.shape == (*shape, 2, 2)
        assert_close(cov, np.broadcast_to(expected, cov.shape), what=f"Σ_{c}")


def test_cov_returns_writable_copy(paper: AliasedClassifier) -> None:
    cov = paper.cov(0, np.zeros(3))
    cov[0, 0, 0] = 99.0
    assert paper.cov(0, 0.0)[0, 0] != 99.0


@pytest.mark.parametrize("shape", [(), *PSI_SHAPES])
def test_mean_shape_follows_psi(paper: AliasedClassifier, shape: tuple[int, ...]) -> None:
    assert paper.mean(0, np.zeros(shape)).shape == (*shape, 2)


@pytest.mark.parametrize("shape", PSI_SHAPES)
@pytest.mark.parametrize("c", [0, 1])
def test_log_likelihood_matches_scipy(
    paper: AliasedClassifier, rng: np.random.Generator, shape: tuple[int, ...], c: int
) -> None:
    psi = rng.uniform(-np.pi, np.pi, shape)
    z = rng.normal(0.5, 0.8, (*shape, 2))
    got = paper.log_likelihood(z, c, psi)
    assert got.shape == shape
    assert_close(got, _scipy_log_likelihood(paper, z, c, psi), rtol=1e-12, atol=1e-12, what="log N")


@pytest.mark.parametrize("shape", PSI_SHAPES)
def test_log_likelihood_broadcasts_one_score_over_psi(
    paper: AliasedClassifier, rng: np.random.Generator, shape: tuple[int, ...]
) -> None:
    psi = rng.uniform(-np.pi, np.pi, shape)
    z = rng.normal(0.5, 0.8, 2)
    got = paper.log_likelihood(z, 1, psi)
    expected = _scipy_log_likelihood(paper, np.broadcast_to(z, (*shape, 2)), 1, psi)
    assert_close(got, expected, rtol=1e-12, atol=1e-12, what="log N, one z")


def test_log_likelihood_of_random_model_matches_scipy(rng: np.random.Generator) -> None:
    model = AliasedClassifier.random(5, rng)
    psi = rng.uniform(-np.pi, np.pi, (4, 5))
    z = rng.normal(0.3, 0.5, (4, 5, 5))
    for c in range(5):
        expected = _scipy_log_likelihood(model, z, c, psi)
        assert_close(model.log_likelihood(z, c, psi), expected, rtol=1e-12, what=f"class {c}")


def test_log_likelihood_with_full_sqrt_info_matches_scipy(rng: np.random.Generator) -> None:
    r = np.triu(rng.normal(size=(3, 3))) + 2.0 * np.eye(3)
    model = AliasedClassifier((2, 0, 1), (0.3, -1.0, 2.0), r)
    psi = rng.uniform(-np.pi, np.pi, 50)
    z = rng.normal(0.3, 0.5, (50, 3))
    for c in range(3):
        expected = _scipy_log_likelihood(model, z, c, psi)
        assert_close(model.log_likelihood(z, c, psi), expected, rtol=1e-12, what=f"class {c}")


def test_gaussian_log_likelihood_matches_scipy(rng: np.random.Generator) -> None:
    a = rng.normal(size=(20, 3, 3))
    cov = a @ np.swapaxes(a, -1, -2) + 0.1 * np.eye(3)
    mean, z = rng.normal(size=(20, 3)), rng.normal(size=(20, 3))
    expected = [multivariate_normal.logpdf(z[i], mean[i], cov[i]) for i in range(20)]
    assert_close(gaussian_log_likelihood(z, mean, cov), expected, rtol=1e-10, what="log N")


@pytest.mark.parametrize("num_classes", [2, 4])
@pytest.mark.parametrize("shape", PSI_SHAPES)
def test_first_components_is_exact_marginal(
    rng: np.random.Generator, num_classes: int, shape: tuple[int, ...]
) -> None:
    full = paper_classifier() if num_classes == 2 else AliasedClassifier.random(num_classes, rng)
    marginal = FirstComponents(full)
    assert marginal.dim == num_classes - 1
    assert marginal.num_classes == num_classes
    psi = rng.uniform(-np.pi, np.pi, shape)
    z = rng.normal(0.4, 0.6, (*shape, num_classes - 1))
    for c in range(num_classes):
        expected = np.empty(shape)
        for idx in np.ndindex(*shape):
            p = float(psi[idx])
            mean, cov = full.mean(c, p)[:-1], full.cov(c, p)[:-1, :-1]
            expected[idx] = multivariate_normal.logpdf(z[idx], mean, cov)
        got = marginal.log_likelihood(z, c, psi)
        assert got.shape == shape
        assert_close(got, expected, rtol=1e-12, atol=1e-12, what=f"marginal, class {c}")


def test_first_components_mean_and_cov_drop_last_component(paper: AliasedClassifier) -> None:
    marginal = FirstComponents(paper)
    psi = np.linspace(-3.0, 3.0, 7)
    assert_close(marginal.mean(0, psi), paper.mean(0, psi)[:, :1], what="mean")
    assert_close(marginal.cov(1, psi), paper.cov(1, psi)[:, :1, :1], what="cov")


@pytest.mark.parametrize(
    ("alias", "best_view", "sqrt_info", "match"),
    [
        ((0, 1), (0.0, 0.0), np.eye(2), "alias"),
        ((1, 1), (0.0, 0.0), np.eye(2), "alias"),
        ((1, 2), (0.0, 0.0), np.eye(2), "alias"),
        ((1, -1), (0.0, 0.0), np.eye(2), "alias"),
        ((1, 0), (0.0,), np.eye(2), "best_view"),
        ((1, 0), (0.0, 0.0, 0.0), np.eye(2), "best_view"),
        ((1, 0), (0.0, math.nan), np.eye(2), "best_view"),
        ((1, 0), (0.0, math.inf), np.eye(2), "best_view"),
        ((1, 0), (0.0, 0.0), np.array([[1.0, 2.0], [0.5, 1.0]]), "invertible"),
        ((1, 0), (0.0, 0.0), np.zeros((2, 2)), "invertible"),
        ((1, 0), (0.0, 0.0), np.eye(3), "sqrt_info"),
        ((1, 0), (0.0, 0.0), np.array([[1.0, math.nan], [0.0, 1.0]]), "sqrt_info"),
        ((0,), (0.0,), np.eye(1), "two classes"),
    ],
)
def test_aliased_classifier_rejects_invalid_parameters(
    alias: tuple[int, ...], best_view: tuple[float, ...], sqrt_info: np.ndarray, match: str
) -> None:
    with pytest.raises(ValueError, match=match):
        AliasedClassifier(alias, best_view, sqrt_info)


@pytest.mark.parametrize("c", [-1, 2])
def test_aliased_classifier_rejects_class_out_of_range(paper: AliasedClassifier, c: int) -> None:
    for method in (paper.mean, paper.cov, paper.sharpness):
        with pytest.raises(ValueError, match="out of range"):
            method(c, 0.0)
    with pytest.raises(ValueError, match="out of range"):
        paper.log_likelihood(np.zeros(2), c, 0.0)


def test_aliased_classifier_freezes_sqrt_info() -> None:
    r = np.eye(2)
    model = AliasedClassifier((1, 0), (0.0, 0.0), r)
    r[0, 0] = 5.0
    assert model.sqrt_info[0, 0] == 1.0
    with pytest.raises(ValueError):
        model.sqrt_info[0, 0] = 2.0


@pytest.mark.parametrize("num_classes", [2, 3, 5, 10])
def test_aliased_classifier_random_is_valid(num_classes: int) -> None:
    rng = np.random.default_rng(num_classes)
    model = AliasedClassifier.random(num_classes, rng, noise_std=0.2)
    assert isinstance(model, ClassifierModel)
    assert model.num_classes == num_classes
    assert model.dim == num_classes
    assert len(model.best_view) == num_classes
    assert all(-math.pi <= b <= math.pi for b in model.best_view)
    assert all(0 <= a < num_classes and a != c for c, a in enumerate(model.alias))
    assert_close(model.sqrt_info, np.eye(num_classes) / 0.2, what="sqrt_info")
    eye = np.eye(num_classes)
    for c in range(num_classes):
        best = model.best_view[c]
        assert_close(model.mean(c, best), eye[c], atol=1e-12, what=f"h_{c} at best view")
        blurred = 0.5 * (eye[c] + eye[model.alias[c]])
        assert_close(model.mean(c, best + math.pi), blurred, atol=1e-12, what=f"h_{c} opposite")


def test_aliased_classifier_random_is_reproducible() -> None:
    a = AliasedClassifier.random(6, np.random.default_rng(11))
    b = AliasedClassifier.random(6, np.random.default_rng(11))
    assert a.alias == b.alias
    assert a.best_view == b.best_view


def test_aliased_classifier_random_rejects_one_class() -> None:
    with pytest.raises(ValueError):
        AliasedClassifier.random(1, np.random.default_rng(0))


def test_sharpness_is_one_at_best_view_and_zero_opposite(paper: AliasedClassifier) -> None:
    assert_close(paper.sharpness(0, math.pi / 2), 1.0, what="s at best view")
    assert_close(paper.sharpness(0, -math.pi / 2), 0.0, atol=1e-15, what="s opposite")


def test_paper_classifier_satisfies_protocol(paper: AliasedClassifier) -> None:
    assert isinstance(paper, ClassifierModel)
    assert isinstance(FirstComponents(paper), ClassifierModel)


def _gtsam_viewpoint(robot: np.ndarray, obj: np.ndarray) -> float:
    r, o = gtsam.Pose2(*map(float, robot)), gtsam.Pose2(*map(float, obj))
    p = o.inverse().compose(r).translation()
    return math.atan2(p[1], p[0])


def test_viewpoint_matches_gtsam(rng: np.random.Generator) -> None:
    robot = np.column_stack([rng.uniform(-10, 10, (200, 2)), rng.uniform(-np.pi, np.pi, 200)])
    obj = np.column_stack([rng.uniform(-10, 10, (200, 2)), rng.uniform(-np.pi, np.pi, 200)])
    expected = [_gtsam_viewpoint(r, o) for r, o in zip(robot, obj, strict=True)]
    got = viewpoint(robot, obj)
    assert got.shape == (200,)
    assert_angles_close(got, expected, atol=1e-12, what="ψ")


def test_viewpoint_broadcasts_robots_over_objects(rng: np.random.Generator) -> None:
    robot = np.concatenate([rng.uniform(-10, 10, (5, 7, 2)), rng.uniform(-3, 3, (5, 7, 1))], -1)
    obj = np.concatenate([rng.uniform(-10, 10, (7, 2)), rng.uniform(-3, 3, (7, 1))], -1)
    got = viewpoint(robot, obj)
    assert got.shape == (5, 7)
    expected = np.array(
        [[_gtsam_viewpoint(robot[i, j], obj[j]) for j in range(7)] for i in range(5)]
    )
    assert_angles_close(got, expected, atol=1e-12, what="ψ")


@pytest.mark.parametrize(
    ("robot_xy", "psi_deg"), [((1.0, 0.0), 0.0), ((0.0, 1.0), 90.0), ((-1.0, 0.0), 180.0)]
)
def test_viewpoint_is_azimuth_in_object_frame(
    robot_xy: tuple[float, float], psi_deg: float
) -> None:
    # An object at (2, 3) facing +y: its x axis is world +y, its y axis world −x.
    obj = np.array([2.0, 3.0, math.pi / 2])
    rx, ry = robot_xy
    robot = np.array([2.0 - ry, 3.0 + rx, 1.234])  # the heading of the robot must not matter
    assert_angles_close(viewpoint(robot, obj), math.radians(psi_deg), atol=1e-12, what="ψ")


@pytest.mark.parametrize("c", [0, 1])
def test_mean_dpsi_matches_central_difference(c: int) -> None:
    psi = np.linspace(-np.pi, np.pi, 41)
    h = 1e-6
    for model in (paper_classifier(), FirstComponents(paper_classifier())):
        numeric = (model.mean(c, psi + h) - model.mean(c, psi - h)) / (2 * h)
        assert_close(model.mean_dpsi(c, psi), numeric, rtol=0.0, atol=1e-8, what="dh/dψ")


# -- the viewpoint convention --------------------------------------------------------------------


def _turned(model: AliasedClassifier) -> AliasedClassifier:
    """The same model in the other convention: camera → object with every best view turned by π
    is object → camera (and the other way round)."""
    other = "camera_to_object" if model.viewpoint == "object_to_camera" else "object_to_camera"
    turn = math.pi if other == "camera_to_object" else -math.pi
    best = tuple(b - turn for b in model.best_view)
    return AliasedClassifier(model.alias, best, model.sqrt_info, other)


@pytest.mark.parametrize("seed", range(3))
def test_a_camera_to_object_model_is_the_object_to_camera_model_turned_by_pi(seed: int) -> None:
    """Every method of a camera → object model (random M = 4, non-uniform noise) equals the
    object → camera model whose best views are turned by π: mean, its derivative, sharpness,
    components, and the log-likelihoods, vectorised and scalar."""
    rng = np.random.default_rng(seed)
    base = AliasedClassifier.random(4, rng)
    r = np.triu(rng.normal(0.0, 0.3, (4, 4))) + np.diag(rng.uniform(1.0, 3.0, 4))
    c2o = AliasedClassifier(base.alias, base.best_view, r, "camera_to_object")
    o2c = _turned(c2o)
    assert o2c.viewpoint == "object_to_camera"
    psi = rng.uniform(-np.pi, np.pi, (6, 5))
    z = rng.normal(0.4, 0.5, (5, 4))
    for c in range(4):
        assert_close(c2o.mean(c, psi), o2c.mean(c, psi), atol=1e-12)
        assert_close(c2o.mean_dpsi(c, psi), o2c.mean_dpsi(c, psi), atol=1e-12)
        assert_close(c2o.sharpness(c, psi), o2c.sharpness(c, psi), atol=1e-12)
        assert_close(c2o.mean(c, 0.7), o2c.mean(c, 0.7), atol=1e-12)  # the scalar path
        assert_close(c2o.mean_dpsi(c, 0.7), o2c.mean_dpsi(c, 0.7), atol=1e-12)
        assert_close(c2o.log_likelihood(z[0], c, psi), o2c.log_likelihood(z[0], c, psi), atol=1e-9)
        assert_angles_close(c2o.components(c)[2], o2c.components(c)[2], atol=1e-12)
    assert_close(c2o.log_likelihoods(z, psi), o2c.log_likelihoods(z, psi), atol=1e-9)
    # and it is a different model from the same numbers read object → camera
    same_numbers = AliasedClassifier(base.alias, base.best_view, r)
    assert not np.allclose(c2o.mean(0, psi), same_numbers.mean(0, psi))


@pytest.mark.parametrize("seed", range(3))
def test_camera_to_object_is_the_paper_authors_viewpoint(seed: int) -> None:
    """The paper's authors' score generator (VovaTch/MH_and_JLP_inference_and_planning,
    tests/basic_lambda_test.py) takes ψ = atan2(−rel.y, −rel.x), rel = object.between(camera):
    the direction from the camera to the object in the object's frame. A camera → object model
    fed semfleet's ψ (object → camera) gives the paper model's scores at that ψ."""
    rng = np.random.default_rng(seed)
    c2o = paper_classifier("camera_to_object")
    plain = paper_classifier()
    for _ in range(20):
        obj = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)])
        cam = np.array([*rng.uniform(-5, 5, 2), rng.uniform(-np.pi, np.pi)])
        rel = gtsam.Pose2(*obj).between(gtsam.Pose2(*cam))
        authors = math.atan2(-rel.y(), -rel.x())
        ours = float(viewpoint(cam, obj))
        for c in range(2):
            assert_close(c2o.mean(c, ours), plain.mean(c, authors), atol=1e-12)


def test_an_unknown_viewpoint_convention_is_refused() -> None:
    with pytest.raises(ValueError, match="viewpoint 'camera'"):
        AliasedClassifier((1, 0), (0.0, 0.0), np.eye(2), "camera")
