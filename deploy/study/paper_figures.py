"""The paper's published figures, as read off them, and a study's means against them
(`semfleet study --paper`, docs/paper.md).

Tchuiev & Indelman, "Distributed Consistent Multi-Robot Semantic Localization and Mapping"
(RA-L 2020) publish their simulation's results as curves only (Fig. 2b–e, 3a). The values below
were read off those curves at the step named; a point value carries the reading's own
uncertainty, ±10 %; Fig. 3a's distributed and double-counting curves are given as the ranges
they were read as. Only what was read is listed: Fig. 2c and 2e (object error and uncertainty)
have no read-off values here, and a study does not draw what it does not have.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

# The bundled world that reproduces the paper's simulation: the only one these values describe.
PAPER_WORLD = "paper"

PAPER_SOURCE = (
    "Tchuiev & Indelman, Distributed Consistent Multi-Robot Semantic Localization and Mapping, "
    "RA-L 2020: values read off Fig. 2b, 2d and 3a"
)

# The uncertainty of reading a point off a published curve.
READING = 0.10


@dataclass(frozen=True)
class PaperValue:
    """One value of a published figure: ``metric`` (a results.json curve) of ``method`` at step
    ``step`` lies in [low, high] as read."""

    figure: str
    metric: str
    method: str
    step: int
    low: float
    high: float

    @property
    def middle(self) -> float:
        return (self.low + self.high) / 2

    def holds(self, value: float) -> bool:
        return self.low <= value <= self.high


def _about(figure: str, metric: str, method: str, step: int, value: float) -> PaperValue:
    """A point read off a curve, ±:data:`READING`."""
    return PaperValue(figure, metric, method, step, value * (1 - READING), value * (1 + READING))


PAPER_VALUES: tuple[PaperValue, ...] = (
    _about("Fig. 3a", "msde", "local", 60, 0.09),
    PaperValue("Fig. 3a", "msde", "distributed", 60, 0.01, 0.02),
    PaperValue("Fig. 3a", "msde", "double_count", 60, 0.02, 0.03),
    _about("Fig. 2b", "robot_error", "local", 60, 0.62),
    _about("Fig. 2d", "robot_sqrt_det", "local", 60, 0.03),
    _about("Fig. 2d", "robot_sqrt_det", "distributed", 60, 0.009),
    _about("Fig. 2d", "robot_sqrt_det", "double_count", 60, 0.006),
)


def paper_world_error(scenario_name: str) -> str | None:
    """Why a study of ``scenario_name`` cannot be compared with the paper's figures, None when it
    can: they describe the paper's world only (its variants keep its name)."""
    if scenario_name == PAPER_WORLD:
        return None
    return (
        f"--paper compares with the paper's figures, which describe the bundled "
        f"{PAPER_WORLD!r} world only (this study's scenario is {scenario_name!r})"
    )


@dataclass(frozen=True)
class Comparison:
    """A :class:`PaperValue` and the study's mean at its step (None: not scored there)."""

    value: PaperValue
    ours: float | None

    @property
    def ratio(self) -> float | None:
        """Ours over the middle of the paper's interval."""
        return None if self.ours is None else self.ours / self.value.middle

    @property
    def holds(self) -> bool | None:
        return None if self.ours is None else self.value.holds(self.ours)

    def document(self) -> dict[str, Any]:
        """A row of paper.json."""
        v = self.value
        return {
            "figure": v.figure,
            "metric": v.metric,
            "method": v.method,
            "step": v.step,
            "paper_low": v.low,
            "paper_high": v.high,
            "ours": self.ours,
            "ratio": self.ratio,
            "within": self.holds,
        }


def values_for(doc: Mapping[str, Any]) -> list[PaperValue]:
    """The read-off values a results document can be compared with: methods it ran, steps it
    has."""
    return [v for v in PAPER_VALUES if v.method in doc["methods"] and 1 <= v.step <= doc["steps"]]


def compare(doc: Mapping[str, Any]) -> list[Comparison]:
    """Every value of :func:`values_for` against the document's mean over runs and robots."""
    rows = []
    for v in values_for(doc):
        curve = doc["methods"][v.method]["mean"].get(v.metric)
        ours = None if curve is None else curve[v.step - 1]
        if ours is not None and not math.isfinite(ours):
            ours = None
        rows.append(Comparison(v, ours))
    return rows


def by_metric(values: Sequence[PaperValue]) -> dict[str, list[PaperValue]]:
    """``values`` grouped by their metric, for the plot of each curve."""
    out: dict[str, list[PaperValue]] = {}
    for v in values:
        out.setdefault(v.metric, []).append(v)
    return out
