"""The given-id reference of data association: only the detections a robot's association could
confirm (``sim.confirmable``), on hand-made label sequences and on a simulated world."""

from __future__ import annotations

import collections

import pytest

from estimator.association import AssociationConfig
from sim.confirmable import CLUTTER, ConfirmRule, confirmable
from sim.generate import generate_scenario
from sim.sensors import Detector, Simulator

RULE = ConfirmRule(confirm=3, drop_after=2, forget_after=4)


def _kept(labels: list[list[int]], in_view: list[set[int]] | None = None) -> list[list[int]]:
    view = in_view if in_view is not None else [set() for _ in labels]
    keep = confirmable(labels, view, RULE)
    return [
        [lab for lab, ok in zip(step, mask, strict=True) if ok]
        for step, mask in zip(labels, keep, strict=True)
    ]


def test_the_third_hit_confirms_and_brings_the_first_two() -> None:
    labels = [[7], [7, CLUTTER], [], [7], [7, 8], [8]]
    assert _kept(labels) == [[7], [7], [], [7], [7], []]


def test_clutter_and_objects_seen_twice_never_enter() -> None:
    labels = [[CLUTTER, 5], [CLUTTER], [5], [CLUTTER, CLUTTER]]
    assert _kept(labels) == [[], [], [], []]


def test_a_gap_longer_than_forget_after_starts_the_count_again() -> None:
    gap = [[]] * 4  # hits 5 steps apart: the first is forgotten
    assert _kept([[3], [3], *gap, [3]]) == [[], [], *gap, []]
    close = [[]] * 3  # 4 steps apart: within forget_after
    assert _kept([[3], [3], *close, [3]]) == [[3], [3], *close, [3]]


def test_in_view_misses_drop_a_tentative_object_and_out_of_view_steps_do_not() -> None:
    labels = [[4], [], [], [4], [4]]
    assert _kept(labels, [set(), {4}, {4}, {4}, {4}]) == [[], [], [], [], []]
    assert _kept(labels, [set(), {4}, set(), {4}, {4}]) == [[4], [], [], [4], [4]]


def test_a_confirmed_object_stays_confirmed() -> None:
    labels = [[1], [1], [1], *([[]] * 10), [1]]
    assert _kept(labels, [{1}] * len(labels))[-1] == [1]


def test_the_rule_is_the_association_s_and_refuses_nonsense() -> None:
    a = AssociationConfig()
    assert ConfirmRule() == ConfirmRule(a.confirm, a.drop_after, a.forget_after)
    with pytest.raises(ValueError, match="must be ≥ 1"):
        ConfirmRule(confirm=0)
    with pytest.raises(ValueError, match="steps of labels"):
        confirmable([[1]], [], RULE)
    with pytest.raises(ValueError, match="confirmable needs global ids"):
        Detector("none", confirmable=ConfirmRule())


def test_a_simulated_run_keeps_only_the_confirmable_detections_to_the_bit() -> None:
    """Kept detections are the delivered ones (same noise), every kept object has at least
    ``confirm`` detections of its robot, no clutter is kept, and something was dropped."""
    world = generate_scenario(3, 40, 3, seed=11, steps=80, area=20.0)
    every = Simulator(world, 2, detector=Detector(clutter=0.1, miss=0.2))
    rule = ConfirmRule()
    sim = Simulator(world, 2, detector=Detector(clutter=0.1, miss=0.2, confirmable=rule))
    dropped = 0
    for robot in world.robot_ids:
        hits: collections.Counter[int] = collections.Counter()
        for k in range(1, world.steps + 1):
            frame, labels = sim.labelled_frame(robot, k)
            full, full_labels = every.labelled_frame(robot, k)
            assert frame.odometry.tobytes() == full.odometry.tobytes()
            delivered = {
                (d.object_id, d.z_geo.tobytes(), d.z_sem.tobytes()) for d in full.detections
            }
            for d in frame.detections:
                assert (d.object_id, d.z_geo.tobytes(), d.z_sem.tobytes()) in delivered
            assert CLUTTER not in labels
            hits.update(labels)
            dropped += sum(lab != CLUTTER for lab in full_labels) - len(labels)
        assert min(hits.values()) >= rule.confirm
    assert dropped > 0
