"""A smoother whose robot poses leave it after a window of steps (``BeliefConfig.window``).

A full iSAM2 keeps every pose of every robot. On a map a robot keeps revisiting, a loop closure
re-eliminates and back-substitutes the whole loop, so a step costs more the longer the mission
(docs/estimator.md, "Step cost over a long mission"). Here, whenever the oldest pose is two
windows old, the poses older than one window are marginalised: the factors that touch them are
linearised at the current estimate and the old poses eliminated from them, which leaves one
Gaussian factor on what they were connected to (the window's first pose and the objects they
saw); a fresh iSAM2 is built from the kept factors, that marginal and the current estimate.
Objects are never marginalised: they are the map.

The marginal enters as :func:`relative_marginal` (the default; ``relative=False`` keeps the
first form, a ``LinearContainerFactor``, as the reference): the same Gaussian, re-expressed in
its variables' poses relative to one of them, so that when a later loop closure turns and
shifts the old map the marginal sees only how the map bent, not how it moved. The linear form
read such a turn through local coordinates taken variable by variable and pulled the old map
back: on the 2,000-step mission it ended D's object error 2.0–2.7× the full smoother's on two
of three seeds; the relative form ends within the seeds' spread of it (docs/estimator.md, "A
window of poses").

Unlike GTSAM's ``IncrementalFixedLagSmoother`` (``ISAM2.marginalizeLeaves``), no variable's
linearisation point is frozen: iSAM2 relinearises the objects as before, and the marginal with
them. (``marginalizeLeaves`` froze every object an old pose saw: the distributed belief, whose
objects move most when slots arrive, ended the 2,000-step mission at twice the full smoother's
error; it also refused, "Asking to remove variables from the variable index that are not
unused", whenever two robots' old poses shared a clique.) A marginalised pose no longer moves
with later loop closures.

:class:`WindowedISAM2` offers the part of ``gtsam.ISAM2``'s interface a belief uses, so the
belief, its slots and the distributed fusion work on either; its factor indices stay valid across
rebuilds (the distributed belief removes a slot's ξ factors by index).
"""

from __future__ import annotations

from collections.abc import Sequence

import gtsam
import numpy as np

from estimator.models import MAX_STEP
from estimator.relative_marginal import relative_marginal

_INDEX_MASK = (1 << 56) - 1  # gtsam.Symbol: the character in the top 8 bits, the index below
_POSE = ord("x")


def pose_step(key: int) -> int | None:
    """The step of a robot pose key (``estimator.factors.pose_key``), None for any other key."""
    if key >> 56 != _POSE:
        return None
    return (key & _INDEX_MASK) % (MAX_STEP + 1)


def pose_steps(keys: Sequence[int] | np.ndarray) -> np.ndarray:
    """:func:`pose_step` of robot pose keys (K,), vectorised."""
    k = np.asarray(keys, dtype=np.uint64)
    return ((k & np.uint64(_INDEX_MASK)) % np.uint64(MAX_STEP + 1)).astype(np.int64)


def marginal_covariances(isam: gtsam.ISAM2 | WindowedISAM2, keys: Sequence[int]) -> np.ndarray:
    """The marginal covariance of each of ``keys``, (K, d, d) (d = 3 for Pose2, 2 for a point
    object; all keys of one kind): key by key from a full
    iSAM2, whose cliques keep them apart; from one joint marginal from a windowed one
    (:meth:`WindowedISAM2.marginal_covariances`)."""
    if isinstance(isam, WindowedISAM2):
        return isam.marginal_covariances(keys)
    if not keys:
        return np.zeros((0, 3, 3))
    return np.array([isam.marginalCovariance(k) for k in keys])


class _Result:
    """What a belief reads of an update's ``gtsam.ISAM2Result``: the indices of the new factors
    (stable across rebuilds)."""

    def __init__(self, indices: list[int]) -> None:
        self._indices = indices

    def getNewFactorsIndices(self) -> list[int]:
        return list(self._indices)


class WindowedISAM2:
    """iSAM2 that keeps the robot poses of the last ``window`` to ``2 · window`` steps (and
    every object)."""

    def __init__(self, params: gtsam.ISAM2Params, window: int, relative: bool = True) -> None:
        if window < 1:
            raise ValueError(f"window must be ≥ 1 step, got {window}")
        self.window = window
        self.relative = relative
        self._params = params
        self.isam = gtsam.ISAM2(params)
        self.latest = 0  # the latest step of any pose it holds
        self.oldest = 0  # the oldest step of the poses it holds
        self.rebuilds = 0
        # Stable index → the factor's index in the current iSAM2.
        self._index: dict[int, int] = {}
        self._next = 0

    def copy(self) -> WindowedISAM2:
        """An independent copy (``gtsam.ISAM2``'s copy constructor; the marginal factors, which
        hold no state, are shared)."""
        twin = WindowedISAM2(self._params, self.window, self.relative)
        twin.isam = gtsam.ISAM2(self.isam)
        twin.latest, twin.oldest, twin.rebuilds = self.latest, self.oldest, self.rebuilds
        twin._index = dict(self._index)
        twin._next = self._next
        return twin

    def oldest_kept(self) -> int:
        """The oldest step whose poses the smoother still holds (older ones were marginalised)."""
        return self.oldest

    def update(
        self,
        graph: gtsam.NonlinearFactorGraph | None = None,
        values: gtsam.Values | None = None,
        remove: Sequence[int] = (),
    ) -> _Result:
        """``gtsam.ISAM2.update(graph, values, remove)`` with stable factor indices; then, if
        the oldest pose is two windows old, the poses older than one window are marginalised."""
        graph = gtsam.NonlinearFactorGraph() if graph is None else graph
        values = gtsam.Values() if values is None else values
        for key in values.keys():  # noqa: SIM118 - gtsam.Values is not iterable
            step = pose_step(int(key))
            if step is not None:
                self.latest = max(self.latest, step)
        gone = [i for i in remove if i not in self._index]
        if gone:
            raise ValueError(f"factors {gone} are not held (removed, or marginalised)")
        actual = [self._index.pop(i) for i in remove]
        result = self.isam.update(graph, values, actual)
        stable = []
        for index in result.getNewFactorsIndices():
            self._index[self._next] = int(index)
            stable.append(self._next)
            self._next += 1
        if self.latest - self.oldest >= 2 * self.window:
            self._marginalise(self.latest - self.window)
        return _Result(stable)

    def _marginalise(self, oldest: int) -> None:
        """Marginalise every pose older than step ``oldest`` and rebuild iSAM2 (module doc)."""
        estimate = self.isam.calculateEstimate()
        factors = self.isam.getFactorsUnsafe()
        keys = [int(k) for k in estimate.keys()]  # noqa: SIM118 - gtsam.Values is not iterable
        steps = pose_steps(keys)
        is_pose = np.array([pose_step(k) is not None for k in keys], dtype=bool)
        dropped = {k for k, st, p in zip(keys, steps, is_pose, strict=True) if p and st < oldest}
        old = gtsam.GaussianFactorGraph()
        kept = gtsam.NonlinearFactorGraph()
        stable_of = {actual: stable for stable, actual in self._index.items()}
        kept_stable: list[int | None] = []
        for i in range(factors.size()):
            f = factors.at(i) if factors.exists(i) else None
            if f is None:
                continue
            if any(int(k) in dropped for k in f.keys()):  # noqa: SIM118 - not iterable
                old.push_back(f.linearize(estimate))
            else:
                kept.push_back(f)
                kept_stable.append(stable_of.get(i))
        ordering = gtsam.Ordering()
        for k in sorted(dropped):
            ordering.push_back(k)
        _, marginal = old.eliminatePartialMultifrontal(ordering)
        values = gtsam.Values()
        for k in keys:
            if k not in dropped:
                values.insert(k, _value(estimate, k))
        for i in range(marginal.size()):
            g = marginal.at(i)
            if g is None or g.empty():
                continue
            lin = gtsam.Values()
            for k in g.keys():  # noqa: SIM118 - not iterable
                lin.insert(int(k), _value(estimate, int(k)))
            # The root-shifted form is written for poses; a marginal that holds point objects
            # keeps the linear form (docs/estimator.md, "A window of poses").
            if self.relative and len(gtsam.utilities.extractPoint2(lin)) == 0:
                factor = relative_marginal(g, estimate)
                if factor is None:
                    continue
                kept.push_back(factor)
            else:
                kept.push_back(gtsam.LinearContainerFactor(g, lin))
            kept_stable.append(None)
        self.isam = gtsam.ISAM2(self._params)
        result = self.isam.update(kept, values)
        self._index = {
            stable: int(actual)
            for stable, actual in zip(kept_stable, result.getNewFactorsIndices(), strict=True)
            if stable is not None
        }
        self.oldest = oldest
        self.rebuilds += 1

    def calculateEstimate(self) -> gtsam.Values:
        return self.isam.calculateEstimate()

    def calculateEstimatePose2(self, key: int) -> gtsam.Pose2:
        return self.isam.calculateEstimatePose2(key)

    def calculateEstimatePoint2(self, key: int) -> np.ndarray:
        return self.isam.calculateEstimatePoint2(key)

    def jointMarginalInformation(self, keys: gtsam.KeyVector) -> gtsam.JointMarginal:
        return self.isam.jointMarginalInformation(keys)

    def jointMarginalCovariance(self, keys: gtsam.KeyVector) -> gtsam.JointMarginal:
        return self.isam.jointMarginalCovariance(keys)

    def marginalCovariance(self, key: int) -> np.ndarray:
        return self.isam.marginalCovariance(key)

    def marginal_covariances(self, keys: Sequence[int]) -> np.ndarray:
        """Each key's marginal covariance, (K, d, d), from one joint marginal: the window's
        marginal puts every object its old poses saw into one clique, and recovering each key's
        covariance from it one by one repeats that clique's inversion per key (598 ms against
        14 ms for 81 objects of the dense world, equal to 3e-12)."""
        if not keys:
            return np.zeros((0, 3, 3))
        joint = self.isam.jointMarginalCovariance(gtsam.KeyVector(list(keys)))
        return np.array([joint.at(k, k) for k in keys])

    def getDelta(self) -> gtsam.VectorValues:
        return self.isam.getDelta()

    def getLinearizationPoint(self) -> gtsam.Values:
        return self.isam.getLinearizationPoint()

    def getFactorsUnsafe(self) -> gtsam.NonlinearFactorGraph:
        return self.isam.getFactorsUnsafe()

    def params(self) -> gtsam.ISAM2Params:
        return self.isam.params()


def _value(values: gtsam.Values, key: int) -> gtsam.Pose2 | np.ndarray:
    """``key``'s value in ``values``: a Pose2, or a point object's Point2."""
    try:
        return values.atPose2(key)
    except RuntimeError:
        return values.atPoint2(key)
