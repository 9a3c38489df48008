"""Semantic Unscented FastSLAM (design doc §5): a Rao-Blackwellised particle filter whose every
Gaussian step is an unscented one, with same-x, same-y and collinear relations on top.

The particles live in arrays — poses (N, 3), pose covariances (N, 3, 3), landmark means (N, C, 2)
and covariances (N, C, 2, 2), log-weights (N,) — with one landmark index space shared by all
particles (C is a growing capacity; the first ``len(landmark_ids)`` slots are mapped). Every step is
vectorised over the particles; Python loops only run over the one or two observations of a step.

Over 300 lines for a reason: prediction, landmark update and initialisation, the relation
updates and resampling share the particle arrays and their index space; the unscented transform
and the relations' geometry live in their own modules.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.models.se2 import wrap_angle
from estimator.ufastslam import unscented as ut
from estimator.ufastslam.models import (
    inverse_observe,
    motion,
    observe,
    observe_jacobians,
    relation_residual,
)
from estimator.ufastslam.relations import (
    Group,
    MapView,
    RelationConfig,
    RelationError,
    Row,
    detect,
    parse_label,
    references,
)

Array = NDArray[np.float64]
IntArray = NDArray[np.intp]

log = logging.getLogger(__name__)

ASSOCIATIONS = ("known", "nearest")
_CHI2_2DOF_95 = 5.991
_INITIAL_CAPACITY = 16


@dataclass(frozen=True, slots=True)
class UFastSLAMConfig:
    """Everything the filter assumes (design doc §3–8).

    ``control_std`` = (σ_v m/s, σ_ω rad/s) of the control noise, which must also cover the
    odometry's systematic errors; ``measurement_std`` = (σ_r m, σ_b rad); ``dt`` in seconds;
    ``ut`` the sigma-point scaling; resample when N_eff < ``resample_threshold`` · N;
    ``association``: ``known`` ids, or ``nearest`` neighbour with a χ² ``association_gate``;
    measurements closer than ``min_range`` metres are rejected.
    """

    particles: int = 50
    dt: float = 0.5
    control_std: tuple[float, float] = (0.05, 0.05)
    measurement_std: tuple[float, float] = (0.15, math.radians(2.0))
    ut: ut.UTParams = field(default_factory=ut.UTParams)
    resample_threshold: float = 0.5
    association: str = "known"
    association_gate: float = _CHI2_2DOF_95
    min_range: float = 0.05
    relations: RelationConfig = field(default_factory=RelationConfig)

    def __post_init__(self) -> None:
        if self.particles < 1:
            raise ValueError(f"particles must be ≥ 1, got {self.particles}")
        stds = (self.dt, *self.control_std, *self.measurement_std, self.association_gate)
        if len(self.control_std) != 2 or len(self.measurement_std) != 2:
            raise ValueError("control_std and measurement_std take two numbers each")
        if not all(math.isfinite(s) and s > 0 for s in stds):
            raise ValueError("dt, control_std, measurement_std and the gate must be finite, > 0")
        if not 0.0 <= self.resample_threshold <= 1.0:
            raise ValueError(f"resample_threshold must be in [0, 1], got {self.resample_threshold}")
        if self.association not in ASSOCIATIONS:
            raise ValueError(f"association {self.association!r} (known: {', '.join(ASSOCIATIONS)})")
        if not (math.isfinite(self.min_range) and self.min_range >= 0):
            raise ValueError(f"min_range must be finite and ≥ 0, got {self.min_range}")

    @property
    def control_cov(self) -> Array:
        return np.diag(np.square(self.control_std))

    @property
    def measurement_cov(self) -> Array:
        return np.diag(np.square(self.measurement_std))


@dataclass(frozen=True, slots=True)
class Observation:
    """One range-bearing measurement ``z`` = (r m, b rad) of landmark id ``landmark`` (ignored by
    nearest-neighbour association), with the front end's relation ``labels`` (``KIND:NAME``)."""

    landmark: int
    z: tuple[float, float]
    labels: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if len(self.z) != 2 or not all(math.isfinite(v) for v in self.z):
            raise ValueError(f"observation of landmark {self.landmark}: z must be 2 finite numbers")
        if isinstance(self.labels, str) or not isinstance(self.labels, tuple | list):
            raise RelationError(
                f"observation of landmark {self.landmark}: labels must be a tuple of strings, "
                f"got {self.labels!r}"
            )
        object.__setattr__(self, "labels", tuple(self.labels))
        for label in self.labels:
            parse_label(label)


@dataclass(frozen=True, slots=True)
class AcceptedRelation:
    """A relation applied to a newly mapped landmark: ``kind`` between landmark id ``landmark``
    and the reference ids ``refs``, for the group named ``group``."""

    kind: str
    group: str
    landmark: int
    refs: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class StepReport:
    """What one step did: the landmark id of every observation (−1: rejected), the ids mapped
    this step, the relations applied to them, N_eff before resampling and whether it resampled."""

    associations: tuple[int, ...]
    new_landmarks: tuple[int, ...]
    relations: tuple[AcceptedRelation, ...]
    n_eff: float
    resampled: bool


@dataclass(slots=True)
class _Pending:
    """An observation of this step: its landmark index and whether it is mapped already."""

    obs: Observation
    index: int
    new: bool
    rows: list[Row] = field(default_factory=list)


def systematic_resample(weights: ArrayLike, rng: np.random.Generator) -> IntArray:
    """Indices (N,) drawn by systematic resampling from normalised ``weights`` (N,): one uniform
    offset, N evenly spaced pointers. Particle i is copied ⌊N w_i⌋ or ⌈N w_i⌉ times, so
    E[copies] = N w_i exactly."""
    w = np.asarray(weights, dtype=float)
    n = len(w)
    cumulative = np.cumsum(w)
    cumulative[-1] = 1.0
    pointers = (rng.random() + np.arange(n)) / n
    return np.asarray(np.searchsorted(cumulative, pointers, side="right"), dtype=np.intp)


def _block_diag(blocks: Sequence[Array], batch: tuple[int, ...]) -> Array:
    sizes = [b.shape[-1] for b in blocks]
    n = sum(sizes)
    out = np.zeros((*batch, n, n))
    i = 0
    for b, s in zip(blocks, sizes, strict=True):
        out[..., i : i + s, i : i + s] = b
        i += s
    return out


class UFastSLAM:
    """The filter. ``step(control, observations, rng)`` runs one Δt; estimates are read with
    ``pose_estimate()`` and ``map_estimate()``. Randomness comes only from the ``rng`` argument."""

    def __init__(
        self, config: UFastSLAMConfig, start: ArrayLike, start_cov: ArrayLike | None = None
    ) -> None:
        n = config.particles
        self.config = config
        pose = np.asarray(start, dtype=float)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise ValueError(f"start must be 3 finite numbers (x, y, θ), got {start!r}")
        cov = np.zeros((3, 3)) if start_cov is None else np.asarray(start_cov, dtype=float)
        self.pose = np.tile(pose, (n, 1))
        self.pose[:, 2] = wrap_angle(self.pose[:, 2])
        self.pose_cov = np.tile(cov, (n, 1, 1))
        self.log_w = np.full(n, -math.log(n))
        self.mu = np.zeros((n, _INITIAL_CAPACITY, 2))
        self.sigma = np.zeros((n, _INITIAL_CAPACITY, 2, 2))
        self.landmark_ids: list[int] = []
        self._index: dict[int, int] = {}
        self.groups: list[Group] = []
        self._group_by_name: dict[str, int] = {}
        self._memberships: list[list[int]] = []
        self._next_id = 0

    # ---- public reading -------------------------------------------------------------------

    @property
    def weights(self) -> Array:
        """Normalised particle weights (N,)."""
        w = np.exp(self.log_w - self.log_w.max())
        return np.asarray(w / w.sum())

    @property
    def num_landmarks(self) -> int:
        return len(self.landmark_ids)

    def pose_estimate(self) -> Array:
        """Weighted mean pose (3,), θ as a circular mean."""
        w = self.weights
        xy = w @ self.pose[:, :2]
        theta = math.atan2(float(w @ np.sin(self.pose[:, 2])), float(w @ np.cos(self.pose[:, 2])))
        return np.array([xy[0], xy[1], theta])

    def pose_moments(self) -> tuple[Array, Array]:
        """The filter's pose belief as a Gaussian: the weighted mean (3,) and the covariance
        (3, 3) of the particles' spread plus their mean proposal covariance (θ wrapped)."""
        w = self.weights
        mean = self.pose_estimate()
        dev = self.pose - mean
        dev[:, 2] = wrap_angle(dev[:, 2])
        cov = np.einsum("i,ik,im->km", w, dev, dev) + np.einsum("i,ikm->km", w, self.pose_cov)
        return mean, cov

    def map_estimate(self) -> tuple[list[int], Array]:
        """Landmark ids and their weighted mean positions (L, 2)."""
        n = self.num_landmarks
        return list(self.landmark_ids), np.einsum("i,ilk->lk", self.weights, self.mu[:, :n])

    def group_members(self) -> list[tuple[str, str, list[int]]]:
        """(kind, name, member landmark ids) of every relation group."""
        return [(g.kind, g.name, [self.landmark_ids[m] for m in g.members]) for g in self.groups]

    # ---- the step -------------------------------------------------------------------------

    def step(
        self, control: ArrayLike, observations: Sequence[Observation], rng: np.random.Generator
    ) -> StepReport:
        """One Δt: predict with ``control`` = (v, ω) measured by odometry, then update with the
        ``observations`` made at the new pose."""
        u = np.asarray(control, dtype=float)
        if u.shape != (2,) or not np.all(np.isfinite(u)):
            raise ValueError(f"control must be 2 finite numbers (v, ω), got {control!r}")
        self._predict(u)
        usable = [o for o in observations if o.z[0] >= self.config.min_range]
        if not usable:
            ids = (-1,) * len(observations)
            return StepReport(ids, (), (), self._normalise(), False)
        mapped_before = self.num_landmarks
        pending = self._associate(usable)
        accepted = self._attach_relations(pending, mapped_before)
        self._attach_known_rows(pending, mapped_before)
        for p in pending:
            if not p.new:
                self._propose(p.rows, p)
        for p in pending:
            if p.new and p.rows:
                self._propose(p.rows, p)
        self._sample(rng)
        self._update_known([p for p in pending if not p.new])
        self._add_new([p for p in pending if p.new])
        n_eff = self._normalise()
        resampled = n_eff < self.config.resample_threshold * self.config.particles
        if resampled:
            log.debug("resampling at N_eff = %.1f", n_eff)
            self._resample(rng)
        by_obs = {id(p.obs): self.landmark_ids[p.index] for p in pending}
        ids = tuple(by_obs.get(id(o), -1) for o in observations)
        new_ids = tuple(self.landmark_ids[p.index] for p in pending if p.new)
        return StepReport(ids, new_ids, tuple(accepted), n_eff, resampled)

    # 1. prediction: augmented [pose; n_u] through the motion model
    def _predict(self, u: Array) -> None:
        n = self.config.particles
        mean = np.concatenate([self.pose, np.zeros((n, 2))], axis=1)
        cov = _block_diag([self.pose_cov, self.config.control_cov], (n,))
        dt = self.config.dt

        def f(chi: Array) -> Array:
            return motion(chi[..., :3], u + chi[..., 3:], dt)

        self.pose, self.pose_cov = ut.transform(mean, cov, f, self.config.ut, angular=(2,))

    # 2. data association: known ids, or nearest neighbour on the weighted χ² distance
    def _associate(self, observations: Sequence[Observation]) -> list[_Pending]:
        if self.config.association == "known":
            ids = [o.landmark for o in observations]
            twice = sorted({i for i in ids if ids.count(i) > 1})
            if twice:
                raise ValueError(f"landmark {twice[0]} observed twice in one step")
            return [self._pending_known(o) for o in observations]
        return self._pending_nearest(observations)

    def _pending_known(self, obs: Observation) -> _Pending:
        index = self._index.get(obs.landmark)
        if index is not None:
            return _Pending(obs, index, False)
        return _Pending(obs, self._reserve(obs.landmark), True)

    def _pending_nearest(self, observations: Sequence[Observation]) -> list[_Pending]:
        mapped = self.num_landmarks
        taken: set[int] = set()
        out = []
        for obs in observations:
            best = None
            if mapped:
                d2 = self._weighted_chi2(np.asarray(obs.z), mapped)
                d2[list(taken)] = np.inf
                j = int(np.argmin(d2))
                if d2[j] < self.config.association_gate:
                    best = j
            if best is None:
                out.append(_Pending(obs, self._reserve(self._next_id), True))
            else:
                taken.add(best)
                out.append(_Pending(obs, best, False))
        return out

    def _weighted_chi2(self, z: Array, mapped: int) -> Array:
        """Σ_i w_i νᵀ S⁻¹ ν per mapped landmark (L,), S = H_x P H_xᵀ + H_m Σ H_mᵀ + R linearised
        at each particle's predicted pose."""
        mu = self.mu[:, :mapped]
        h_x, h_m = observe_jacobians(self.pose[:, None, :], mu)
        s = (
            h_m @ self.sigma[:, :mapped] @ np.swapaxes(h_m, -1, -2)
            + h_x @ self.pose_cov[:, None] @ np.swapaxes(h_x, -1, -2)
            + self.config.measurement_cov
        )
        nu = z - observe(self.pose[:, None, :], mu)
        nu[..., 1] = wrap_angle(nu[..., 1])
        d2 = np.einsum("...i,...i->...", nu, np.linalg.solve(s, nu[..., None])[..., 0])
        return np.asarray(self.weights @ d2)

    def _reserve(self, landmark_id: int) -> int:
        """A landmark index for a new landmark; mapped once ``_add_new`` fills it."""
        index = len(self.landmark_ids)
        if index >= self.mu.shape[1]:
            grow = self.mu.shape[1]
            n = self.config.particles
            self.mu = np.concatenate([self.mu, np.zeros((n, grow, 2))], axis=1)
            self.sigma = np.concatenate([self.sigma, np.zeros((n, grow, 2, 2))], axis=1)
        self.landmark_ids.append(landmark_id)
        self._index[landmark_id] = index
        self._memberships.append([])
        self._next_id = max(self._next_id, landmark_id + 1)
        return index

    # 3. relations of the new landmarks, decided once for the whole filter
    def _attach_relations(self, pending: list[_Pending], mapped: int) -> list[AcceptedRelation]:
        rc = self.config.relations
        new = [p for p in pending if p.new]
        if rc.source == "off" or not new:
            return []
        view = self._map_view(mapped)
        accepted = []
        if rc.source == "labels":
            for p in new:
                for label in p.obs.labels:
                    parsed = parse_label(label)
                    g = self._group_by_name.get(parsed.key)
                    if g is None:
                        g = self._new_group(parsed.kind, parsed.key, [])
                    accepted += self._join(p, g, mapped, view)
            return accepted
        pose, pose_cov = self.pose_moments()
        covisible = [p.index for p in pending if not p.new]
        for p in new:
            p_hat, p_cov = self._inverse_moments(pose, pose_cov, np.asarray(p.obs.z))
            for c in detect(p_hat, p_cov, view, self.groups, covisible, rc):
                g = c.group
                if g is None:
                    g = self._new_group(c.kind, f"{c.kind}#{len(self.groups)}", list(c.partners))
                accepted += self._join(p, g, mapped, view)
        return accepted

    def _new_group(self, kind: str, name: str, members: list[int]) -> int:
        g = len(self.groups)
        self.groups.append(Group(kind, name, list(members)))
        self._group_by_name[name] = g
        for m in members:
            self._memberships[m].append(g)
        return g

    def _join(self, p: _Pending, g: int, mapped: int, view: MapView) -> list[AcceptedRelation]:
        group = self.groups[g]
        if p.index in group.members:
            return []
        refs = references(group.kind, [m for m in group.members if m < mapped], view)
        group.members.append(p.index)
        self._memberships[p.index].append(g)
        if not refs:
            return []
        p.rows.append(Row(group.kind, g, p.index, refs))
        ref_ids = tuple(self.landmark_ids[r] for r in refs)
        log.debug(
            "landmark %d joins %s, referenced to %s",
            self.landmark_ids[p.index],
            group.name,
            ref_ids,
        )
        return [AcceptedRelation(group.kind, group.name, self.landmark_ids[p.index], ref_ids)]

    def _attach_known_rows(self, pending: list[_Pending], mapped: int) -> None:
        """EVERY mode: the relation rows of the already mapped landmarks (none in ONCE mode)."""
        known = [p for p in pending if not p.new]
        if self.config.relations.mode == "once" or not known:
            return
        view = self._map_view(mapped)
        for p in known:
            for g in self._memberships[p.index]:
                group = self.groups[g]
                others = [m for m in group.members if m < mapped and m != p.index]
                refs = references(group.kind, others, view)
                if refs:
                    p.rows.append(Row(group.kind, g, p.index, refs))

    def _map_view(self, mapped: int) -> MapView:
        w = self.weights
        mu, sigma = self.mu[:, :mapped], self.sigma[:, :mapped]
        mean = np.einsum("i,ilk->lk", w, mu)
        dev = mu - mean
        spread = np.einsum("i,ilk,ilm->lkm", w, dev, dev)
        return MapView(mean, np.einsum("i,ilkm->lkm", w, sigma) + spread)

    def _inverse_moments(self, pose: Array, pose_cov: Array, z: Array) -> tuple[Array, Array]:
        mean = np.concatenate([pose, np.zeros(2)])
        cov = _block_diag([pose_cov, self.config.measurement_cov], ())

        def f(chi: Array) -> Array:
            return inverse_observe(chi[..., :3], z - chi[..., 3:])

        return ut.transform(mean, cov, f, self.config.ut)

    # 4. pose proposal: one unscented update per observation, fresh sigma points each time
    def _propose(self, rows: list[Row], p: _Pending) -> None:
        n = self.config.particles
        z = np.asarray(p.obs.z)
        if p.new:
            blocks_mean = [self.pose, np.zeros((n, 2))]
            blocks_cov = [self.pose_cov, np.broadcast_to(self.config.measurement_cov, (n, 2, 2))]
        else:
            blocks_mean = [self.pose, self.mu[:, p.index]]
            blocks_cov = [self.pose_cov, self.sigma[:, p.index]]
        refs = _unique_refs(rows)
        for r in refs:
            blocks_mean.append(self.mu[:, r])
            blocks_cov.append(self.sigma[:, r])
        mean = np.concatenate(blocks_mean, axis=1)
        cov = _block_diag(blocks_cov, (n,))
        new = p.new

        def g(chi: Array) -> Array:
            pose = chi[..., :3]
            if new:
                landmark = inverse_observe(pose, z - chi[..., 3:5])
                out = []
            else:
                landmark = chi[..., 3:5]
                out = [observe(pose, landmark)]
            out += _relation_rows(rows, refs, landmark, chi[..., 5:])
            return np.concatenate(out, axis=-1)

        y, r_add, angular = self._measurement(z, len(rows), with_range_bearing=not new)
        res = ut.update(mean, cov, g, y, r_add, 3, self.config.ut, angular)
        self.pose = res.mean
        self.pose[:, 2] = wrap_angle(self.pose[:, 2])
        self.pose_cov = res.cov
        self.log_w = self.log_w + res.log_likelihood

    def _measurement(
        self, z: Array, n_rows: int, with_range_bearing: bool
    ) -> tuple[Array, Array, tuple[int, ...]]:
        """Measured vector, additive noise and angular components of [h; relation rows]."""
        s2 = self.config.relations.row_std**2
        if not with_range_bearing:
            return np.zeros(n_rows), s2 * np.eye(n_rows), ()
        y = np.concatenate([z, np.zeros(n_rows)])
        r = np.zeros((2 + n_rows, 2 + n_rows))
        r[:2, :2] = self.config.measurement_cov
        r[2:, 2:] = s2 * np.eye(n_rows)
        return y, r, (1,)

    # 5. sample every particle's pose from its proposal
    def _sample(self, rng: np.random.Generator) -> None:
        root = ut.psd_sqrt(self.pose_cov)
        eps = rng.standard_normal(self.pose.shape)
        self.pose = self.pose + np.einsum("nij,nj->ni", root, eps)
        self.pose[:, 2] = wrap_angle(self.pose[:, 2])
        self.pose_cov = np.zeros_like(self.pose_cov)

    # 6. landmark updates given the sampled pose (batched over landmarks in ONCE mode)
    def _update_known(self, known: list[_Pending]) -> None:
        plain = []
        for p in known:
            if p.rows:
                self._update_landmark(p, p.rows)
            else:
                plain.append(p)
        if not plain:
            return
        idx = np.array([p.index for p in plain])
        zs = np.array([p.obs.z for p in plain])
        pose = self.pose[:, None, None, :]

        def g(chi: Array) -> Array:
            return observe(pose, chi)

        res = ut.update(
            self.mu[:, idx],
            self.sigma[:, idx],
            g,
            zs,
            self.config.measurement_cov,
            2,
            self.config.ut,
            (1,),
        )
        self.mu[:, idx] = res.mean
        self.sigma[:, idx] = res.cov

    def _update_landmark(self, p: _Pending, rows: list[Row]) -> None:
        """One landmark with relation rows; the references are consider states."""
        n = self.config.particles
        z = None if p.new else np.asarray(p.obs.z)
        refs = _unique_refs(rows)
        mean = np.concatenate([self.mu[:, p.index], *(self.mu[:, r] for r in refs)], axis=1)
        cov = _block_diag([self.sigma[:, p.index], *(self.sigma[:, r] for r in refs)], (n,))
        pose = self.pose[:, None, :]

        def g(chi: Array) -> Array:
            landmark = chi[..., :2]
            out = [] if z is None else [observe(pose, landmark)]
            out += _relation_rows(rows, refs, landmark, chi[..., 2:])
            return np.concatenate(out, axis=-1)

        y, r_add, angular = self._measurement(
            np.zeros(2) if z is None else z, len(rows), with_range_bearing=z is not None
        )
        res = ut.update(mean, cov, g, y, r_add, 2, self.config.ut, angular)
        self.mu[:, p.index] = res.mean
        self.sigma[:, p.index] = res.cov

    # 7. new landmarks: unscented transform of h⁻¹ over the measurement noise, then relations
    def _add_new(self, new: list[_Pending]) -> None:
        if not new:
            return
        idx = np.array([p.index for p in new])
        zs = np.array([p.obs.z for p in new])[None, :, None, :]
        pose = self.pose[:, None, None, :]

        def f(noise: Array) -> Array:
            return inverse_observe(pose, zs - noise)

        mean, cov = ut.transform(np.zeros(2), self.config.measurement_cov, f, self.config.ut)
        self.mu[:, idx] = mean
        self.sigma[:, idx] = cov
        for p in new:
            if p.rows:
                self._update_landmark(p, p.rows)

    # 8–9. weights and resampling
    def _normalise(self) -> float:
        """Normalise the log-weights; return N_eff = 1 / Σ w²."""
        self.log_w = self.log_w - _logsumexp(self.log_w)
        w = np.exp(self.log_w)
        return float(1.0 / np.sum(w * w))

    def _resample(self, rng: np.random.Generator) -> None:
        idx = systematic_resample(np.exp(self.log_w), rng)
        # Fancy indexing copies: no two particles ever share a landmark array.
        self.pose = self.pose[idx]
        self.pose_cov = self.pose_cov[idx]
        self.mu = self.mu[idx]
        self.sigma = self.sigma[idx]
        self.log_w = np.full(self.config.particles, -math.log(self.config.particles))


def _unique_refs(rows: list[Row]) -> list[int]:
    """The reference landmarks of ``rows``, each once: a landmark that anchors two rows is one
    consider state, not two independent copies."""
    return list(dict.fromkeys(r for row in rows for r in row.refs))


def _relation_rows(rows: list[Row], refs: list[int], landmark: Array, block: Array) -> list[Array]:
    """Residual columns (..., 1) of every row; ``block`` (..., 2·len(refs)) holds the reference
    landmarks ``refs`` in order."""
    where = {r: i for i, r in enumerate(refs)}
    out = []
    for row in rows:
        cols = [c for r in row.refs for c in (2 * where[r], 2 * where[r] + 1)]
        ref = block[..., cols].reshape(*block.shape[:-1], len(row.refs), 2)
        out.append(relation_residual(row.kind, landmark, ref)[..., None])
    return out


def _logsumexp(x: Array) -> float:
    top = float(np.max(x))
    return top + math.log(float(np.sum(np.exp(x - top))))
