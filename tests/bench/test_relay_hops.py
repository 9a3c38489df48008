"""The relay bench's measure of a hop (bench/bench_agents.py, issue 47): from a hand-made log of
the slots each robot's stacks carried, with known answers."""

from __future__ import annotations

import pytest

from bench.bench_agents import forward_hops

LINE = ["r1", "r2", "r3", "r4"]


def test_a_hop_is_the_time_from_one_robots_first_forwarding_to_the_next_ones() -> None:
    log = [
        (10.000, "r1", {"r1": 5}),
        (10.004, "r2", {"r1": 5}),
        (10.003, "r2", {"r1": 5}),  # a later copy that came first: the earliest counts
        (10.011, "r3", {"r1": 5}),
        (10.020, "r1", {"r1": 5}),  # re-sent: not a new first forwarding
        (10.100, "r4", {"r4": 7}),
        (10.090, "r3", {"r4": 7}),  # r3 forwarded r4's version before r4's stack came here
        (10.103, "r2", {"r4": 7}),
    ]
    hops = sorted((k, round(ms, 6)) for k, ms in forward_hops(log, LINE))
    # r1's version 5: r1 → r2 3 ms, r2 → r3 8 ms (r4 never forwards it: no hop). r4's version 7:
    # r4 → r3 out of order (no hop), r3 → r2 13 ms.
    assert hops == [(5, pytest.approx(3.0)), (5, pytest.approx(8.0)), (7, pytest.approx(13.0))]


def test_hops_go_away_from_the_owner_in_both_directions() -> None:
    log = [(0.0, "r2", {"r2": 1}), (0.002, "r1", {"r2": 1}), (0.005, "r3", {"r2": 1}),
           (0.009, "r4", {"r2": 1})]  # fmt: skip
    hops = sorted(round(ms, 6) for _, ms in forward_hops(log, LINE))
    assert hops == [pytest.approx(2.0), pytest.approx(4.0), pytest.approx(5.0)]


def test_after_meeting_keeps_the_samples_of_the_later_steps_only() -> None:
    import numpy as np

    from bench.bench_aoi import after_meeting
    from deploy.launch.aoi import AgeOfInformation

    aoi = AgeOfInformation(
        age_s=np.array([1.0, 0.5, 0.52, 0.99]),
        hops=np.array([3, 1, 3, 2]),
        owner=("r1", "r2", "r1", "r4"),
        receiver=("r4", "r3", "r4", "r2"),
        step=np.array([1, 3, 4, 2]),
        unreached=2,
    )
    later = after_meeting(aoi, 2)
    assert later.age_s.tolist() == [0.5, 0.52] and later.hops.tolist() == [1, 3]
    assert later.owner == ("r2", "r1") and later.receiver == ("r3", "r4")
    assert later.step.tolist() == [3, 4] and later.unreached == 2
