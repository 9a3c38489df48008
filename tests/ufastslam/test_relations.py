"""Relation labels, their errors, and the threshold detector."""

from __future__ import annotations

import numpy as np
import pytest

from estimator.ufastslam import Observation, RelationConfig, RelationError, parse_label
from estimator.ufastslam.relations import Group, MapView, detect, references


def test_parse_label() -> None:
    label = parse_label("x:west-wall")
    assert (label.kind, label.name, label.key) == ("x", "west-wall", "x:west-wall")
    assert parse_label("col:desks.2").kind == "col"


@pytest.mark.parametrize(
    ("label", "fragment"),
    [
        ("xwall", "relation label 'xwall': expected KIND:NAME"),
        ("z:wall", "relation label 'z:wall': unknown kind 'z' (known: x, y, col)"),
        ("X:wall", "unknown kind 'X'"),
        ("x:", "relation label 'x:': group name '' must be 1–64"),
        ("y:two words", "group name 'two words'"),
        ("col:" + "a" * 65, "must be 1–64"),
        (3, "relation label 3: expected a string KIND:NAME"),
        (None, "relation label None: expected a string"),
    ],
)
def test_malformed_labels_are_clear_errors(label: object, fragment: str) -> None:
    with pytest.raises(RelationError) as info:
        parse_label(label)
    assert fragment in str(info.value)


def test_observation_rejects_malformed_labels_at_construction() -> None:
    with pytest.raises(RelationError, match="relation label 'q:wall': unknown kind 'q'"):
        Observation(4, (2.0, 0.1), ("x:wall", "q:wall"))
    with pytest.raises(RelationError, match="labels must be a tuple"):
        Observation(4, (2.0, 0.1), "x:wall")  # type: ignore[arg-type]
    assert Observation(4, (2.0, 0.1), ["x:wall"]).labels == ("x:wall",)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="z must be 2 finite numbers"):
        Observation(4, (float("nan"), 0.1))


@pytest.mark.parametrize(
    ("kwargs", "fragment"),
    [
        ({"source": "gt"}, "relations.source 'gt'"),
        ({"mode": "always"}, "relations.mode 'always'"),
        ({"std": 0.0}, "relations.std must be finite and > 0"),
        ({"line_threshold": float("inf")}, "relations.line_threshold"),
        ({"collinear_min_axis_angle_deg": 45.0}, "collinear_min_axis_angle_deg"),
    ],
)
def test_relation_config_is_validated(kwargs: dict[str, object], fragment: str) -> None:
    with pytest.raises(RelationError) as info:
        RelationConfig(**kwargs)  # type: ignore[arg-type]
    assert fragment in str(info.value)


def _view(points: list[tuple[float, float]], var: float = 0.01) -> MapView:
    pts = np.array(points, dtype=float)
    return MapView(pts, np.tile(var * np.eye(2), (len(pts), 1, 1)))


CFG = RelationConfig(source="threshold")
P_COV = 0.01 * np.eye(2)


def test_detect_joins_the_x_group_within_the_threshold() -> None:
    view = _view([(-1.5, 1.0), (-1.5, 3.5), (4.0, 8.0)])
    groups = [Group("x", "wall", [0, 1])]
    found = detect(np.array([-1.3, 6.0]), P_COV, view, groups, [], CFG)
    assert [(c.kind, c.group, c.partners) for c in found] == [("x", 0, ())]


def test_detect_needs_every_member_of_a_group_within_the_threshold() -> None:
    """A group's mean alone would admit a landmark 0.5 m from one of its members."""
    view = _view([(-1.5, 1.0), (-1.1, 3.5)])
    groups = [Group("x", "wall", [0, 1])]
    assert detect(np.array([-1.0, 6.0]), P_COV, view, groups, [], CFG) == []
    assert [c.group for c in detect(np.array([-1.3, 6.0]), P_COV, view, groups, [], CFG)] == [0]


def test_detect_founds_a_group_with_an_ungrouped_landmark() -> None:
    view = _view([(-1.5, 1.0), (4.0, 8.0)])
    found = detect(np.array([4.1, 2.0]), P_COV, view, [], [], CFG)
    assert [(c.kind, c.group, c.partners) for c in found] == [("x", None, (1,))]


def test_detect_nothing_beyond_threshold_or_gate() -> None:
    view = _view([(-1.5, 1.0), (4.0, 8.0)])
    assert detect(np.array([-1.0, 5.0]), P_COV, view, [], [], CFG) == []  # 0.5 m > 0.4 m
    tight = RelationConfig(source="threshold", gate=0.5)
    # 0.3 m is within 0.4 m but 0.3² / (0.01 + 0.01 + 0.05²) = 4 fails a gate of 0.5
    assert detect(np.array([-1.2, 5.0]), P_COV, view, [], [], tight) == []


def test_detect_collinear_only_from_covisible_off_axis_lines() -> None:
    view = _view([(0.0, 0.0), (3.0, 1.5), (10.0, 0.0)])
    p_hat = np.array([6.0, 3.1])  # 0.09 m off the line through landmarks 0 and 1
    found = detect(p_hat, P_COV, view, [], [0, 1], CFG)
    assert [(c.kind, c.partners) for c in found] == [("col", (0, 1))]
    assert detect(p_hat, P_COV, view, [], [], CFG) == []  # not seen together: no new line
    # an axis-aligned line is a same-x/same-y fact, not a collinear one
    flat = _view([(0.0, 0.0), (3.0, 0.0)])
    assert [c.kind for c in detect(np.array([6.0, 0.1]), P_COV, flat, [], [0, 1], CFG)] == ["y"]


def test_references_pick_the_least_uncertain_and_the_most_separated() -> None:
    view = MapView(
        np.array([[0.0, 0.0], [1.0, 1.0], [5.0, 5.0], [2.0, 2.0]]),
        np.array([0.3 * np.eye(2), 0.1 * np.eye(2), 0.2 * np.eye(2), 0.4 * np.eye(2)]),
    )
    assert references("x", [0, 1, 2], view) == (1,)
    assert set(references("col", [0, 1, 2, 3], view)) == {0, 2}
    assert references("col", [3], view) == ()
    assert references("y", [], view) == ()
