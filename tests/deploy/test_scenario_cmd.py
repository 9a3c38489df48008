"""`semfleet scenario` helpers that need no subprocess."""

from __future__ import annotations

import pytest

from deploy.scenario_cmd import default_cone_steps


@pytest.mark.parametrize(
    ("steps", "cones"),
    [(60, [20, 40, 60]), (56, [19, 37, 56]), (18, [6, 12, 18]), (2, [1, 2]), (1, [1])],
)
def test_default_cone_steps_evenly_spaced_ending_at_the_last_step(
    steps: int, cones: list[int]
) -> None:
    assert default_cone_steps(steps) == cones
