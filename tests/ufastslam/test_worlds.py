"""The bundled worlds (rectangle, office, aisles), their ground truth and their measurements."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.ufastslam import bundled_worlds, load_world, simulate
from sim.ufastslam.world import GROUP_TOLERANCE, arc, group_residuals
from tests.tolerance import assert_close

WORLDS = ("aisles", "office", "rectangle")


def test_the_three_worlds_are_bundled() -> None:
    assert bundled_worlds() == list(WORLDS)


@pytest.mark.parametrize("name", WORLDS)
def test_world_basics(name: str) -> None:
    w = load_world(name)
    assert w.name == name and w.dt == 0.5
    assert w.camera.half_angle == pytest.approx(math.radians(35.0))
    assert w.odometry.scale_error != 0 and w.odometry.yaw_rate_bias != 0
    kinds = {g.kind for g in w.groups}
    assert kinds == {"x", "y", "col"}
    index = {lid: j for j, lid in enumerate(w.landmark_ids)}
    for g in w.groups:
        pts = w.landmarks[[index[m] for m in g.members]]
        assert np.max(np.abs(group_residuals(g.kind, pts))) <= GROUP_TOLERANCE
    seen: set[int] = set()
    for k in range(1, w.steps + 1):
        seen.update(int(w.landmark_ids[j]) for j in w.visible(k)[0])
    assert seen == set(w.landmark_ids), "every landmark is seen at least once"


def test_rectangle_is_an_8_by_14_loop() -> None:
    w = load_world("rectangle")
    t = w.trajectory
    assert_close(t[:, 0].min(), 0.0, atol=1e-9)
    assert_close(t[:, 0].max(), 8.0, atol=1e-9)
    assert_close(t[:, 1].min(), 0.0, atol=1e-9)
    assert_close(t[:, 1].max(), 14.0, atol=1e-9)
    # one full turn, ending on the first leg again (5 m past the start)
    assert_close(np.sum(w.controls[:, 1]) * w.dt, -2 * math.pi, atol=1e-9)
    assert_close(t[-1], [0.0, 5.0, math.pi / 2], atol=1e-9)
    per_step = np.mean([len(w.visible(k)[0]) for k in range(1, w.steps + 1)])
    assert 1.0 <= per_step <= 2.0  # the bench's "1–2 observations per step"


def test_office_sees_its_start_landmark_again_only_at_the_end() -> None:
    w = load_world("office")
    j = w.landmark_ids.index(1)
    sightings = [k for k in range(1, w.steps + 1) if j in w.visible(k)[0]]
    first_pass = [k for k in sightings if k < w.steps // 2]
    again = [k for k in sightings if k >= w.steps // 2]
    assert first_pass and first_pass[0] == 1
    assert again and again[0] > 0.8 * w.steps
    assert_close(w.trajectory[-1, :2], [5.0, 0.0], atol=1e-9)


def test_aisles_zig_zag_without_a_loop() -> None:
    w = load_world("aisles")
    t = w.trajectory
    # up, down, up, down: heading north, south, north, south in four aisles 4 m apart
    ups = np.flatnonzero(np.diff(np.sign(np.sin(t[:, 2]))) != 0)
    assert len(ups) >= 3
    assert_close(t[-1, 0], 12.0, atol=0.05)
    assert np.linalg.norm(t[-1, :2] - t[0, :2]) > 10.0
    assert any(len(g.members) >= 6 for g in w.groups if g.kind == "col")


def test_arc_is_exact_for_a_full_circle() -> None:
    p = np.array([1.0, 2.0, 0.3])
    for _ in range(8):
        p = arc(p, 0.4, math.pi / 2, 0.5)
    assert_close(p, [1.0, 2.0, 0.3], atol=1e-12)


def test_controls_respect_speed_and_turn_rate() -> None:
    w = load_world("aisles")
    assert np.all(np.abs(w.controls[:, 0]) <= w.speed + 1e-12)
    assert np.all(np.abs(w.controls[:, 1]) <= w.turn_rate + 1e-12)


def test_simulation_is_reproducible_per_seed() -> None:
    w = load_world("rectangle")
    a, b, c = simulate(w, 3), simulate(w, 3), simulate(w, 4)
    np.testing.assert_array_equal(a.odometry, b.odometry)
    for fa, fb in zip(a.frames, b.frames, strict=True):
        np.testing.assert_array_equal(fa.ids, fb.ids)
        np.testing.assert_array_equal(fa.z, fb.z)
    assert not np.array_equal(a.odometry, c.odometry)


def test_odometry_carries_scale_error_and_yaw_rate_bias() -> None:
    w = load_world("rectangle")
    runs = [simulate(w, s) for s in range(10)]
    measured = np.concatenate([r.odometry for r in runs])
    true = np.tile(w.controls, (10, 1))
    moving = true[:, 0] > 0
    scale = np.mean(measured[moving, 0] / true[moving, 0]) - 1.0
    bias = np.mean(measured[:, 1] - true[:, 1])
    assert scale == pytest.approx(w.odometry.scale_error, abs=0.01)
    assert bias == pytest.approx(
        w.odometry.yaw_rate_bias, abs=0.1 * abs(w.odometry.yaw_rate_bias) + 1e-3
    )


def test_measurements_match_the_camera_model() -> None:
    w = load_world("rectangle")
    runs = [simulate(w, s) for s in range(5)]
    residuals = []
    for r in runs:
        for f in r.frames:
            seen, z_true = w.visible(f.k)
            np.testing.assert_array_equal(f.ids, np.asarray(w.landmark_ids)[seen])
            residuals.append(f.z - z_true)
    res = np.concatenate(residuals)
    res[:, 1] = (res[:, 1] + math.pi) % (2 * math.pi) - math.pi
    assert np.std(res[:, 0]) == pytest.approx(w.camera.range_std, rel=0.1)
    assert np.std(res[:, 1]) == pytest.approx(w.camera.bearing_std, rel=0.1)


def test_oracle_labels_are_the_ground_truth_groups() -> None:
    w = load_world("rectangle")
    assert w.labels[1] == ("x:west-wall", "y:row-1")
    assert w.labels[19] == ("col:desks",)


def test_simulate_rejects_bad_seeds() -> None:
    w = load_world("rectangle")
    for bad in (-1, 2**63, 1.5, True):
        with pytest.raises(ValueError, match="seed must be an integer"):
            simulate(w, bad)  # type: ignore[arg-type]
