"""Which detections a robot's association could ever confirm, decided on the truth: the given-id
reference of data association (issue 45).

A robot without global ids holds a new object back until it has hit it ``confirm`` times
(``estimator.association``): a tentative object is dropped after ``drop_after`` steps in view
without a hit, or ``forget_after`` steps without one wherever it is; at its confirmation its
earlier hits enter the belief too. An object a robot sees fewer times never enters its map, and
so never its slot: a single sighting looks like clutter, however good the association. Given ids
carry such sightings into the fleet's belief, so "without ids against given ids" mixes two costs:
the association's mistakes and the information that confirmation gives up. A given-id run
restricted to :func:`confirmable` detections pays only the second: the difference between it and
a run without ids is the association's own.

On the truth the rule differs from the association's only in what "in view" means: here the
object is in the sensor's true field, there in the field around the robot's estimate. False
detections (:data:`CLUTTER`) are never confirmable.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from dataclasses import dataclass, field

CLUTTER = -1  # the truth label of a false detection (``sim.sensors`` re-exports it)


@dataclass(frozen=True, slots=True)
class ConfirmRule:
    """The association's confirmation (``estimator.association.AssociationConfig``'s fields of
    the same names; ``sim`` does not import the estimator's association)."""

    confirm: int = 3
    drop_after: int = 3
    forget_after: int = 50

    def __post_init__(self) -> None:
        if min(self.confirm, self.drop_after, self.forget_after) < 1:
            raise ValueError(
                "confirm, drop_after and forget_after must be ≥ 1, got "
                f"{self.confirm}, {self.drop_after}, {self.forget_after}"
            )


@dataclass(slots=True)
class _Tentative:
    hits: list[tuple[int, int]] = field(default_factory=list)  # (step index, detection index)
    misses: int = 0


def confirmable(
    labels: Sequence[Sequence[int]], in_view: Sequence[Collection[int]], rule: ConfirmRule
) -> list[tuple[bool, ...]]:
    """Per step and detection, whether its object is confirmed at or after it. ``labels[s]``:
    what each detection of the robot's step s truly is (an object id or CLUTTER); ``in_view[s]``:
    the objects in its sensor's field at that step, detected or missed."""
    if len(labels) != len(in_view):
        raise ValueError(f"{len(labels)} steps of labels against {len(in_view)} of in_view")
    keep = [[False] * len(step) for step in labels]
    confirmed: set[int] = set()
    tentative: dict[int, _Tentative] = {}
    for s, step in enumerate(labels):
        hit: set[int] = set()
        for i, label in enumerate(step):
            if label == CLUTTER:
                continue
            if label in confirmed:
                keep[s][i] = True
                continue
            t = tentative.setdefault(label, _Tentative())
            t.hits.append((s, i))
            t.misses = 0
            hit.add(label)
            if len(t.hits) >= rule.confirm:
                confirmed.add(label)
                del tentative[label]
                for a, b in t.hits:
                    keep[a][b] = True
        for label in list(tentative):  # as ``Associator._misses``: after the frame's hits
            t = tentative[label]
            if label not in hit and label in in_view[s]:
                t.misses += 1
            if t.misses >= rule.drop_after or s - t.hits[-1][0] >= rule.forget_after:
                del tentative[label]
    return [tuple(step) for step in keep]
