"""The default layout of a launch's Rerun recording (docs/deploy.md, "Live view and
recordings"): the fleet seen from above on the left; on the right one tab per robot with its
counters in five plots, and below one tab per robot with D's class probabilities.

``rrb`` is ``rerun.blueprint``, passed in so that this module imports without the optional extra.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from sim.scenario import Scenario

# The agents' counters (docs/agents.md) in five plots per robot; the last one holds every counter
# not named here: faults and recovery (rejections, invalid input, duplicates, resends, restores
# ...), mostly zero, so that a rise is seen.
COUNTER_PLOTS = (
    ("timing (µs)", ("step_us_local", "step_us_distributed", "loop_lag_max_us",
                     "gossip_gap_max_us")),
    ("hypotheses", ("hypotheses_local", "hypotheses_distributed")),
    ("gossip", ("stacks_sent", "stacks_received", "stacks_merged", "stacks_unchanged",
                "slots_decoded", "slots_skipped", "slots_reused", "frames_processed",
                "estimates_sent")),
    ("bytes", ("bytes_sent", "bytes_sent_ticks", "bytes_received")),
)  # fmt: skip
EYE_HEIGHT = 1.0  # the top-down camera's height over the world's extent
EYE_MARGIN_M = 3.0


def fleet_blueprint(rrb: Any, scenario: Scenario, robots: Sequence[str]) -> Any:
    """The fleet seen from above next to each robot's counters and D's class probabilities."""
    counters = [
        rrb.Grid(*counter_views(rrb, r), name=f"{r} counters", grid_columns=2) for r in robots
    ]
    classes = [
        rrb.TensorView(origin=f"robots/{r}/distributed/classes", name=f"{r} D classes")
        for r in robots
    ]
    right = rrb.Vertical(rrb.Tabs(*counters), rrb.Tabs(*classes), row_shares=[3, 2])
    eye = top_down_eye(rrb, scenario)
    fleet = rrb.Spatial3DView(origin="world", name="fleet", eye_controls=eye)
    return rrb.Blueprint(
        rrb.Horizontal(fleet, right, column_shares=[3, 2]),
        rrb.SelectionPanel(state="collapsed"),
    )


def counter_views(rrb: Any, robot: str) -> list[Any]:
    """One time-series view per group of ``COUNTER_PLOTS`` and one for every other counter."""
    origin = f"robots/{robot}/counters"
    legend = rrb.PlotLegend(corner=rrb.Corner2D.LeftTop)
    named = [c for _, names in COUNTER_PLOTS for c in names]
    plots = [(t, [f"+ $origin/{c}" for c in names]) for t, names in COUNTER_PLOTS]
    rest = ["+ $origin/**", "- $origin/step", *(f"- $origin/{c}" for c in named)]
    return [
        rrb.TimeSeriesView(origin=origin, contents=contents, name=title, plot_legend=legend)
        for title, contents in [*plots, ("faults and recovery", rest)]
    ]


def top_down_eye(rrb: Any, scenario: Scenario) -> Any:
    """A camera above the middle of the robots' starts and the objects, looking down with +y up,
    high enough to see them all."""
    starts = np.array([r.start[:2] for r in scenario.robots], dtype=float).reshape(-1, 2)
    points = np.concatenate([starts, scenario.object_poses()[:, :2].reshape(-1, 2)])
    lo, hi = points.min(axis=0), points.max(axis=0)
    cx, cy = (lo + hi) / 2.0
    height = EYE_HEIGHT * float(max(hi - lo)) + EYE_MARGIN_M
    return rrb.EyeControls3D(
        kind=rrb.Eye3DKind.Orbital,
        position=[cx, cy - 0.05 * height, height],  # a slight tilt: orbiting is defined
        look_target=[cx, cy, 0.0],
        eye_up=[0.0, 0.0, 1.0],
    )
