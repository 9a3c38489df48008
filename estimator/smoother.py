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


def relative_marginal(g: gtsam.GaussianFactor, estimate: gtsam.Values) -> gtsam.CustomFactor | None:
    """A linear marginal ``g`` on poses, re-expressed in its variables' poses relative to one of
    them (the root: its first robot pose, else its first key), as a nonlinear factor.

    With δ each variable's tangent at the linearisation point ``estimate``, ``g`` is
    ½‖A δ − b‖². Let r_k = x_root⁻¹ v_k; its tangent is ρ_k = δ_k − Ad(r̂_k⁻¹) δ_root to first
    order, so δ_k = ρ_k + Ad(r̂_k⁻¹) ρ_root and the same Gaussian reads ½‖A′ ρ − b‖² with
    A′_root = A_root + Σ_k A_k Ad(r̂_k⁻¹) and A′_k = A_k. Evaluated with ρ_root =
    Log(x̂_root⁻¹ x_root) and ρ_k = Log(r̂_k⁻¹ x_root⁻¹ v_k), the factor equals ``g`` to first order
    at the linearisation point, and a rigid motion of all its variables together (a later loop
    closure turning the old map) leaves every ρ_k unchanged: only the information ``g`` holds on
    the root's absolute pose (from the robots' start priors) sees it, and that is relinearised on
    the group like a prior. A ``LinearContainerFactor`` takes each variable's local coordinates
    on its own: a pure turn of the whole map stays in its null space, but a turn with a bend
    mixes the two (second-order cross terms of the size of the bend; tested), so after a large
    loop correction it pulls the old map towards where it was. This is the root-shifted form of
    the generic linear constraints of Carlevaris-Bianco, Kaess & Eustice (T-RO 2014).

    None when ``g`` holds no information.
    """
    keys = [int(k) for k in g.keys()]  # noqa: SIM118 - not iterable
    info = g.augmentedInformation()
    n = info.shape[0] - 1
    lam, eta = 0.5 * (info[:n, :n] + info[:n, :n].T), info[:n, n]
    s, u = np.linalg.eigh(lam)
    keep = s > max(float(s.max(initial=0.0)), 1.0) * 1e-12
    if not keep.any():
        return None
    a = np.sqrt(s[keep])[:, None] * u[:, keep].T
    b = (u[:, keep].T @ eta) / np.sqrt(s[keep])
    poses = [k for k in keys if pose_step(k) is not None]
    root = poses[0] if poses else keys[0]
    others = [k for k in keys if k != root]
    order = [root, *others]  # the factor's keys: the root first
    cols = {k: slice(3 * i, 3 * i + 3) for i, k in enumerate(keys)}
    a = np.concatenate([a[:, cols[k]] for k in order], axis=1).reshape(a.shape[0], len(order), 3)
    lin_root = estimate.atPose2(root)
    rel = np.array([_xyt(lin_root.between(estimate.atPose2(k))) for k in others]).reshape(-1, 3)
    # A′: the root's columns gather each other variable's through Ad(r̂_k⁻¹); kept per key,
    # (K, rows, 3), so that the Jacobians are batched products.
    ap = a.transpose(1, 0, 2).copy()
    ap[0] += (a.transpose(1, 0, 2)[1:] @ _adjoint(_inverse(rel))).sum(axis=0)
    flat = ap.transpose(1, 0, 2).reshape(a.shape[0], -1)
    rows = a.shape[0]
    lin_root_inv = _inverse(_xyt(lin_root)[None])
    rel_inv = _inverse(rel)

    def error(this: gtsam.CustomFactor, values: gtsam.Values, jac: list | None) -> np.ndarray:
        x_root = _xyt(values.atPose2(root))[None]
        v = np.array([_xyt(values.atPose2(k)) for k in others]).reshape(-1, 3)
        q = _compose(_inverse(x_root), v)  # x_root⁻¹ v_k
        rho = np.empty((len(order), 3))
        rho[0] = _logmap(_compose(lin_root_inv, x_root))[0]
        rho[1:] = _logmap(_compose(rel_inv, q))
        if jac is not None:
            j = _logmap_derivative(rho)  # d ρ / d e, with d e_root / d x_root = d e_k / d v_k = I
            own = ap @ j
            # d e_k / d x_root = −Ad(q_k⁻¹)
            via = -(j[1:] @ _adjoint(_inverse(q)))
            jac[0] = own[0] + (ap[1:] @ via).sum(axis=0)
            for i in range(1, len(order)):
                jac[i] = own[i]
        return flat @ rho.ravel() - b

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(rows), order, error)


def _xyt(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


def _wrap(theta: np.ndarray) -> np.ndarray:
    return np.arctan2(np.sin(theta), np.cos(theta))


def _inverse(p: np.ndarray) -> np.ndarray:
    """Pose2 inverses of poses (K, 3) as (x, y, θ) rows."""
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    x, y = p[:, 0], p[:, 1]
    return np.stack([-c * x - s * y, s * x - c * y, -p[:, 2]], axis=1)


def _compose(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """p ∘ q of poses (K, 3) or (1, 3) each, as (x, y, θ) rows."""
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    return np.stack(
        [
            p[:, 0] + c * q[:, 0] - s * q[:, 1],
            p[:, 1] + s * q[:, 0] + c * q[:, 1],
            _wrap(p[:, 2] + q[:, 2]),
        ],
        axis=1,
    )


def _adjoint(p: np.ndarray) -> np.ndarray:
    """GTSAM's ``Pose2.AdjointMap`` of poses (K, 3): (K, 3, 3)."""
    c, s = np.cos(p[:, 2]), np.sin(p[:, 2])
    out = np.zeros((len(p), 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = c, -s, p[:, 1]
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = s, c, -p[:, 0]
    out[:, 2, 2] = 1.0
    return out


def _logmap(p: np.ndarray) -> np.ndarray:
    """GTSAM's ``Pose2.Logmap`` of poses (K, 3) with θ in (−π, π]."""
    w = p[:, 2]
    small = np.abs(w) < 1e-10
    c1, s = np.cos(w) - 1.0, np.sin(w)
    det = np.where(small, 1.0, c1 * c1 + s * s)
    # R⁻¹ t − t, turned by π/2
    ux = np.cos(w) * p[:, 0] + s * p[:, 1] - p[:, 0]
    uy = -s * p[:, 0] + np.cos(w) * p[:, 1] - p[:, 1]
    scale = w / det
    out = np.stack([-uy * scale, ux * scale, w], axis=1)
    out[small, :2] = p[small, :2]
    return out


def _logmap_derivative(v: np.ndarray) -> np.ndarray:
    """GTSAM's ``Pose2.LogmapDerivative`` of tangent vectors (K, 3): (K, 3, 3)."""
    a, v1, v2 = v[:, 2], v[:, 0], v[:, 1]
    out = np.zeros((len(v), 3, 3))
    big = np.abs(a) > 1e-5
    ab = np.where(big, a, 1.0)
    half_cot = 0.5 * np.sin(ab) / (1.0 - np.cos(ab))
    out[:, 0, 0] = np.where(big, a * half_cot, 1.0)
    out[:, 0, 1] = np.where(big, -0.5 * a, 0.0)
    out[:, 0, 2] = np.where(big, v1 / ab - v1 * half_cot + 0.5 * v2, 0.5 * v2)
    out[:, 1, 0] = np.where(big, 0.5 * a, 0.0)
    out[:, 1, 1] = out[:, 0, 0]
    out[:, 1, 2] = np.where(big, v2 / ab - 0.5 * v1 - v2 * half_cot, -0.5 * v1)
    out[:, 2, 2] = 1.0
    return out


def marginal_covariances(isam: gtsam.ISAM2 | WindowedISAM2, keys: Sequence[int]) -> np.ndarray:
    """The marginal covariance of each of ``keys`` (Pose2), (K, 3, 3): key by key from a full
    iSAM2, whose cliques keep them apart; from one joint marginal from a windowed one
    (:meth:`WindowedISAM2.marginal_covariances`)."""
    if isinstance(isam, WindowedISAM2):
        return isam.marginal_covariances(keys)
    return np.array([isam.marginalCovariance(k) for k in keys]).reshape(len(keys), 3, 3)


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
                values.insert(k, estimate.atPose2(k))
        for i in range(marginal.size()):
            g = marginal.at(i)
            if g is None or g.empty():
                continue
            if self.relative:
                factor = relative_marginal(g, estimate)
                if factor is None:
                    continue
                kept.push_back(factor)
            else:
                lin = gtsam.Values()
                for k in g.keys():  # noqa: SIM118 - not iterable
                    lin.insert(int(k), estimate.atPose2(int(k)))
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

    def jointMarginalInformation(self, keys: gtsam.KeyVector) -> gtsam.JointMarginal:
        return self.isam.jointMarginalInformation(keys)

    def jointMarginalCovariance(self, keys: gtsam.KeyVector) -> gtsam.JointMarginal:
        return self.isam.jointMarginalCovariance(keys)

    def marginalCovariance(self, key: int) -> np.ndarray:
        return self.isam.marginalCovariance(key)

    def marginal_covariances(self, keys: Sequence[int]) -> np.ndarray:
        """Each key's marginal covariance, (K, 3, 3), from one joint marginal: the window's
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
