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

from collections.abc import Callable
from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import NDArray

from estimator.factors import object_key
from estimator.models import ClassifierModel, viewpoint
from estimator.models.classifier import all_log_likelihoods

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
KeyArray = NDArray[np.uint64]


@dataclass(slots=True)
class SemanticLedger:
    """Every detection a continuous belief's weights hold: the robot pose key, the object id
    and the scores z (dim,) of each, ``applied`` (D, M): log P(z_d | c, ψ̂_d) at the estimate the
    weights were last brought to, and ``psi`` (D,) the ψ̂_d of that estimate.

    A step's cost must not grow with the mission (issue 40): the poses of every detection are
    read from the estimate in one call, and only the detections whose ψ̂ moved are evaluated
    again — a variable iSAM2 leaves alone keeps its estimate to the bit, so an old detection of
    objects no longer in view costs a comparison, not a likelihood."""

    robot_keys: list[int] = field(default_factory=list)
    object_ids: list[int] = field(default_factory=list)
    scores: list[Array] = field(default_factory=list)
    applied: Array = field(default_factory=lambda: np.zeros((0, 0)))
    psi: Array = field(default_factory=lambda: np.zeros(0))
    # The first len(...) detections as arrays, extended as detections are added.
    _columns: tuple[KeyArray, KeyArray, Array] | None = None

    def copy(self) -> SemanticLedger:
        return SemanticLedger(
            list(self.robot_keys),
            list(self.object_ids),
            list(self.scores),
            self.applied.copy(),
            self.psi.copy(),
            self._columns,  # never written in place: shared safely
        )

    def add(self, robot_key: int, object_id: int, z: Array) -> None:
        """A detection whose evidence the weights took at this step (its reference is the
        estimate of the next :meth:`refresh`)."""
        self.robot_keys.append(robot_key)
        self.object_ids.append(object_id)
        self.scores.append(np.asarray(z, dtype=float))

    def settle(self, pose: Callable[[int], Array], model: ClassifierModel) -> None:
        """Take the detections added since the last evaluation as they are: their evidence was
        just evaluated around the estimate ``pose`` (key → (x, y, θ)) reads, which becomes
        their reference; nothing else is read (a step between two refreshes costs what it
        added)."""
        known, d = len(self.psi), len(self.robot_keys)
        if known == d:
            return
        robot_keys, object_keys, scores = self._arrays()
        robots = np.array([pose(int(k)) for k in robot_keys[known:]])
        objects = np.array([_as_pose(pose(int(k))) for k in object_keys[known:]])
        psi = viewpoint(robots, objects)
        now = all_log_likelihoods(model, scores[known:], psi[None, :])[0]
        applied = self.applied if known else np.zeros((0, model.num_classes))
        self.applied = np.concatenate([applied, now])
        self.psi = np.concatenate([self.psi, psi])

    def retire(self, keep: NDArray[np.bool_]) -> None:
        """Drop the detections where ``keep`` (D,) is False: their evidence stays in the weights
        as last refreshed, final from now on (the smoother marginalised their robot poses,
        ``estimator.smoother``). Only detections that have a reference can be dropped."""
        keep = np.asarray(keep, dtype=bool)
        known = len(self.psi)
        if keep.all():
            return
        if not keep[known:].all():
            raise ValueError("a detection without a reference cannot be retired")
        robot_keys, object_keys, scores = self._arrays()
        self.robot_keys = [k for k, y in zip(self.robot_keys, keep, strict=True) if y]
        self.object_ids = [j for j, y in zip(self.object_ids, keep, strict=True) if y]
        self.scores = [z for z, y in zip(self.scores, keep, strict=True) if y]
        self.applied = self.applied[keep[:known]]
        self.psi = self.psi[keep[:known]]
        self._columns = (robot_keys[keep], object_keys[keep], scores[keep])

    def robot_key_array(self) -> KeyArray:
        """The robot pose key (D,) of every detection."""
        if not self.robot_keys:
            return np.zeros(0, dtype=np.uint64)
        return self._arrays()[0]

    def refresh(
        self, estimate: gtsam.Values, model: ClassifierModel, object_index: dict[int, int]
    ) -> Array:
        """The change (n, M) of every object's Σ_d log P(z_d | c, ψ̂_d) since the last refresh,
        ψ̂ taken at ``estimate``, with objects in ``object_index`` order; the new values become
        the reference. Detections added since the last refresh or :meth:`settle` contribute
        nothing (their evidence was just evaluated around this estimate). It reads every
        detection's poses: a belief refreshes every few steps and settles in between."""
        m = model.num_classes
        out = np.zeros((len(object_index), m))
        if not self.robot_keys:
            return out
        robot_keys, object_keys, scores = self._arrays()
        poses = _poses(estimate, np.concatenate([robot_keys, object_keys]))
        d = len(robot_keys)
        psi = viewpoint(poses[:d], poses[d:])
        known = len(self.psi)
        now = np.empty((d, m))
        # Old detections whose viewpoint did not move keep their values; the others, and the
        # new ones, are evaluated.
        moved = np.ones(d, dtype=bool)
        moved[:known] = psi[:known] != self.psi
        if known:
            now[:known] = self.applied
        if moved.any():
            now[moved] = all_log_likelihoods(model, scores[moved], psi[moved][None, :])[0]
        if known:
            change = now[:known] - self.applied
            rows = np.array([object_index[j] for j in self.object_ids[:known]], dtype=np.int64)
            np.add.at(out, rows, change)
        self.applied = now
        self.psi = psi
        return out

    def moved_to(
        self, values: gtsam.Values, model: ClassifierModel, object_index: dict[int, int]
    ) -> Array:
        """The change (n, M) of every object's Σ_d log P(z_d | c, ψ̂_d) were ψ̂ read at
        ``values`` instead of where the weights last took it (objects in ``object_index``
        order); nothing is changed. Detections that have no reference yet contribute nothing."""
        out = np.zeros((len(object_index), model.num_classes))
        known = len(self.psi)
        if not known:
            return out
        robot_keys, object_keys, scores = self._arrays()
        poses = _poses(values, np.concatenate([robot_keys[:known], object_keys[:known]]))
        psi = viewpoint(poses[:known], poses[known:])
        moved = np.flatnonzero(psi != self.psi)
        if len(moved):
            now = all_log_likelihoods(model, scores[moved], psi[moved][None, :])[0]
            rows = np.array([object_index[self.object_ids[i]] for i in moved], dtype=np.int64)
            np.add.at(out, rows, now - self.applied[moved])
        return out

    def _arrays(self) -> tuple[KeyArray, KeyArray, Array]:
        """Robot pose keys (D,), object keys (D,) and scores (D, dim) of every detection."""
        d = len(self.robot_keys)
        have = 0 if self._columns is None else len(self._columns[0])
        if have < d:
            tail = slice(have, d)
            robots = np.array(self.robot_keys[tail], dtype=np.uint64)
            objects = np.array([object_key(j) for j in self.object_ids[tail]], dtype=np.uint64)
            scores = np.stack(self.scores[tail])
            if self._columns is not None:
                old_r, old_o, old_s = self._columns
                robots = np.concatenate([old_r[:have], robots])
                objects = np.concatenate([old_o[:have], objects])
                scores = np.concatenate([old_s[:have], scores])
            self._columns = (robots, objects, scores)
        assert self._columns is not None
        r, o, z = self._columns
        return r[:d], o[:d], z[:d]


def _poses(estimate: gtsam.Values, keys: KeyArray) -> Array:
    """The (x, y, θ) of ``keys`` (K,) in ``estimate`` (a point object as (x, y, 0), the pose
    its viewpoint is read at: ``estimator.models.objects``), read in one or two calls where
    every value is a Pose2 or a point object (``extractPose2`` and ``extractPoint2`` give each
    kind in key order), key by key otherwise."""
    every = np.array(estimate.keys(), dtype=np.uint64)
    poses = np.asarray(gtsam.utilities.extractPose2(estimate)).reshape(-1, 3)
    points = np.asarray(gtsam.utilities.extractPoint2(estimate)).reshape(-1, 2)
    is_point = np.zeros(len(every), dtype=bool)
    if len(points):
        is_point = (every >> np.uint64(56)) == np.uint64(ord("o"))
    if len(poses) == (~is_point).sum() and len(points) == is_point.sum():
        table = np.empty((len(every), 3))
        table[~is_point] = poses
        table[is_point] = _as_pose(points)
        rows = np.searchsorted(every, keys)
        if (rows < len(every)).all() and (every[np.minimum(rows, len(every) - 1)] == keys).all():
            return table[rows]
    return np.array([_pose(estimate, int(k)) for k in keys])


def _as_pose(p: Array) -> Array:
    """Positions (..., 2) as poses at heading 0 (..., 3); poses (..., 3) as they are."""
    a = np.asarray(p, dtype=float)
    if a.shape[-1] == 3:
        return a
    return np.concatenate([a, np.zeros((*a.shape[:-1], 1))], axis=-1)


def _pose(estimate: gtsam.Values, key: int) -> tuple[float, float, float]:
    try:
        p = estimate.atPose2(key)
    except RuntimeError:  # a point object
        x, y = estimate.atPoint2(key)
        return (float(x), float(y), 0.0)
    return (p.x(), p.y(), p.theta())
