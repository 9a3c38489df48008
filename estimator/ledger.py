"""The semantic evidence of a shared continuous belief, kept up to date as its estimate moves.

When the semantic factors stay out of the Gaussians (``BeliefConfig.semantic_poses = False``),
a step weighs its detections under the geometry known at that step (Eq. 6): a detection's class
evidence, log ∫ P(z | c, ψ) p(ψ | Z_geo,1:k) dψ, is evaluated once, around the viewpoint ψ̂ the
robot believed in then. Later geometry moves ψ̂ — most in the first steps after an object is
first seen — and the evidence would stay where it was evaluated. (A belief per class realisation
corrects this implicitly: the semantic factors pull its poses, and the geometric evidence of
later steps responds to the pull.) The ledger re-linearises the evidence instead, as iSAM2 does
its factors: it keeps every detection's log-likelihood at the estimate the weights last saw,
and each step moves the weights by the change of Σ log P(z_d | c, ψ̂_d) at the current estimate
— the first-order change of the integral when the mean of ψ moves (docs/estimator.md, "One
continuous belief").
"""

from __future__ import annotations

from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import NDArray

from estimator.factors import object_key
from estimator.models import ClassifierModel, viewpoint
from estimator.models.classifier import all_log_likelihoods

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(slots=True)
class SemanticLedger:
    """Every detection a continuous belief's weights hold: the robot pose key, the object id
    and the scores z (dim,) of each, and ``applied`` (D, M): log P(z_d | c, ψ̂_d) at the
    estimate the weights were last brought to (NaN until its first :meth:`refresh`)."""

    robot_keys: list[int] = field(default_factory=list)
    object_ids: list[int] = field(default_factory=list)
    scores: list[Array] = field(default_factory=list)
    applied: Array = field(default_factory=lambda: np.zeros((0, 0)))

    def copy(self) -> SemanticLedger:
        return SemanticLedger(
            list(self.robot_keys), list(self.object_ids), list(self.scores), self.applied.copy()
        )

    def add(self, robot_key: int, object_id: int, z: Array) -> None:
        """A detection whose evidence the weights took at this step (its reference is the
        estimate of the next :meth:`refresh`)."""
        self.robot_keys.append(robot_key)
        self.object_ids.append(object_id)
        self.scores.append(np.asarray(z, dtype=float))

    def refresh(
        self, estimate: gtsam.Values, model: ClassifierModel, object_index: dict[int, int]
    ) -> Array:
        """The change (n, M) of every object's Σ_d log P(z_d | c, ψ̂_d) since the last refresh,
        ψ̂ taken at ``estimate``, with objects in ``object_index`` order; the new values become
        the reference. Detections added since the last refresh contribute nothing (their
        evidence was just evaluated around this estimate)."""
        m = model.num_classes
        out = np.zeros((len(object_index), m))
        if not self.robot_keys:
            return out
        poses = {k: _pose(estimate, k) for k in dict.fromkeys(self.robot_keys)}  # once a pose
        robots = np.array([poses[k] for k in self.robot_keys])
        objects = {j: _pose(estimate, object_key(j)) for j in set(self.object_ids)}
        psi = viewpoint(robots, np.array([objects[j] for j in self.object_ids]))
        now = all_log_likelihoods(model, np.stack(self.scores), psi[None, :])[0]  # (D, M)
        known = len(self.applied)
        if known:
            change = now[:known] - self.applied
            rows = np.array([object_index[j] for j in self.object_ids[:known]], dtype=np.int64)
            np.add.at(out, rows, change)
        self.applied = now
        return out


def _pose(estimate: gtsam.Values, key: int) -> tuple[float, float, float]:
    p = estimate.atPose2(key)
    return (p.x(), p.y(), p.theta())
