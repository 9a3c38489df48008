"""Data association on the robot (design note "data association", §2): which of the robot's map
objects each detection of a frame without global ids measures, or whether it is new.

Step 0 of a robot's step, before its belief steps: predict the robot pose x_k = x_{k−1} ∘ u, take
the map objects within the sensor's range (+ a margin) with their joint marginal covariance with
x_k (iSAM2's, propagated through the odometry), gate every pairing of a detection and an object
on χ²_d(1 − α) (d the object kind's dimension), and choose the frame's pairings jointly (joint
compatibility, Neira & Tardós 2001): the jointly compatible set of pairings of highest score,

    Σ_pairs [log N(ν; 0, S_joint) + class LLR] + Σ_unpaired log λ_d,

searched exhaustively up to ``exhaustive`` detections, greedily beyond. The class LLR of a
pairing (detection d, object j) is ``log Σ_c P(c_j = c) P(z | c, ψ̂_j) − log Σ_c P(c) P(z | c,
ψ_d)``: the belief's class marginals and the classifier model at the predicted viewpoint, against
a new object of unknown class seen where the detection places it. λ_d is the density of new
objects and false detections in measurement space (``AssociationConfig.density``, per m²).

Detections left over go to *tentative* objects (second stage: they take only what the map did
not; individually gated, greedy one-to-one by score). A tentative object lives here, never in
the belief: confirmed at its ``confirm``-th hit, its detection of that step enters the belief as
a new object; dropped after ``drop_after`` steps in view without a hit (or ``forget_after``
steps without one), so clutter that is never confirmed leaves nothing behind. At its
confirmation its earlier detections go to the belief too (``Association.replay``), which adds
them from the poses they were made at (``HybridBelief.step``'s ``replay``): an object a robot
passes by is seen a handful of times, and leaving out the first ``confirm`` − 1 of them made
the dense world's robot error at k = 200 1.5× that of given ids (1.99 against 1.33 m; with
them 1.30 m, docs/estimator.md).

The result is the same frame with robot-local ids (the confirmed objects' track numbers,
``ids = "local"``) holding only detections of confirmed objects, and the replay.
Pure: no clock, no randomness; the result does not depend on the order of a frame's detections
(they are put in a canonical order first).

Over 300 lines for a reason: prediction, gating, the joint search and the tentative objects'
life are one decision per frame over one set of candidates; split, each part would need the
others' covariance layout and track numbering.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import NDArray

from estimator.chi2 import chi2_ppf
from estimator.factors import object_key
from estimator.hybrid import BeliefModel, Continuous, HybridBelief
from estimator.logsumexp import logsumexp
from estimator.models import LOCAL_IDS, Detection, SensorFrame, se2, viewpoint
from estimator.models.objects import ObjectKind

Array = NDArray[np.float64]

_STEP = 1e-6  # numerical Jacobians: central differences of this size


@dataclass(frozen=True, slots=True)
class SensorField:
    """Where the robot's sensor sees: within ``range`` metres and ``|bearing| ≤ half_angle``."""

    range: float
    half_angle: float

    def sees(self, xy: Array) -> NDArray[np.bool_]:
        """Whether body-frame positions (..., 2) are in the field."""
        r = np.hypot(xy[..., 0], xy[..., 1])
        bearing = np.abs(np.arctan2(xy[..., 1], xy[..., 0]))
        return np.asarray((r <= self.range) & (bearing <= self.half_angle))


@dataclass(frozen=True, slots=True)
class AssociationConfig:
    """``alpha``: the gates' false-rejection rate; ``density``: new objects and false detections
    per m² (λ's source: λ = density / 2π per m² rad for a pose's (x, y, θ), density × range per
    rad m for a point's (bearing, range)); ``confirm``: hits that make a tentative object a map
    object; ``drop_after``: in-view steps without a hit that drop a tentative one;
    ``forget_after``: steps without a hit that drop it wherever it is; ``exhaustive``: the most
    detections searched exhaustively (greedy beyond); ``budget``: the most joint evaluations
    (one each ~0.07 ms here) an exhaustive search may make: cut short beyond, it keeps the best
    pairing found so far or the greedy one, whichever scores higher (``Association.cut``), so a
    frame's search stays bounded in time where many candidates gate (a map with split objects:
    MRCLAM without its barcodes took 55,000 evaluations, 3.7 s, on one frame; the dense
    simulated world at most 1,372); ``margin``: metres beyond the sensor's
    range within which map objects are candidates; ``class_evidence``: whether the class LLR
    enters the score (off: geometry alone, the baseline)."""

    alpha: float = 1e-3
    density: float = 0.1
    confirm: int = 3
    drop_after: int = 3
    forget_after: int = 50
    exhaustive: int = 8
    budget: int = 2000
    margin: float = 1.0
    class_evidence: bool = True

    def __post_init__(self) -> None:
        if not 0.0 < self.alpha < 1.0:
            raise ValueError(f"alpha must be in (0, 1), got {self.alpha}")
        if not (math.isfinite(self.density) and self.density > 0.0):
            raise ValueError(f"density must be > 0 per m², got {self.density}")
        if min(self.confirm, self.drop_after, self.forget_after, self.budget) < 1:
            raise ValueError("confirm, drop_after, forget_after and budget must be ≥ 1")
        if self.exhaustive < 0:
            raise ValueError("exhaustive must be ≥ 0")
        if not (math.isfinite(self.margin) and self.margin >= 0.0):
            raise ValueError(f"margin must be ≥ 0 m, got {self.margin}")


@dataclass(slots=True)
class _Tentative:
    """A tentative object: its track number, world estimate (dim,) from its last hit and that
    estimate's covariance (dim, dim) from the detection's noise, the step of the last hit, its
    hits, in-view misses since, class log-evidence (M,) and its detections so far with their
    steps (at most ``confirm``: the earlier ones are replayed into the belief at its
    confirmation)."""

    track: int
    obj: Array
    cov: Array
    k: int
    hits: int
    misses: int
    log_evidence: Array
    seen: list[tuple[int, Detection]] = field(default_factory=list)


@dataclass(frozen=True, slots=True)
class Association:
    """One frame's association. ``frame``: for the belief, robot-local ids, only detections of
    confirmed objects, in a canonical order (of their values); ``tracks`` (per input detection):
    the track it went to, a map object's local id or a tentative object's number (the same
    numbering); ``entered``
    (per input detection): whether it is in ``frame``; ``confirmed``: tracks that became map
    objects at this frame; ``dropped``: tentative tracks dropped; ``nis``: the normalised
    innovation squared of each detection paired with a map object (NaN for the others);
    ``cut``: the joint search stopped at its budget (``AssociationConfig.budget``);
    ``replay``: the earlier detections of the objects confirmed at this frame as (robot, step,
    detection under the object's local id), for the belief to add from those steps' poses
    (``HybridBelief.step``'s ``replay``), in the order of their steps and values."""

    frame: SensorFrame
    tracks: tuple[int, ...]
    entered: tuple[bool, ...]
    confirmed: tuple[int, ...] = ()
    dropped: tuple[int, ...] = ()
    nis: tuple[float, ...] = field(default=())
    cut: bool = False
    replay: tuple[tuple[str, int, Detection], ...] = ()


class Associator:
    """Associates one robot's frames with its own belief's objects (module docstring), under
    the belief's ``model`` (object kind, noise, classes, classifier); ``sensor``: where the
    robot's sensor sees."""

    def __init__(
        self, model: BeliefModel, sensor: SensorField, config: AssociationConfig | None = None
    ) -> None:
        self.kind: ObjectKind = model.objects
        self.field = sensor
        self.config = config or AssociationConfig()
        self.classifier = model.classifier
        self._q = np.asarray(model.odometry_noise.cov, dtype=float)
        self._r = np.asarray(model.geometric_noise.cov, dtype=float)
        self._log_prior = np.log(np.asarray(model.class_prior, dtype=float))
        self._gate = chi2_ppf(1.0 - self.config.alpha, self.kind.dim)
        self.tentative: list[_Tentative] = []
        self.next_track = 0

    # -- the frame ------------------------------------------------------------------------

    def associate(
        self, belief: HybridBelief, frame: SensorFrame, guide: HybridBelief | None = None
    ) -> Association:
        """Associate ``frame`` (any id kind; its ids are not read) with ``belief``, a robot's own
        belief at step k − 1, and update the tentative objects.

        ``guide``: a belief that holds ``belief``'s objects under the same ids and knows the
        robot better, at the same step (a node's D, fused with its peers'): the detections are
        then gated and scored on the guide's estimate of the robot and of those objects, their
        covariances and class posterior, and new tentative objects are placed from the guide's
        pose. Which object a detection is stays a decision; what enters ``belief`` is still the
        robot's own detection, so no peer's information is counted in it. A robot whose own
        estimate has drifted metres off (its map with it) would otherwise gate its detections
        on a wrong prediction, split its objects and localise on the copies."""
        robot = frame.robot
        source = belief
        among: set[int] | None = None
        if guide is not None:
            if guide.step_of.get(robot) != belief.step_of.get(robot):
                raise ValueError(
                    f"the guide of {robot}'s association is at step {guide.step_of.get(robot)}, "
                    f"its belief at {belief.step_of.get(robot)}"
                )
            source, among = guide, set(belief.object_ids)
        cont, x_prev, x_k, order, dets, z = self._prepared(source, frame)
        track: list[int | None] = [None] * len(dets)
        nis = [math.nan] * len(dets)
        cut = False
        if dets and belief.object_ids:
            cut = self._map_stage(source, cont, robot, x_prev, x_k, dets, z, track, nis, among)
        hit, confirmed, seen = self._tentative_stage(belief, x_k, frame.k, dets, z, track)
        dropped = self._misses(x_k, frame.k, hit)
        entered = [False] * len(dets)
        known = set(belief.object_ids)
        for i, t in enumerate(track):
            assert t is not None
            entered[i] = t in known or t in confirmed
        out_tracks = [0] * len(dets)
        out_entered = [False] * len(dets)
        out_nis = [math.nan] * len(dets)
        for i, j in enumerate(order):
            out_tracks[j], out_entered[j], out_nis[j] = int(track[i] or 0), entered[i], nis[i]
        # in the canonical order too, so that the belief's step does not see the arrival order
        kept = tuple(
            Detection(out_tracks[j], frame.detections[j].z_geo, frame.detections[j].z_sem)
            for j in order
            if out_entered[j]
        )
        local = SensorFrame(robot, frame.k, frame.odometry, kept, frame.true_pose, LOCAL_IDS)
        return Association(
            local,
            tuple(out_tracks),
            tuple(out_entered),
            confirmed,
            dropped,
            tuple(out_nis),
            cut,
            tuple((robot, step, d) for step, d in seen),
        )

    def pair(
        self, belief: HybridBelief, frame: SensorFrame, among: Collection[int]
    ) -> dict[int, int]:
        """Pair ``frame``'s detections with ``belief``'s objects ``among`` (stage 1 alone: the
        gates and the joint search, scored against a new object; the tentative objects are
        neither read nor changed): detection index (in ``frame``'s order) → object id. A node
        pairs the detections its L left unconfirmed with the objects only peers inform D of."""
        among = set(among)
        if not frame.detections or not among.intersection(belief.object_ids):
            return {}
        cont, x_prev, x_k, order, dets, z = self._prepared(belief, frame)
        track: list[int | None] = [None] * len(dets)
        nis = [math.nan] * len(dets)
        self._map_stage(belief, cont, frame.robot, x_prev, x_k, dets, z, track, nis, among)
        return {order[i]: t for i, t in enumerate(track) if t is not None}

    def _prepared(
        self, belief: HybridBelief, frame: SensorFrame
    ) -> tuple[Continuous, Array, Array, list[int], list[Detection], Array]:
        """What both stages read: ``belief``'s continuous part, the robot's pose x_{k−1} and its
        prediction x_k, the detections' canonical order, the detections in it and their z."""
        cont = belief.map_hypothesis().continuous
        x_prev = cont.pose(belief.pose_key(frame.robot))
        x_k = se2.compose(x_prev, frame.odometry)
        order = _canonical(frame.detections)
        dets = [frame.detections[i] for i in order]
        z = np.array([d.z_geo for d in dets]).reshape(len(dets), self.kind.dim)
        return cont, x_prev, x_k, order, dets, z

    # -- stage 1: the map's objects ---------------------------------------------------------

    def _map_stage(
        self,
        belief: HybridBelief,
        cont: Continuous,
        robot: str,
        x_prev: Array,
        x_k: Array,
        dets: Sequence[Detection],
        z: Array,
        track: list[int | None],
        nis: list[float],
        among: Collection[int] | None = None,
    ) -> bool:
        """Pair detections with map objects (into ``track`` and ``nis``; only those ``among``
        when given); whether the joint search was cut short at its budget."""
        kind, dim = self.kind, self.kind.dim
        ids = np.array(belief.object_ids)
        objects = np.array([cont.pose(object_key(int(j))) for j in ids]).reshape(-1, dim)
        rel = _body_xy(x_k, objects)
        reach = self.field.range + self.config.margin
        near = np.flatnonzero(np.hypot(rel[:, 0], rel[:, 1]) <= reach)
        if among is not None:
            near = near[np.isin(ids[near], np.fromiter(among, dtype=ids.dtype))]
        if not len(near):
            return False
        ids, objects = ids[near], objects[near]
        keys = [belief.pose_key(robot), *(object_key(int(j)) for j in ids)]
        joint = cont.isam.jointMarginalCovariance(gtsam.KeyVector(keys))
        p = _propagate(np.asarray(joint.fullMatrix()), x_prev, x_k, self._q)
        n = len(ids)
        h = _jacobians(kind, x_k, objects)  # (n, dim, 3 + dim)
        z_pred = kind.measure(x_k, objects)  # (n, dim)
        nu = _residual(kind, z_pred[None, :, :], z[:, None, :])  # (D, n, dim)
        rows = np.zeros((n, dim, 3 + n * dim))  # each candidate's Jacobian in the joint layout
        for c in range(n):
            rows[c, :, :3] = h[c, :, :3]
            rows[c, :, 3 + c * dim : 3 + (c + 1) * dim] = h[c, :, 3:]
        flat = rows.reshape(n * dim, -1)
        hph = (flat @ p @ flat.T).reshape(n, dim, n, dim)
        s_ind = hph[np.arange(n), :, np.arange(n), :] + self._r  # (n, dim, dim)
        s_inv = np.linalg.inv(s_ind)
        d2 = np.einsum("dni,nij,dnj->dn", nu, s_inv, nu)
        log_norm = -0.5 * np.linalg.slogdet(2.0 * np.pi * s_ind)[1]  # (n,)
        llr = self._class_llr(belief, near, x_k, objects, dets, z)
        log_new = np.array([self._log_lambda(zi) for zi in z])
        gain = -0.5 * d2 + log_norm[None, :] + llr - log_new[:, None]  # a pairing against "new"
        search = _JointSearch(nu, hph, self._r, llr - log_new[:, None], self.config.alpha)
        best, cut = search.best(d2 <= self._gate, gain, self.config.exhaustive, self.config.budget)
        for d, c in best.items():
            track[d] = int(ids[c])
            nis[d] = float(d2[d, c])
        return cut

    def _class_llr(
        self,
        belief: HybridBelief,
        near: NDArray[np.int64],
        x_k: Array,
        objects: Array,
        dets: Sequence[Detection],
        z: Array,
    ) -> Array:
        """(D, n): log Σ_c P(c_j = c) P(z_d | c, ψ̂_j) − log Σ_c P(c) P(z_d | c, ψ_d)."""
        if not self.config.class_evidence:
            return np.zeros((len(dets), len(near)))
        log_p = np.log(np.maximum(belief.class_marginals()[near], 1e-300))  # (n, M)
        psi_obj = viewpoint(x_k, self.kind.as_pose(objects))  # (n,)
        ll_obj = self._log_likelihoods(dets, np.broadcast_to(psi_obj, (len(dets), len(near))))
        psi_det = viewpoint(x_k, self.kind.as_pose(self.kind.place(x_k, z)))  # (D,)
        ll_det = self._log_likelihoods(dets, psi_det[:, None])[:, 0]  # (D, M)
        same = logsumexp(ll_obj + log_p[None, :, :], axis=2)
        new = logsumexp(ll_det + self._log_prior[None, :], axis=1)
        return np.asarray(same - np.asarray(new)[:, None])

    def _log_likelihoods(self, dets: Sequence[Detection], psi: Array) -> Array:
        """log P(z_d | c, ψ_dn) (D, n, M) for ψ (D, n)."""
        model = self.classifier
        out = np.empty((*psi.shape, len(self._log_prior)))
        for d, det in enumerate(dets):
            for c in range(len(self._log_prior)):
                out[d, :, c] = model.log_likelihood(det.z_sem, c, psi[d])
        return out

    def _log_lambda(self, z: Array) -> float:
        """log λ of a detection ``z`` (module docstring)."""
        if self.kind.dim == 3:
            return math.log(self.config.density / (2.0 * math.pi))
        return math.log(self.config.density * max(float(z[1]), 1e-3))

    # -- stage 2: tentative objects ---------------------------------------------------------

    def _tentative_stage(
        self,
        belief: HybridBelief,
        x_k: Array,
        k: int,
        dets: Sequence[Detection],
        z: Array,
        track: list[int | None],
    ) -> tuple[set[int], tuple[int, ...], tuple[tuple[int, Detection], ...]]:
        """The detections the map did not take, paired greedily with tentative objects (or
        starting new ones); the tentatives hit, the tracks confirmed at this frame and the
        earlier detections of those (``Association.replay``)."""
        kind = self.kind
        left = [i for i, t in enumerate(track) if t is None]
        hit: set[int] = set()
        confirmed: list[int] = []
        scores = []
        if left and self.tentative:
            objs = np.array([t.obj for t in self.tentative])
            z_pred = kind.measure(x_k, objs)  # (T, dim)
            h = _jacobians(kind, x_k, objs)  # (T, dim, 3 + dim)
            hx, ho = h[:, :, :3], h[:, :, 3:]
            drift = np.array([k - t.k for t in self.tentative], dtype=float)
            cov = np.array([t.cov for t in self.tentative])
            s = (
                drift[:, None, None] * (hx @ self._q @ hx.transpose(0, 2, 1))
                + ho @ cov @ ho.transpose(0, 2, 1)
                + self._r
            )
            s_inv = np.linalg.inv(s)
            log_norm = -0.5 * np.linalg.slogdet(2.0 * np.pi * s)[1]  # (T,)
            nu = _residual(kind, z_pred[None, :, :], z[left][:, None, :])  # (L, T, dim)
            d2 = np.einsum("lti,tij,ltj->lt", nu, s_inv, nu)
            for li, ti in zip(*np.nonzero(d2 <= self._gate), strict=True):
                i, t = left[int(li)], self.tentative[int(ti)]
                score = -0.5 * float(d2[li, ti]) + float(log_norm[ti]) - self._log_lambda(z[i])
                if self.config.class_evidence:
                    score += self._tentative_llr(t, x_k, dets[i], z[i])
                if score > 0.0:  # more likely this tentative object than a new one
                    scores.append((-score, i, int(ti)))
        taken: set[int] = set()
        for _, i, ti in sorted(scores):
            if i in taken or ti in hit:
                continue
            taken.add(i)
            hit.add(ti)
            t = self.tentative[ti]
            self._update(t, x_k, k, dets[i], z[i])
            track[i] = t.track
            if t.hits >= self.config.confirm:
                confirmed.append(t.track)
        for i in left:
            if i in taken:
                continue
            t = self._new_tentative(x_k, k, dets[i], z[i])
            track[i] = t.track
            hit.add(len(self.tentative) - 1)
            if t.hits >= self.config.confirm:
                confirmed.append(t.track)
        done = set(confirmed)
        hit_tracks = {self.tentative[ti].track for ti in hit}
        replay = sorted(
            (
                (step, Detection(t.track, d.z_geo, d.z_sem))
                for t in self.tentative
                if t.track in done
                for step, d in t.seen
                if step != k
            ),
            key=lambda sd: (sd[0], sd[1].object_id, tuple(sd[1].z_geo.tolist())),
        )
        self.tentative = [t for t in self.tentative if t.track not in done]
        return hit_tracks, tuple(confirmed), tuple(replay)

    def _tentative_llr(self, t: _Tentative, x_k: Array, det: Detection, z: Array) -> float:
        psi_t = float(viewpoint(x_k, self.kind.as_pose(t.obj)))
        psi_d = float(viewpoint(x_k, self.kind.as_pose(self.kind.place(x_k, z))))
        ll_t = self._log_likelihoods([det], np.array([[psi_t, psi_d]]))[0]  # (2, M)
        post = t.log_evidence + self._log_prior
        post = post - logsumexp(post)
        return float(logsumexp(ll_t[0] + post) - logsumexp(ll_t[1] + self._log_prior))

    def _placed(self, x_k: Array, z: Array) -> tuple[Array, Array]:
        """The object a detection places from x_k and its covariance from the detection's
        noise alone (the robot's own uncertainty is the trajectory's, shared by every later
        prediction from it)."""
        obj = self.kind.place(x_k, z)
        j = np.empty((self.kind.dim, self.kind.dim))
        for a in range(self.kind.dim):
            e = np.zeros(self.kind.dim)
            e[a] = _STEP
            hi = _object_local(self.kind, obj, self.kind.place(x_k, _retract(self.kind, z, e)))
            lo = _object_local(self.kind, obj, self.kind.place(x_k, _retract(self.kind, z, -e)))
            j[:, a] = (hi - lo) / (2 * _STEP)
        return obj, j @ self._r @ j.T

    def _class_evidence(self, x_k: Array, obj: Array, det: Detection) -> Array:
        psi = float(viewpoint(x_k, self.kind.as_pose(obj)))
        return np.asarray(self._log_likelihoods([det], np.array([[psi]]))[0, 0])

    def _new_tentative(self, x_k: Array, k: int, det: Detection, z: Array) -> _Tentative:
        obj, cov = self._placed(x_k, z)
        t = _Tentative(self.next_track, obj, cov, k, 1, 0, self._class_evidence(x_k, obj, det))
        t.seen.append((k, det))
        self.next_track += 1
        self.tentative.append(t)
        return t

    def _update(self, t: _Tentative, x_k: Array, k: int, det: Detection, z: Array) -> None:
        """A hit: the tentative object's estimate fused with the one the detection places (the
        old one widened by the odometry noise since its last hit), in the new one's tangent."""
        obj, cov = self._placed(x_k, z)
        dim = self.kind.dim
        old_cov = t.cov + (k - t.k) * self._q[:dim, :dim]
        old_info = np.linalg.inv(old_cov)
        t.cov = np.linalg.inv(old_info + np.linalg.inv(cov))
        shift = t.cov @ old_info @ _object_local(self.kind, obj, t.obj)
        t.obj = _retract(self.kind, obj, shift)
        t.k, t.hits, t.misses = k, t.hits + 1, 0
        t.log_evidence = t.log_evidence + self._class_evidence(x_k, t.obj, det)
        t.seen.append((k, det))

    def _misses(self, x_k: Array, k: int, hit: set[int]) -> tuple[int, ...]:
        """Count an in-view miss for every tentative object not hit; drop those past
        ``drop_after`` misses or ``forget_after`` steps without a hit."""
        dropped = []
        kept = []
        for t in self.tentative:
            in_view = bool(self.field.sees(_body_xy(x_k, t.obj[None, :]))[0])
            if t.track not in hit and in_view:
                t.misses += 1
            if t.misses >= self.config.drop_after or k - t.k >= self.config.forget_after:
                dropped.append(t.track)
            else:
                kept.append(t)
        self.tentative = kept
        return tuple(dropped)


# -- the joint search ---------------------------------------------------------------------------


class _JointSearch:
    """The jointly compatible pairings of one frame's detections (D) with the candidates (n):
    innovations ``nu`` (D, n, dim), H P Hᵀ between the candidates' predictions ``hph``
    (n, dim, n, dim), the detection noise ``r`` (dim, dim) and each pairing's score apart from
    its Gaussian, ``extra`` (D, n): class LLR − log λ."""

    def __init__(self, nu: Array, hph: Array, r: Array, extra: Array, alpha: float) -> None:
        self.nu, self.hph, self.r, self.extra, self.alpha = nu, hph, r, extra, alpha
        self.dim = r.shape[0]

    def joint(self, pairs: Sequence[tuple[int, int]]) -> float | None:
        """The score of a set of pairings (joint log N(ν; 0, S) + Σ extra), or None when they
        are not jointly compatible (joint NIS above χ²_{m·dim}(1 − α))."""
        if not pairs:
            return 0.0
        m, dim = len(pairs), self.dim
        det = [d for d, _ in pairs]
        cand = [c for _, c in pairs]
        s = self.hph[np.ix_(cand, range(dim), cand, range(dim))].transpose(0, 1, 2, 3)
        s = s.reshape(m * dim, m * dim) + np.kron(np.eye(m), self.r)
        nu = self.nu[det, cand].reshape(-1)
        try:
            chol = np.linalg.cholesky(s)
        except np.linalg.LinAlgError:
            return None
        white = np.linalg.solve(chol, nu)
        d2 = float(white @ white)
        if d2 > _chi2(m * dim, self.alpha):
            return None
        log_det = 2.0 * float(np.log(np.diag(chol)).sum())
        gauss = -0.5 * d2 - 0.5 * log_det - 0.5 * m * dim * math.log(2.0 * math.pi)
        return gauss + float(self.extra[det, cand].sum())

    def best(
        self, gated: NDArray[np.bool_], gain: Array, exhaustive: int, budget: int = 2000
    ) -> tuple[dict[int, int], bool]:
        """Detection → candidate: the best jointly compatible one-to-one pairing, exhaustive up
        to ``exhaustive`` detections with a gated candidate, greedy by ``gain`` beyond; and
        whether the exhaustive search was cut short after ``budget`` joint evaluations (then the
        better of the best found and the greedy pairing)."""
        # Each detection's candidates best first, and "new" after them: a search cut short at
        # its budget has then met the pairings most likely to score, not only "all new" ones.
        # (A search that finishes finds the same optimum in any order.)
        options: list[list[int]] = []
        for d in range(len(gated)):
            cands = np.flatnonzero(gated[d])
            options.append(cands[np.argsort(-gain[d, cands], kind="stable")].tolist())
        active = [d for d, o in enumerate(options) if o]
        if len(active) > exhaustive:
            return self._greedy(gated, gain), False
        best: tuple[float, list[tuple[int, int]]] = (0.0, [])
        left = budget

        def joint(pairs: list[tuple[int, int]]) -> float | None:
            nonlocal left
            left -= 1
            return self.joint(pairs)

        def visit(at: int, pairs: list[tuple[int, int]], used: set[int], score: float) -> None:
            """``score``: that of ``pairs``, evaluated when their last pairing was added."""
            nonlocal best
            if left <= 0:
                return
            if at == len(active):
                if score > best[0]:
                    best = (score, list(pairs))
                return
            d = active[at]
            for c in options[d]:
                if c in used or left <= 0:
                    continue
                pairs.append((d, c))
                more = joint(pairs)
                if more is not None:  # prune what is not jointly compatible
                    visit(at + 1, pairs, used | {c}, more)
                pairs.pop()
            visit(at + 1, pairs, used, score)  # the detection is new (or clutter)

        visit(0, [], set(), 0.0)
        if left > 0:
            return dict(best[1]), False
        greedy = self._greedy(gated, gain)
        score = self.joint(list(greedy.items()))
        if score is not None and score > best[0]:
            return greedy, True
        return dict(best[1]), True

    def _greedy(self, gated: NDArray[np.bool_], gain: Array) -> dict[int, int]:
        pairs: list[tuple[int, int]] = []
        order = sorted(zip(*np.nonzero(gated), strict=True), key=lambda p: -gain[p])
        used_d: set[int] = set()
        used_c: set[int] = set()
        for d, c in order:
            if gain[d, c] <= 0.0 or d in used_d or c in used_c:
                continue
            if self.joint([*pairs, (int(d), int(c))]) is not None:
                pairs.append((int(d), int(c)))
                used_d.add(int(d))
                used_c.add(int(c))
        return dict(pairs)


_CHI2: dict[tuple[int, float], float] = {}


def _chi2(dof: int, alpha: float) -> float:
    """χ²_dof(1 − α), remembered."""
    key = (dof, alpha)
    if key not in _CHI2:
        _CHI2[key] = chi2_ppf(1.0 - alpha, dof)
    return _CHI2[key]


# -- geometry -----------------------------------------------------------------------------------


def _canonical(detections: Sequence[Detection]) -> list[int]:
    """The detections' indices in an order of their values alone (not of their arrival)."""
    keys = [(tuple(d.z_geo.tolist()), tuple(d.z_sem.tolist())) for d in detections]
    return sorted(range(len(detections)), key=keys.__getitem__)


def _body_xy(x: Array, objects: Array) -> Array:
    """Objects' (n, dim) positions (n, 2) in the frame of robot pose ``x`` (3,)."""
    return np.asarray(se2.transform_to(x, objects[..., :2]))


def _retract(kind: ObjectKind, v: Array, delta: Array) -> Array:
    """An object or a detection moved by a tangent ``delta``: Pose2's retraction, or addition."""
    return se2.retract(v, delta) if kind.dim == 3 else np.asarray(v + delta)


def _object_local(kind: ObjectKind, a: Array, b: Array) -> Array:
    """The tangent at ``a`` that reaches ``b`` (objects or detections of ``kind``)."""
    return se2.local(a, b) if kind.dim == 3 else np.asarray(b - a)


def _residual(kind: ObjectKind, z_pred: Array, z: Array) -> Array:
    """ν: the detection ``z`` against the prediction ``z_pred`` in the detection noise's
    coordinates (Pose2's tangent at the prediction; bearing wrapped and range)."""
    if kind.dim == 3:
        return np.asarray(se2.local(z_pred, z))
    diff = np.asarray(z - z_pred)
    return np.stack([se2.wrap_angle(diff[..., 0]), diff[..., 1]], -1)


def _jacobians(kind: ObjectKind, x: Array, objects: Array) -> Array:
    """dν/d(δx, δo) (n, dim, 3 + dim) of each object's predicted detection from ``x``, by
    central differences in the tangent spaces (robot: Pose2's; object: its kind's)."""
    dim = kind.dim
    n = len(objects)
    z0 = kind.measure(x, objects)
    out = np.empty((n, dim, 3 + dim))
    for a in range(3 + dim):
        e = np.zeros(3 + dim)
        e[a] = _STEP
        cols = []
        for sign in (1.0, -1.0):
            xs = se2.retract(x, sign * e[:3])
            os = _retract(kind, objects, np.broadcast_to(sign * e[3:], objects.shape))
            cols.append(_residual(kind, z0, kind.measure(xs, os)))
        out[:, :, a] = (cols[0] - cols[1]) / (2 * _STEP)
    return out


def _propagate(p_prev: Array, x_prev: Array, x_k: Array, q: Array) -> Array:
    """The joint covariance of (x_k, objects) from that of (x_{k−1}, objects) ``p_prev``:
    x_k = x_{k−1} ∘ u, its tangent δ_k = Ad(u⁻¹) δ_{k−1} + the odometry noise (cov ``q``)."""
    u = se2.between(x_prev, x_k)
    f = np.empty((3, 3))
    for a in range(3):
        e = np.zeros(3)
        e[a] = _STEP
        hi = se2.local(x_k, se2.compose(se2.retract(x_prev, e), u))
        lo = se2.local(x_k, se2.compose(se2.retract(x_prev, -e), u))
        f[:, a] = (hi - lo) / (2 * _STEP)
    t = np.eye(len(p_prev))
    t[:3, :3] = f
    p = t @ p_prev @ t.T
    p[:3, :3] += q
    return np.asarray(p)
