"""Vectorised SE(2) against gtsam.Pose2, on random poses that include the edge cases of the maps.

GTSAM's closed-form Expmap/Logmap compute ``1 − cos θ`` directly, so for 1e-10 < |θ| ≲ 1e-5 they
lose ~ε/|θ| of absolute accuracy per unit length; the comparisons with GTSAM allow exactly that, and
an independent cancellation-free reference (``2 sin²(θ/2)/θ``, ``(θ/2) cos(θ/2)/sin(θ/2)``) checks
those angles tightly.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimator.models import se2
from tests.tolerance import assert_angles_close, assert_close

N = 200
Vec3 = tuple[float, float, float]
EPS = float(np.finfo(float).eps)


def _angles(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n,) angles in five equal groups: uniform; within 1e-9..1e-3 of ±π; small (1e-5..1e-1);
    tiny (1e-11..1e-5, both sides of the 1e-6 series switch); ~1e-8, every fifth exactly 0."""
    q = n // 5
    uniform = rng.uniform(-np.pi, np.pi, n - 4 * q)
    sign = rng.choice([-1.0, 1.0], size=4 * q)
    near_pi = sign[:q] * (np.pi - 10.0 ** rng.uniform(-9, -3, q))
    small = sign[q : 2 * q] * 10.0 ** rng.uniform(-5, -1, q)
    tiny = sign[2 * q : 3 * q] * 10.0 ** rng.uniform(-11, -5, q)
    very_tiny = sign[3 * q :] * 10.0 ** rng.uniform(-8.5, -7.5, q)
    very_tiny[::5] = 0.0
    return rng.permutation(np.concatenate([uniform, near_pi, small, tiny, very_tiny]))


def _poses(rng: np.random.Generator, n: int = N) -> np.ndarray:
    """(n, 3) poses with |x|, |y| ≤ 10 and the angles of :func:`_angles`."""
    return np.column_stack([rng.uniform(-10, 10, (n, 2)), _angles(rng, n)])


def _pose2(p: np.ndarray) -> gtsam.Pose2:
    return gtsam.Pose2(float(p[0]), float(p[1]), float(p[2]))


def _array(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


def _assert_poses_close(actual: np.ndarray, expected: np.ndarray, atol: float, what: str) -> None:
    assert_close(actual[..., :2], expected[..., :2], rtol=0.0, atol=atol, what=f"{what}: x, y")
    assert_angles_close(actual[..., 2], expected[..., 2], atol=atol, what=f"{what}: θ")


def _atol_vs_gtsam(theta: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """(n, 1) tolerance per row against GTSAM's Expmap/Logmap: its cancellation error
    ~ε·(1 + |x| + |y|)/|θ| where 1e-10 < |θ| < 1e-5 (module docstring), else 1e-9."""
    theta = np.abs(np.asarray(theta))
    small = (theta > 0) & (theta < 1e-5)
    size = 1.0 + np.abs(xy).sum(axis=-1)
    cancellation = 8.0 * EPS * size / np.where(small, theta, 1.0)
    return (1e-9 + np.where(small, cancellation, 0.0))[:, None]


def _assert_rows_within(got: np.ndarray, expected: np.ndarray, atol: np.ndarray, what: str) -> None:
    err = np.abs(got - expected)
    bad = np.flatnonzero(np.any(err > atol, axis=-1))
    if bad.size:
        i = bad[0]
        raise AssertionError(
            f"{what}: {bad.size} rows differ; row {i}: got {got[i]}, expected {expected[i]}, "
            f"tolerance {atol[i]}"
        )


def _expmap_reference(v: np.ndarray) -> np.ndarray:
    """Expmap of one tangent vector (3,) without cancellation, in plain floats."""
    vx, vy, w = (float(c) for c in v)
    if w == 0.0:
        return np.array([vx, vy, 0.0])
    a = math.sin(w) / w
    b = 2.0 * math.sin(w / 2.0) ** 2 / w  # (1 − cos w)/w
    return np.array([a * vx - b * vy, b * vx + a * vy, w])


def _logmap_reference(p: np.ndarray) -> np.ndarray:
    """Logmap of one pose (3,) with θ in (−π, π), without cancellation."""
    x, y, t = (float(c) for c in p)
    half = t / 2.0
    a = 1.0 if t == 0.0 else half * math.cos(half) / math.sin(half)
    return np.array([a * x + half * y, -half * x + a * y, t])


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20240611)


def test_wrap_angle_maps_into_half_open_range(rng: np.random.Generator) -> None:
    theta = np.concatenate([rng.uniform(-50, 50, 1000), np.arange(-5, 6) * np.pi])
    wrapped = se2.wrap_angle(theta)
    assert wrapped.shape == theta.shape
    assert np.all(wrapped >= -np.pi)
    assert np.all(wrapped < np.pi)
    assert_angles_close(wrapped, theta, atol=1e-12, what="wrap_angle changes the angle")


def test_wrap_angle_sends_pi_to_minus_pi() -> None:
    assert se2.wrap_angle(np.pi) == -np.pi
    assert se2.wrap_angle(-np.pi) == -np.pi


def test_wrap_angle_keeps_shape_of_scalars_and_stacks() -> None:
    assert se2.wrap_angle(0.5).shape == ()
    assert se2.wrap_angle(np.zeros((4, 5))).shape == (4, 5)


def test_wrap_angle_stays_below_pi_just_under_minus_pi() -> None:
    theta = np.nextafter(-np.pi, -4.0)  # −3.1415926535897936
    assert se2.wrap_angle(theta) < np.pi


def test_wrap_angle_leaves_in_range_angles_unchanged() -> None:
    theta = np.array([1e-8, -3e-9, 1e-20, 2.5, -1.0])
    np.testing.assert_array_equal(se2.wrap_angle(theta), theta)


def test_compose_matches_gtsam(rng: np.random.Generator) -> None:
    a, b = _poses(rng), _poses(rng)
    expected = np.array([_array(_pose2(p).compose(_pose2(q))) for p, q in zip(a, b, strict=True)])
    _assert_poses_close(se2.compose(a, b), expected, atol=1e-9, what="compose")


def test_inverse_matches_gtsam(rng: np.random.Generator) -> None:
    a = _poses(rng)
    expected = np.array([_array(_pose2(p).inverse()) for p in a])
    _assert_poses_close(se2.inverse(a), expected, atol=1e-9, what="inverse")


def test_between_matches_gtsam(rng: np.random.Generator) -> None:
    a, b = _poses(rng), _poses(rng)
    expected = np.array([_array(_pose2(p).between(_pose2(q))) for p, q in zip(a, b, strict=True)])
    _assert_poses_close(se2.between(a, b), expected, atol=1e-9, what="between")


def test_between_equals_inverse_then_compose(rng: np.random.Generator) -> None:
    a, b = _poses(rng), _poses(rng)
    _assert_poses_close(
        se2.between(a, b), se2.compose(se2.inverse(a), b), atol=1e-9, what="between"
    )


def test_transform_to_matches_gtsam(rng: np.random.Generator) -> None:
    a, pts = _poses(rng), rng.uniform(-20, 20, (N, 2))
    expected = np.array([_pose2(p).transformTo(q) for p, q in zip(a, pts, strict=True)])
    assert_close(se2.transform_to(a, pts), expected, rtol=0.0, atol=1e-9, what="transform_to")


def test_transform_from_matches_gtsam(rng: np.random.Generator) -> None:
    a, pts = _poses(rng), rng.uniform(-20, 20, (N, 2))
    expected = np.array([_pose2(p).transformFrom(q) for p, q in zip(a, pts, strict=True)])
    assert_close(se2.transform_from(a, pts), expected, rtol=0.0, atol=1e-9, what="transform_from")


def test_transform_from_inverts_transform_to(rng: np.random.Generator) -> None:
    a, pts = _poses(rng), rng.uniform(-20, 20, (N, 2))
    back = se2.transform_from(a, se2.transform_to(a, pts))
    assert_close(back, pts, rtol=0.0, atol=1e-12, what="transform_from ∘ transform_to")


def _tangents(rng: np.random.Generator, n: int = N) -> np.ndarray:
    """(n, 3) tangent vectors; ω from :func:`_angles`, plus a few beyond ±π."""
    omega = _angles(rng, n)
    omega[:10] = rng.uniform(np.pi, 2.5 * np.pi, 10) * rng.choice([-1.0, 1.0], 10)
    return np.column_stack([rng.uniform(-3, 3, (n, 2)), omega])


def test_expmap_matches_gtsam(rng: np.random.Generator) -> None:
    v = _tangents(rng)
    expected = np.array([_array(gtsam.Pose2.Expmap(w)) for w in v])
    got = se2.expmap(v)
    atol = _atol_vs_gtsam(v[:, 2], v[:, :2])
    _assert_rows_within(got[:, :2], expected[:, :2], atol, "expmap x, y")
    assert_angles_close(got[:, 2], expected[:, 2], atol=1e-12, what="expmap θ")


def test_expmap_matches_cancellation_free_reference(rng: np.random.Generator) -> None:
    v = _tangents(rng)
    expected = np.array([_expmap_reference(w) for w in v])
    got = se2.expmap(v)
    _assert_rows_within(got[:, :2], expected[:, :2], np.full((len(v), 1), 1e-13), "expmap x, y")
    assert_angles_close(got[:, 2], expected[:, 2], atol=1e-12, what="expmap θ")


def test_expmap_is_accurate_just_above_series_switch() -> None:
    v = np.array([[0.0, 1.0, w] for w in (1.0000001e-6, 1.3e-6, 3e-6, 1e-5)])
    expected = np.array([_expmap_reference(w) for w in v])
    assert_close(se2.expmap(v), expected, rtol=1e-12, atol=0.0, what="expmap")


def test_logmap_matches_gtsam(rng: np.random.Generator) -> None:
    p = _poses(rng)
    expected = np.array([gtsam.Pose2.Logmap(_pose2(q)) for q in p])
    _assert_rows_within(se2.logmap(p), expected, _atol_vs_gtsam(p[:, 2], p[:, :2]), "logmap")


def test_logmap_matches_cancellation_free_reference(rng: np.random.Generator) -> None:
    p = _poses(rng)
    expected = np.array([_logmap_reference(q) for q in p])
    # Near ±π, (θ/2)·cot(θ/2) → 0 while x, y ≤ 10, so the error is absolute, not relative.
    assert_close(se2.logmap(p), expected, rtol=1e-12, atol=1e-12, what="logmap")


def test_logmap_returns_minus_pi_at_half_turn() -> None:
    v = se2.logmap(np.array([1.0, 2.0, np.pi]))
    assert v[2] == -np.pi
    _assert_poses_close(se2.expmap(v), np.array([1.0, 2.0, np.pi]), atol=1e-12, what="round trip")


def test_logmap_wraps_angles_outside_range(rng: np.random.Generator) -> None:
    p = _poses(rng)
    shifted = p + np.array([0.0, 0.0, 4.0 * np.pi])
    assert_close(se2.logmap(shifted), se2.logmap(p), rtol=0.0, atol=1e-9, what="logmap")


def test_expmap_and_logmap_are_exact_at_zero() -> None:
    assert_close(se2.expmap(np.array([1.0, -2.0, 0.0])), [1.0, -2.0, 0.0], what="expmap(0)")
    assert_close(se2.logmap(np.array([1.0, -2.0, 0.0])), [1.0, -2.0, 0.0], what="logmap(0)")


def test_retract_matches_gtsam(rng: np.random.Generator) -> None:
    p, v = _poses(rng), _tangents(rng)
    expected = np.array([_array(_pose2(q).retract(w)) for q, w in zip(p, v, strict=True)])
    got = se2.retract(p, v)
    atol = _atol_vs_gtsam(v[:, 2], v[:, :2])
    _assert_rows_within(got[:, :2], expected[:, :2], atol, "retract x, y")
    assert_angles_close(got[:, 2], expected[:, 2], atol=1e-9, what="retract θ")


def test_local_matches_gtsam(rng: np.random.Generator) -> None:
    p, q = _poses(rng), _poses(rng)
    # Make half of the pairs close, so that the relative angle is tiny or near zero.
    q[::2] = se2.retract(p[::2], _tangents(rng, N // 2) * np.array([1.0, 1.0, 1e-3]))
    expected = np.array([_pose2(a).localCoordinates(_pose2(b)) for a, b in zip(p, q, strict=True)])
    rel = se2.between(p, q)
    _assert_rows_within(se2.local(p, q), expected, _atol_vs_gtsam(rel[:, 2], rel[:, :2]), "local")


def test_retract_inverts_local(rng: np.random.Generator) -> None:
    p, q = _poses(rng), _poses(rng)
    _assert_poses_close(se2.retract(p, se2.local(p, q)), q, atol=1e-9, what="retract(p, local)")


def test_local_inverts_retract_below_half_turn(rng: np.random.Generator) -> None:
    p, v = _poses(rng), _tangents(rng)
    v = v[np.abs(v[:, 2]) < np.pi - 1e-6]
    p = p[: len(v)]
    assert_close(se2.local(p, se2.retract(p, v)), v, rtol=0.0, atol=1e-9, what="local(p, retract)")


def _broadcast_loop(
    fn: Callable[[np.ndarray, np.ndarray], np.ndarray], a: np.ndarray, b: np.ndarray, out_dim: int
) -> np.ndarray:
    """fn applied row by row over the broadcast leading axes of a and b."""
    lead = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    a_b = np.broadcast_to(a, lead + a.shape[-1:])
    b_b = np.broadcast_to(b, lead + b.shape[-1:])
    out = np.empty((*lead, out_dim))
    for idx in np.ndindex(*lead):
        out[idx] = fn(a_b[idx], b_b[idx])
    return out


BINARY = {
    "compose": (se2.compose, 3, 3),
    "between": (se2.between, 3, 3),
    "retract": (se2.retract, 3, 3),
    "local": (se2.local, 3, 3),
    "transform_to": (se2.transform_to, 2, 2),
    "transform_from": (se2.transform_from, 2, 2),
}


@pytest.mark.parametrize("name", sorted(BINARY))
@pytest.mark.parametrize(
    ("shape_a", "shape_b"), [((5, 7), (7,)), ((7,), (5, 7)), ((), (4,)), ((5, 1), (1, 7))]
)
def test_binary_ops_broadcast_leading_axes(
    name: str, shape_a: tuple[int, ...], shape_b: tuple[int, ...]
) -> None:
    fn, b_dim, out_dim = BINARY[name]
    rng = np.random.default_rng(7)
    a = rng.uniform(-3, 3, (*shape_a, 3))
    b = rng.uniform(-3, 3, (*shape_b, b_dim))
    got = fn(a, b)
    assert got.shape == (*np.broadcast_shapes(shape_a, shape_b), out_dim)
    assert_close(got, _broadcast_loop(fn, a, b, out_dim), what=f"{name} broadcast")


@pytest.mark.parametrize("name", ["inverse", "expmap", "logmap"])
def test_unary_ops_keep_leading_axes(name: str) -> None:
    fn = getattr(se2, name)
    a = np.random.default_rng(8).uniform(-3, 3, (5, 7, 3))
    got = fn(a)
    assert got.shape == (5, 7, 3)
    assert_close(got[2, 3], fn(a[2, 3]), what=f"{name} row")


@pytest.mark.parametrize("name", ["compose", "between", "retract", "local"])
def test_binary_ops_reject_wrong_last_axis(name: str) -> None:
    with pytest.raises(ValueError, match="shape"):
        getattr(se2, name)(np.zeros((4, 3)), np.zeros((4, 2)))


@pytest.mark.parametrize("name", ["inverse", "expmap", "logmap"])
def test_unary_ops_reject_wrong_last_axis(name: str) -> None:
    with pytest.raises(ValueError, match="shape"):
        getattr(se2, name)(np.zeros((4, 4)))


_coord = st.floats(-100.0, 100.0, allow_nan=False)
_angle = st.floats(-np.pi + 1e-6, np.pi - 1e-6, allow_nan=False)
_pose = st.tuples(_coord, _coord, st.floats(-10.0, 10.0, allow_nan=False))
_tangent = st.tuples(_coord, _coord, _angle)
_props = settings(derandomize=True, max_examples=300, deadline=None)


@_props
@given(p=_pose, q=_pose)
def test_local_round_trips_through_retract(p: tuple, q: Vec3) -> None:
    pa, qa = np.array(p), np.array(q)
    back = se2.retract(pa, se2.local(pa, qa))
    _assert_poses_close(back, qa, atol=1e-9 * (1.0 + np.abs(qa).max()), what="retract(local)")


@_props
@given(v=_tangent)
def test_logmap_round_trips_through_expmap(v: Vec3) -> None:
    va = np.array(v)
    assert_close(se2.logmap(se2.expmap(va)), va, rtol=1e-9, atol=1e-9, what="logmap(expmap(v))")


@_props
@given(a=_pose, b=_pose, c=_pose)
def test_compose_is_associative(a: tuple, b: tuple, c: Vec3) -> None:
    a_, b_, c_ = np.array(a), np.array(b), np.array(c)
    left = se2.compose(se2.compose(a_, b_), c_)
    right = se2.compose(a_, se2.compose(b_, c_))
    _assert_poses_close(left, right, atol=1e-9 * (1.0 + np.abs(left).max()), what="associativity")
