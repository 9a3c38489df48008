"""The hybrid belief of Eq. 4–6: weighted class realisations, each with its own iSAM2 belief.

A :class:`HybridBelief` holds one or more robot trajectories (one for a robot's local belief,
several for the centralized reference) and the objects they have seen. Each step propagates every
hypothesis with the odometry, branches it over the classes of newly seen objects, weighs every
child with the weight integral (``estimator.weights``), prunes, and only then materialises the
surviving children by copying iSAM2 and adding the geometric and semantic factors.

Over 300 lines for a reason: the step (propagate, weigh, branch object by object, prune,
materialise) is one algorithm over one set of hypotheses; the weight integrals
(:mod:`estimator.weights`), the pruning rules (:mod:`estimator.pruning`) and the factors
(:mod:`estimator.factors`) already live apart.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.factors import (
    detection_factor,
    diagonal_noise,
    is_object_key,
    object_key,
    object_prior,
    object_value,
    pose_key,
    semantic_factor,
)
from estimator.ledger import SemanticLedger
from estimator.logsumexp import logsumexp
from estimator.models import ClassifierModel, Detection, GaussianNoise, SensorFrame, viewpoint
from estimator.models.objects import POSE, ObjectKind
from estimator.pruning import PRUNINGS, PruningRule, class_marginals, match_marginals, select
from estimator.smoother import WindowedISAM2, marginal_covariances, pose_steps
from estimator.snapshot import BeliefSnapshot  # re-exported: it used to live here
from estimator.sparse_xi import MAX_XI_PARENTS, XI_PARENTS, SparseXi, Structure
from estimator.summary import Xi
from estimator.weights import (
    WEIGHT_ESTIMATORS,
    InvolvedGaussian,
    SemanticTerms,
    geo_conditioned_batch,
    paper_mc_samples,
)

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]

log = logging.getLogger(__name__)

# How a belief represents its classes (``BeliefConfig.classes``).
CLASS_KINDS = ("joint", "per_object")
# What a per-object slot's ξ is (``BeliefConfig.xi``): chosen per slot by its size, always
# dense, always sparse.
XI_KINDS = ("auto", "dense", "sparse")
# ``xi = "auto"``: a slot of more than this many objects sends the sparse ξ, a smaller one the
# dense ξ. Measured (python -m bench mapscale, sizes 15–60, D's step p50 / p99 in ms; the
# study's wall): at 12 objects in r1's slot dense 4.4 / 8.4, sparse 5.1 / 10.9 (wall 5.5 against
# 6.8 s); at 21, 6.7 / 14.3 against 7.3 / 13.9 (7.7 against 9.4 s); at 45, 9.2 / 55.5 against
# 8.2 / 27.1 (26.0 against 23.6 s). Below the crossing the dense ξ is cheaper to make, send and
# fuse, and exact (the sparse one is conservative: D's position σ 1.26× C's at 300 objects);
# above it the sparse one is cheaper on every count and linear in n on the wire.
SPARSE_XI_ABOVE = 32
# Where a per-object slot's ξ is linearised (``BeliefConfig.slot_linearisation``): at the
# owner's fused estimate (D's), or at L's own linearisation point (the reference).
SLOT_LINEARISATIONS = ("fused", "local")
# Where a per-object slot's class evidence is read (``BeliefConfig.slot_evidence``).
SLOT_EVIDENCES = ("fused", "local")
# The default window of robot poses (per-object classes): poses older than 100–200 steps are
# marginalised. Measured against every pose on five seeds of a 2,000-step mission, a mission
# whose map is known early, and the 120- and 300-object worlds: errors within the seeds' spread,
# the step bounded by the map instead of the mission (docs/estimator.md, "A window of poses").
# At 60 steps (the paper's world) it never acts.
POSE_WINDOW = 100
# BeliefConfig.window's default: POSE_WINDOW for per-object classes, None (every pose) for joint
# class tables, which the window is not built for (a continuous belief per realisation, the
# ledger's retirement and D's joins are not measured with it); resolved when the config is made
# (so an explicit -1 means the default too).
_WINDOW_BY_CLASSES = -1
# How the window stores what its old poses knew: "relative" (estimator.relative_marginal),
# or "linear" (a LinearContainerFactor, the first form, kept as the reference).
WINDOW_MARGINALS = ("relative", "linear")


@dataclass(frozen=True, slots=True)
class BeliefConfig:
    """How a hybrid belief computes and prunes (design doc §2–3, docs/estimator.md).

    ``pruning``: ``"marginal"`` (default) or the paper's ``"ratio"`` (see ``estimator.pruning``);
    ``prune_ratio``: keep hypotheses whose weight is within this ratio of the heaviest;
    ``marginal_ratio``: (``"marginal"`` only) also keep a hypothesis that carries at least
    1/``marginal_ratio`` of the marginal probability of one of its own classes;
    ``class_floor``: (``"marginal"`` only) a class of an object with at least this marginal
    probability keeps its heaviest hypothesis, and the kept hypotheses are reweighted to the
    class marginals before pruning; ``max_hypotheses``: hard cap; ``robot_budget``: the
    hypotheses per robot whose data the belief holds (a robot's local belief keeps at most this
    many; the centralized belief of R robots, and a distributed belief that has integrated the
    slots of R − 1 other robots, at most R times as many; never more than ``max_hypotheses``;
    ``None``: no budget); ``max_join``: the most
    (hypothesis, realisation) pairs a fusion builds for one slot (the lightest hypotheses are
    left out first; bounds the work of a received slot before anything is built);
    ``max_fusion_bytes``: a slot whose information matrices, one per kept hypothesis, would
    take more is refused (``max_hypotheses`` × (3n)² float64 for a slot of n objects);
    ``weight_estimator``:
    ``geo_conditioned`` (default) or ``paper_mc``; ``num_samples`` for the Monte Carlo part;
    ``object_prior_sigmas``: the weak prior on a newly seen object, centred on its first
    measurement; ``start_prior_sigmas``: the prior on a robot's known start; iSAM2's
    ``relinearize_threshold`` (None, the default: a third of the motion model's smallest σ,
    so that no linearisation point lags its variable by more than a fraction of one step's
    noise; 0.011 on the paper's model. A fixed 10⁻³ relinearised hundreds of old poses at every
    check late in a 2,000-step mission, for no change in error), ``relinearize_skip`` (check
    every this many updates),
    ``partial_relinearization`` (iSAM2's partial relinearisation check: descend the Bayes tree
    from the root only through cliques with a variable over the threshold; False: check every
    variable) and the number of ``extra_updates`` after each measurement update.
    ``ledger_every`` (per-object classes): the semantic ledger re-reads every detection's poses
    every this many steps (1, the default: every step, the reference); in between a step reads
    only the keys it needs and a new detection takes its reference from them. At each refresh
    the class evidence equals that of a refresh at every step; in between, old detections'
    evidence waits (up to 0.045 in a class probability against exact enumeration on 6-object
    worlds at 10; none measurable in the paper study's log-loss).

    ``window`` (per-object classes; ``POSE_WINDOW``, 100, by default, and None, every pose, for
    joint classes):
    robot poses older than ``window`` to ``2 · window`` steps are marginalised into one factor on
    what they saw (``estimator.smoother``), so that a step and the memory follow the map, not
    the mission; ``window_marginal`` says how that factor is kept (``"relative"``, the default,
    root-shifted and relinearised with the map, or ``"linear"``, the first form).

    ``classes``: ``"per_object"`` (default) keeps per object its class log-evidence (M numbers;
    ``"joint"``, ``BeliefConfig.joint()``, keeps weighted joint class realisations, Eq. 4,
    pruned as above, as do ``paper()`` and ``exact()``): with one continuous
    belief the classes of different objects couple only through the Monte Carlo draws the
    detections of one step share, so the posterior is taken as a product over objects
    (docs/estimator.md, "Per-object classes"); no realisation, no branching, no pruning.

    ``xi``: the ξ of a per-object slot: ``"dense"`` (the reference) the owner's exact
    prior-divided Λ over its n objects, (3n)² numbers; ``"sparse"`` the conservative sparse form
    of it (``estimator.sparse_xi``: Λ_s ⪯ Λ on a Bayes net's moral graph, mean kept, float32),
    linear in n on the wire and a few small factors in D's iSAM2 instead of one n-object clique
    (docs/estimator.md, "Sparse ξ"); ``"auto"`` (default) the dense ξ up to
    ``SPARSE_XI_ABOVE`` objects and the sparse one above, where it is the cheaper (measured
    there). Joint class tables always send dense ξ (``"auto"`` or ``"dense"``).
    ``xi_parents``: a sparse ξ's Bayes net gives each object its tree parent and up to this many
    more (0 to ``MAX_XI_PARENTS``): each one more buys back information (D's position σ) for
    about 45 wire bytes per object (docs/estimator.md, "Sparse ξ": the curve, measured).

    ``slot_linearisation`` (``"per_object"`` only): where the owner linearises its own factors
    for its slot's ξ. ``"fused"`` (default): at its distributed belief's estimate, the best it
    has and the one its receivers are near, so that they read ξ close to where it was taken;
    ``"local"`` (the reference): at L's own linearisation point, which drifts with L (metres
    on a large map) and leaves every receiver's ξ a linearisation of the owner's drift
    (docs/distributed.md, "Where a slot is linearised"). Only the linearisation point comes
    from D: Λ and η are the owner's own factors', so nothing is counted twice.

    ``slot_evidence`` (``"per_object"`` only): where the viewpoints of the owner's detections
    are read for its slot's class log φ. ``"fused"`` (default): at the same point as ξ (when ξ
    is taken there): each detection's log P(z | c, ψ̂) moved from L's ψ̂ to the fused one, as
    the ledger moves it when L's own estimate moves; ``"local"`` (the reference): at L's
    estimate. Only the viewpoints come from D: the detections are the owner's own. It matters
    where a viewpoint depends on the map's heading (point objects, read in the world frame):
    there L's log φ carried its heading drift (docs/estimator.md, "Point objects").

    ``semantic_poses``: whether the semantic factors also enter the Gaussians, so that every
    class realisation has a continuous belief of its own (Eq. 5 taken literally, the paper's
    model; ``BeliefConfig.paper()``). By default they do not: the semantic measurements weigh the
    class realisations (their viewpoint-dependent likelihood is integrated over the poses, Eq. 6)
    but leave the poses to the geometric factors, so one continuous belief serves every
    hypothesis (docs/estimator.md, "One continuous belief").
    """

    weight_estimator: str = "geo_conditioned"
    num_samples: int = 500
    pruning: str = "marginal"
    prune_ratio: float = 1e4
    class_floor: float = 1e-4
    marginal_ratio: float = 1e4
    max_hypotheses: int = 300
    robot_budget: int | None = None
    max_join: int = 250_000
    max_fusion_bytes: int = 2**30
    object_prior_sigmas: tuple[float, float, float] = (100.0, 100.0, math.pi)
    start_prior_sigmas: tuple[float, float, float] = (1e-3, 1e-3, 1e-3)
    relinearize_threshold: float | None = None
    relinearize_skip: int = 10
    ledger_every: int = 1
    window: int | None = _WINDOW_BY_CLASSES
    window_marginal: str = "relative"
    partial_relinearization: bool = True
    extra_updates: int = 1
    semantic_poses: bool = False
    classes: str = "per_object"
    xi: str = "auto"
    xi_parents: int = XI_PARENTS
    slot_linearisation: str = "fused"
    slot_evidence: str = "fused"

    def __post_init__(self) -> None:
        if self.classes not in CLASS_KINDS:
            raise ValueError(f"classes {self.classes!r} (known: {', '.join(CLASS_KINDS)})")
        if self.xi not in XI_KINDS:
            raise ValueError(f"xi {self.xi!r} (known: {', '.join(XI_KINDS)})")
        if self.xi == "sparse" and self.classes != "per_object":
            raise ValueError('xi = "sparse" needs classes = "per_object"')
        if not 0 <= self.xi_parents <= MAX_XI_PARENTS:
            raise ValueError(f"xi_parents must be 0..{MAX_XI_PARENTS}, got {self.xi_parents}")
        if self.slot_linearisation not in SLOT_LINEARISATIONS:
            known = ", ".join(SLOT_LINEARISATIONS)
            raise ValueError(f"slot_linearisation {self.slot_linearisation!r} (known: {known})")
        if self.slot_evidence not in SLOT_EVIDENCES:
            known = ", ".join(SLOT_EVIDENCES)
            raise ValueError(f"slot_evidence {self.slot_evidence!r} (known: {known})")
        if self.classes == "per_object" and self.semantic_poses:
            raise ValueError(
                'classes = "per_object" needs one continuous belief (semantic_poses = False)'
            )
        if self.weight_estimator not in WEIGHT_ESTIMATORS:
            known = ", ".join(WEIGHT_ESTIMATORS)
            raise ValueError(f"weight_estimator {self.weight_estimator!r} (known: {known})")
        if self.pruning not in PRUNINGS:
            raise ValueError(f"pruning {self.pruning!r} (known: {', '.join(PRUNINGS)})")
        if self.max_join < 1 or self.max_fusion_bytes < 1:
            raise ValueError("max_join and max_fusion_bytes must be ≥ 1")
        threshold = self.relinearize_threshold
        if threshold is not None and not (math.isfinite(threshold) and threshold > 0):
            raise ValueError(f"relinearize_threshold must be > 0 or None, got {threshold}")
        if self.ledger_every < 1:
            raise ValueError(f"ledger_every must be ≥ 1, got {self.ledger_every}")
        if self.window == _WINDOW_BY_CLASSES:
            by_classes = POSE_WINDOW if self.classes == "per_object" else None
            object.__setattr__(self, "window", by_classes)
        if self.window is not None and self.window < 1:
            raise ValueError(f"window must be ≥ 1 step or None, got {self.window}")
        if self.window_marginal not in WINDOW_MARGINALS:
            known = ", ".join(WINDOW_MARGINALS)
            raise ValueError(f"window_marginal {self.window_marginal!r} (known: {known})")
        if self.window is not None and self.classes != "per_object":
            raise ValueError(
                'window needs classes = "per_object" (one continuous belief); '
                "joint classes keep every pose (window=None)"
            )
        if self.num_samples < 1 or self.max_hypotheses < 1 or self.extra_updates < 0:
            raise ValueError("num_samples and max_hypotheses must be ≥ 1, extra_updates ≥ 0")
        if self.robot_budget is not None and self.robot_budget < 1:
            raise ValueError(f"robot_budget must be ≥ 1 or None, got {self.robot_budget}")
        if not self.prune_ratio > 1.0:
            raise ValueError(f"prune_ratio must be > 1, got {self.prune_ratio}")
        if not 0.0 <= self.class_floor < 1.0:
            raise ValueError(f"class_floor must be in [0, 1), got {self.class_floor}")
        sigmas = (*self.object_prior_sigmas, *self.start_prior_sigmas)
        if not all(math.isfinite(s) and s > 0 for s in sigmas):
            raise ValueError("prior sigmas must be finite and positive")

    @classmethod
    def paper(cls, **changes: object) -> BeliefConfig:
        """The paper's model and hypothesis management: a continuous belief per class realisation
        (semantic factors in the Gaussians), joint weight ratio 1/150, cap 300, no budget."""
        fields = {
            "pruning": "ratio",
            "prune_ratio": 150.0,
            "robot_budget": None,
            "semantic_poses": True,
            "classes": "joint",
            **changes,
        }
        return cls(**fields)  # type: ignore[arg-type]

    @classmethod
    def exact(cls, **changes: object) -> BeliefConfig:
        """No pruning (enumeration of the joint realisations, up to 4096 hypotheses): the
        reference of small worlds."""
        fields = {
            "prune_ratio": math.inf,
            "max_hypotheses": 4096,
            "robot_budget": None,
            "classes": "joint",
            **changes,
        }
        return cls(**fields)  # type: ignore[arg-type]

    @classmethod
    def joint(cls, **changes: object) -> BeliefConfig:
        """Joint class realisations with the default management (``"marginal"`` pruning, cap
        300): the representation before per-object classes, kept as their baseline."""
        return cls(**{"classes": "joint", **changes})  # type: ignore[arg-type]

    def cap(self, robots: int = 1) -> int:
        """The most hypotheses a belief over ``robots`` trajectories keeps."""
        if self.robot_budget is None:
            return self.max_hypotheses
        return min(self.max_hypotheses, self.robot_budget * max(1, robots))

    def rule(self, robots: int = 1) -> PruningRule:
        c = self
        return PruningRule(c.pruning, c.prune_ratio, c.class_floor, c.cap(robots), c.marginal_ratio)


@dataclass(frozen=True, slots=True)
class BeliefModel:
    """What the belief assumes about the world: classes, their prior, the classifier, the noise,
    and what an object is (``objects``: pose objects, the paper's, or point landmarks measured by
    bearing and range, ``estimator.models.objects``); ``geometric_noise`` is a detection's, so it
    has as many variances as an object has dimensions."""

    num_classes: int
    class_prior: tuple[float, ...]
    classifier: ClassifierModel
    odometry_noise: GaussianNoise
    geometric_noise: GaussianNoise
    objects: ObjectKind = POSE

    def __post_init__(self) -> None:
        if (
            len(self.class_prior) != self.num_classes
            or self.classifier.num_classes != self.num_classes
        ):
            raise ValueError("class prior, classifier and num_classes disagree")
        if len(self.geometric_noise.variances) != self.objects.dim:
            raise ValueError(
                f"{self.objects.name} objects need {self.objects.dim} detection variances, got"
                f" {len(self.geometric_noise.variances)}"
            )
        if len(self.odometry_noise.variances) != 3:
            raise ValueError("odometry noise needs three variances (x, y, θ)")


@dataclass(frozen=True, slots=True)
class UsedXi:
    """What a continuous belief of D took from another robot's slot: the version's stamp, the
    owner's object ids, the ξ it multiplied in, and the iSAM2 indices of the factors that carry
    that robot's information (removed on the next version when downdating by removal)."""

    stamp: int
    object_ids: tuple[int, ...]
    xi: Xi | SparseXi
    factor_indices: tuple[int, ...]


@dataclass(slots=True, eq=False)
class Continuous:
    """A continuous belief over the robot trajectories and object poses: its iSAM2, the current
    estimate, the mean (3,) of every object's weak prior (needed to divide it out of a slot
    exactly), and in D the ξ of other robots' slots it holds, by owner.

    One continuous belief serves every hypothesis whose factors are the same: all of them when
    the semantic factors stay out of the Gaussians (``BeliefConfig.semantic_poses = False``, the
    default), one per class realisation otherwise. ``ledger``: the semantic evidence its
    hypotheses' weights hold, re-linearised as the estimate moves (``estimator.ledger``; None
    when the semantic factors are in the Gaussians).
    """

    isam: gtsam.ISAM2 | WindowedISAM2
    cached: gtsam.Values | None = field(default=None, repr=False)
    object_priors: dict[int, Array] = field(default_factory=dict, repr=False)
    used: dict[str, UsedXi] = field(default_factory=dict, repr=False)
    ledger: SemanticLedger | None = field(default=None, repr=False)
    # 2: objects are Point2 (``estimator.models.objects``); robot poses are always Pose2
    object_dim: int = 3

    def copy(self) -> Continuous:
        """An independent copy (``gtsam.ISAM2``'s copy constructor)."""
        ledger = None if self.ledger is None else self.ledger.copy()
        isam = self.isam.copy() if isinstance(self.isam, WindowedISAM2) else gtsam.ISAM2(self.isam)
        return Continuous(
            isam, self.cached, dict(self.object_priors), dict(self.used), ledger, self.object_dim
        )

    @property
    def estimate(self) -> gtsam.Values:
        """Every variable's estimate, computed when first asked for after an update: it costs
        time in proportion to the whole trajectory, so a step reads the keys it needs one by
        one (:meth:`pose2`) and only the ledger's periodic refresh and scoring ask for all."""
        if self.cached is None:
            self.cached = self.isam.calculateEstimate()
        return self.cached

    def updated(self) -> None:
        """iSAM2 was updated: the estimate is computed again when next asked for."""
        self.cached = None

    def pose2(self, key: int) -> gtsam.Pose2:
        """One variable's estimate (iSAM2 back-substitutes the delta of that key alone)."""
        if self.cached is not None:
            return self.cached.atPose2(key)
        return self.isam.calculateEstimatePose2(key)

    def point(self, key: int) -> Array:
        """A point object's estimate (x, y)."""
        if self.cached is not None:
            return np.asarray(self.cached.atPoint2(key), dtype=float)
        return np.asarray(self.isam.calculateEstimatePoint2(key), dtype=float)

    def is_point(self, key: int) -> bool:
        return self.object_dim == 2 and is_object_key(key)

    def pose(self, key: int) -> Array:
        """A robot pose (x, y, θ), or an object as its kind holds it ((x, y, θ) or (x, y))."""
        if self.is_point(key):
            return self.point(key)
        return _xytheta(self.pose2(key))

    def values(self, keys: Sequence[int]) -> gtsam.Values:
        """The estimates of ``keys`` only (to linearise a factor on them)."""
        out = gtsam.Values()
        for key in keys:
            out.insert(key, self.point(key) if self.is_point(key) else self.pose2(key))
        return out


@dataclass(slots=True, eq=False)
class Hypothesis:
    """One class realisation ``classes`` (aligned with the belief's ``object_ids``), the
    continuous belief it uses (possibly shared with other hypotheses) and its normalised
    log-weight. ``used_phi``: in a distributed belief, log φ of the realisation of each other
    robot's slot it integrated (subtracted when a newer version replaces it)."""

    classes: tuple[int, ...]
    continuous: Continuous
    log_weight: float
    used_phi: dict[str, float] = field(default_factory=dict, repr=False)

    @property
    def isam(self) -> gtsam.ISAM2 | WindowedISAM2:
        return self.continuous.isam

    @property
    def estimate(self) -> gtsam.Values:
        return self.continuous.estimate

    @property
    def object_priors(self) -> dict[int, Array]:
        return self.continuous.object_priors

    def pose(self, key: int) -> Array:
        return self.continuous.pose(key)


def _xytheta(p: gtsam.Pose2) -> Array:
    return np.array([p.x(), p.y(), p.theta()])


# A point object has no heading: in the involved Gaussian of a step (weights) it takes a pose's
# place with its heading pinned at 0 by this information (rad⁻²), so that the sampled headings
# stay within 1e-6 rad of 0 and the translation samples are the point's own (a pose at heading 0
# retracted by (δx, δy, 0) moves by (δx, δy) in the world frame, a Point2's tangent). Decoupled
# from every other coordinate, it cancels between the prior and the posterior determinants.
_PINNED_HEADING = 1e12
# A snapshot's covariance of a point object's heading, which nothing estimates: "unknown" as the
# ROS convention reads a large variance (position blocks are exact).
UNKNOWN_HEADING_VARIANCE = 1e6


def _as_pose_blocks(info: Array, is_point: Sequence[bool]) -> Array:
    """A joint information over robot poses (3 each) and point objects (2 each), in the order
    ``is_point`` gives, laid out with 3 rows per variable: a point's third one pinned
    (``_PINNED_HEADING``)."""
    dims = np.array([2 if p else 3 for p in is_point])
    index = np.concatenate([3 * i + np.arange(d) for i, d in enumerate(dims)])
    out = np.zeros((3 * len(dims), 3 * len(dims)))
    out[np.ix_(index, index)] = info
    pinned = 3 * np.flatnonzero(np.asarray(is_point)) + 2
    out[pinned, pinned] = _PINNED_HEADING
    return out


def as_pose_covariances(cov: Array) -> Array:
    """Object covariances (..., d, d) as a pose's (..., 3, 3): themselves for d = 3; for a
    point (d = 2) its position block with an unknown heading (``UNKNOWN_HEADING_VARIANCE``)."""
    if cov.shape[-1] == 3:
        return cov
    out = np.zeros((*cov.shape[:-2], 3, 3))
    out[..., :2, :2] = cov
    out[..., 2, 2] = UNKNOWN_HEADING_VARIANCE
    return out


def distinct_continuous(hypotheses: Sequence[Hypothesis]) -> tuple[list[Continuous], IntArray]:
    """The distinct continuous beliefs of ``hypotheses`` (by identity, in order of first use)
    and the index (H,) of each hypothesis' one in that list."""
    index: dict[int, int] = {}
    out: list[Continuous] = []
    which = np.empty(len(hypotheses), dtype=np.int64)
    for i, h in enumerate(hypotheses):
        g = index.get(id(h.continuous))
        if g is None:
            g = index[id(h.continuous)] = len(out)
            out.append(h.continuous)
        which[i] = g
    return out, which


@dataclass(frozen=True, slots=True)
class StepStats:
    """What one step did: hypotheses before, children weighed, hypotheses kept."""

    parents: int
    children: int
    kept: int


# Parents whose weight integrals are vectorised together: at most this many (sample, detection,
# class) log-likelihoods at once (8 bytes each), so that memory stays bounded whatever the step.
_EVIDENCE_CHUNK = 2_000_000


@dataclass(frozen=True, slots=True)
class _Evidence:
    """What branching needs of the parents' weight integrals (see ``HybridBelief._reduce``):
    ``acc`` per parent, ``marg`` and ``lt`` per continuous belief, ``which`` (P,) the continuous
    belief of every parent."""

    acc: Array
    marg: Array
    lt: Array
    which: IntArray


@dataclass(frozen=True, slots=True)
class _Beam:
    """Children of one step while the new objects' classes are assigned: parent index (K,),
    classes of the new objects assigned so far (K, t), their log prior (K,), the per-sample log
    evidence with the unassigned objects summed out (K, S), the log-weight (K,), and how many
    candidates were weighed so far."""

    parent: IntArray
    classes: IntArray
    log_prior: Array
    acc: Array
    log_weight: Array
    weighed: int

    def keep(self, kept: IntArray, log_weight: Array | None = None) -> _Beam:
        return _Beam(
            self.parent[kept],
            self.classes[kept],
            self.log_prior[kept],
            self.acc[kept],
            self.log_weight[kept] if log_weight is None else log_weight,
            self.weighed,
        )


class HybridBelief:
    """A hybrid belief over robot trajectories, object poses and object classes (Eq. 4).

    Over 500 lines for a reason: its 35 methods work on one state that a step (Eqs. 4-12)
    changes as a whole — 12 of them read or write the hypotheses, 8 the object index, 7 the pose
    keys, 5 the class prior (counted from this file's syntax tree); split, each part would need
    the others' invariants (which objects exist, at which key, under which hypothesis)."""

    def __init__(
        self,
        model: BeliefModel,
        starts: Mapping[str, ArrayLike],
        config: BeliefConfig | None = None,
    ) -> None:
        self.model = model
        self.config = config or BeliefConfig()
        self.robots = list(starts)
        self._slot = {r: i for i, r in enumerate(self.robots)}
        self.step_of = dict.fromkeys(self.robots, 0)
        self.object_ids: list[int] = []
        self._object_index: dict[int, int] = {}
        self._odometry_noise = diagonal_noise(model.odometry_noise)
        self._geometric_noise = diagonal_noise(model.geometric_noise)
        self._kind = model.objects
        if self._kind is not POSE and self.config.weight_estimator == "paper_mc":
            raise ValueError('weight_estimator "paper_mc" is for pose objects (the paper\'s)')
        # a point object's prior: the position part of the pose objects' (x, y)
        self._object_prior = gtsam.noiseModel.Diagonal.Sigmas(
            np.array(self.config.object_prior_sigmas[: self._kind.dim])
        )
        self._log_prior = np.log(np.asarray(model.class_prior, dtype=float))
        # class_matrix(): the classes tuples it was built from (kept alive, compared by identity)
        self._class_rows: tuple[list[tuple[int, ...]], IntArray] | None = None
        geo_cov = model.geometric_noise.cov
        self._geo_cov = geo_cov
        self._geo_log_norm = -0.5 * float(np.linalg.slogdet(2.0 * np.pi * geo_cov)[1])
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        start_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(self.config.start_prior_sigmas))
        for r, start in starts.items():
            pose = gtsam.Pose2(*np.asarray(start, dtype=float))
            graph.add(gtsam.PriorFactorPose2(self.pose_key(r), pose, start_noise))
            values.insert(self.pose_key(r), pose)
        isam: gtsam.ISAM2 | WindowedISAM2
        if self.config.window is None:
            isam = gtsam.ISAM2(self._isam_params())
        else:
            isam = WindowedISAM2(
                self._isam_params(),
                self.config.window,
                relative=self.config.window_marginal == "relative",
            )
        isam.update(graph, values)
        ledger = None if self.config.semantic_poses else SemanticLedger()
        first = Continuous(isam, ledger=ledger, object_dim=self._kind.dim)
        self.hypotheses = [Hypothesis((), first, 0.0)]
        # Per-object classes: every known object's class log-evidence L (n, M), the prior left
        # out (P(c_j) ∝ P(c) · exp(L_j)); empty and unused for joint realisations.
        self.log_evidence = np.zeros((0, model.num_classes))
        # Sparse ξ (BeliefConfig.xi): the object ids and Bayes net of the last one summarised
        # from this belief, reused by estimator.slots while the ids are the same.
        self.xi_structure: tuple[tuple[int, ...], Structure] | None = None
        # Slots summarised at other poses (estimator.slots, ``at``): the last excess χ² of the
        # belief's factors there, per dimension, and how many were refused as implausible.
        self.slot_fit = 0.0
        self.slot_fit_refused = 0
        # Per-object classes: steps since the ledger last re-read every detection's poses.
        self._since_refresh = 0
        # Replayed detections (``step``) left out: their pose was marginalised.
        self.replays_dropped = 0

    @property
    def per_object(self) -> bool:
        """Whether classes are per-object beliefs (``BeliefConfig.classes``)."""
        return self.config.classes == "per_object"

    # -- keys and queries -------------------------------------------------------------------

    def information_sources(self) -> int:
        """How many robots' data this belief holds (the unit of ``BeliefConfig.robot_budget``):
        here, its trajectories."""
        return len(self.robots)

    @property
    def cap(self) -> int:
        """The most hypotheses this belief keeps (``BeliefConfig.cap``)."""
        return self.config.cap(self.information_sources())

    def pose_key(self, robot: str, k: int | None = None) -> int:
        """Key of ``robot``'s pose at step ``k`` (default: its latest step)."""
        return pose_key(self._slot[robot], self.step_of[robot] if k is None else k)

    def weights(self) -> Array:
        """Normalised weights (H,)."""
        lw = np.array([h.log_weight for h in self.hypotheses])
        w = np.exp(lw - lw.max())
        return np.asarray(w / w.sum())

    def class_matrix(self) -> IntArray:
        """The classes (H, n) of every hypothesis, read-only, in ``object_ids`` order. Built once
        per set of realisations: a step and a fusion leave theirs here as they make them, and
        the step, its evidence, the summary and the snapshots of the same hypotheses reuse it
        (each was a (300, n) conversion from tuples)."""
        hyps = self.hypotheses
        cached = self._class_rows
        if (
            cached is not None
            and len(cached[0]) == len(hyps)
            and all(c is h.classes for c, h in zip(cached[0], hyps, strict=True))
        ):
            return cached[1]
        matrix = np.array([h.classes for h in hyps], dtype=np.int64)
        return self._remember_classes(matrix.reshape(len(hyps), len(self.object_ids)))

    def _classes_of(self, hyps: Sequence[Hypothesis]) -> IntArray:
        """The classes (H, n) of ``hyps``: :meth:`class_matrix` when they are the belief's."""
        if hyps is self.hypotheses:
            return self.class_matrix()
        return np.array([h.classes for h in hyps], dtype=np.int64).reshape(
            len(hyps), len(self.object_ids)
        )

    def _remember_classes(self, matrix: IntArray) -> IntArray:
        """Keep ``matrix`` as :meth:`class_matrix` of the current hypotheses (rows in order)."""
        matrix = np.array(matrix, dtype=np.int64)  # an own copy, then frozen
        matrix.flags.writeable = False
        self._class_rows = ([h.classes for h in self.hypotheses], matrix)
        return matrix

    def class_marginals(self) -> Array:
        """P(c_j = i) (n, M) for the known objects in ``object_ids`` order."""
        if self.per_object:
            log_post = self.class_log_posterior()
            return np.asarray(np.exp(log_post - np.asarray(logsumexp(log_post, axis=1))[:, None]))
        return class_marginals(self.weights(), self.class_matrix(), self.model.num_classes)

    def class_log_posterior(self) -> Array:
        """Per-object classes: log P(c_j = i) + const (n, M), prior and every piece of evidence
        this belief holds."""
        return self._log_prior[None, :] + self.log_evidence

    def map_hypothesis(self) -> Hypothesis:
        return max(self.hypotheses, key=lambda h: h.log_weight)

    def position(self, robot: str) -> tuple[float, float]:
        """``robot``'s estimated (x, y) at its latest step, in the most probable hypothesis: what
        a robot may tell others about where it is (it never knows its true pose)."""
        pose = self.map_hypothesis().pose(self.pose_key(robot))
        return float(pose[0]), float(pose[1])

    def snapshot(self, robot: str) -> BeliefSnapshot:
        """The belief as arrays (see :class:`BeliefSnapshot`) with ``robot``'s latest pose."""
        return self.snapshots([robot])[robot]

    def snapshots(self, robots: Sequence[str]) -> dict[str, BeliefSnapshot]:
        """:meth:`snapshot` for several robots of this belief; the object marginals, shared by
        every robot, are computed once."""
        keys = [object_key(j) for j in self.object_ids]
        hyps = self.hypotheses
        conts, which = distinct_continuous(hyps)
        n = len(keys)

        def per_hypothesis(per_cont: Array) -> Array:
            # One continuous belief (the default): a read-only view of it for every hypothesis.
            if len(conts) == 1:
                return np.broadcast_to(per_cont, (len(hyps), *per_cont.shape[1:]))
            return per_cont[which]

        kind, dim = self._kind, self._kind.dim
        object_pose = per_hypothesis(
            kind.as_pose(
                np.array([[c.pose(key) for key in keys] for c in conts]).reshape(len(conts), n, dim)
            )
        )
        object_cov = per_hypothesis(
            as_pose_covariances(
                np.array([marginal_covariances(c.isam, keys) for c in conts]).reshape(
                    len(conts), n, dim, dim
                )
            )
        )
        classes = self.class_matrix()
        weights = self.weights()
        probs = self.class_marginals() if self.per_object else None
        out = {}
        for robot in robots:
            xk = self.pose_key(robot)
            out[robot] = BeliefSnapshot(
                tuple(self.object_ids),
                weights,
                classes,
                per_hypothesis(np.array([c.pose(xk) for c in conts])),
                per_hypothesis(np.array([c.isam.marginalCovariance(xk) for c in conts])),
                object_pose,
                object_cov,
                probs,
            )
        return out

    # -- the step ---------------------------------------------------------------------------

    def step(
        self,
        frames: Sequence[SensorFrame],
        rng: np.random.Generator,
        replay: Sequence[tuple[str, int, Detection]] = (),
    ) -> StepStats:
        """Eq. 5–6 for one step: every frame advances its robot by one step.

        ``replay``: earlier detections (robot, step, detection) of
        objects this step's frames hold, added from the poses of the steps they were made at,
        with their class evidence, as if the objects had been known then: a robot that confirms
        an object only at its n-th detection (``estimator.association``) keeps the first n − 1.
        A replayed detection whose pose the window has marginalised is left out
        (``replays_dropped``)."""
        self._check_frames(frames)
        detections = [(f, d) for f in frames for d in f.detections]
        new_ids: list[int] = []
        first: dict[int, tuple[SensorFrame, Detection]] = {}
        for f, d in detections:
            if d.object_id not in self._object_index and d.object_id not in first:
                new_ids.append(d.object_id)
                first[d.object_id] = (f, d)
        if replay:
            detections += self._replayed(frames, replay, first)
        if self.per_object:
            return self._step_per_object(frames, detections, new_ids, first, rng)
        parents = self.hypotheses
        conts, which = distinct_continuous(parents)
        for c in conts:
            self._propagate(c, frames, first)
        for f in frames:
            self.step_of[f.robot] = f.k
        if not detections:
            self._relinearise_evidence()
            return StepStats(len(parents), len(parents), len(parents))
        evidence = self._evidence(parents, conts, which, detections, new_ids, rng)
        beam = self._branch(parents, evidence, new_ids)
        for j in new_ids:
            self._object_index[j] = len(self.object_ids)
            self.object_ids.append(j)
        parent_cls = self._classes_of(parents)
        self.hypotheses = self._materialise(parents, beam, detections)
        self._remember_classes(np.concatenate([parent_cls[beam.parent], beam.classes], axis=1))
        self._relinearise_evidence()
        self._normalise()
        return StepStats(len(parents), beam.weighed, len(self.hypotheses))

    def _replayed(
        self,
        frames: Sequence[SensorFrame],
        replay: Sequence[tuple[str, int, Detection]],
        first: Mapping[int, tuple[SensorFrame, Detection]],
    ) -> list[tuple[SensorFrame, Detection]]:
        """``step``'s ``replay`` checked and paired with frames of their steps (which carry only
        what the factors read: the robot and the step)."""
        now = {f.robot: f for f in frames}
        isam = self.hypotheses[0].continuous.isam
        oldest = 0  # the oldest pose still held after this step's update
        if isinstance(isam, WindowedISAM2):
            latest = max(isam.latest, *(f.k for f in frames))
            oldest = max(isam.oldest_kept(), latest - isam.window)
        out = []
        for robot, k, d in replay:
            f = now.get(robot)
            if f is None or not 1 <= k < f.k:
                raise ValueError(
                    f"replayed detection of object {d.object_id} at step {k} of {robot!r}: not "
                    "an earlier step of a robot this step advances"
                )
            if d.object_id not in self._object_index and d.object_id not in first:
                raise ValueError(
                    f"replayed detection of object {d.object_id}: no frame of this step and no "
                    "earlier one holds that object"
                )
            if np.shape(d.z_geo) != (self._kind.dim,):
                raise ValueError(
                    f"replayed detection of object {d.object_id}: z_geo has "
                    f"{np.size(d.z_geo)} numbers, this belief's {self._kind.name} objects "
                    f"{self._kind.dim}"
                )
            if k < oldest:
                self.replays_dropped += 1
                continue
            out.append((SensorFrame(robot, k, f.odometry, (), f.true_pose, f.ids), d))
        return out

    def _step_per_object(
        self,
        frames: Sequence[SensorFrame],
        detections: Sequence[tuple[SensorFrame, Detection]],
        new_ids: Sequence[int],
        first: Mapping[int, tuple[SensorFrame, Detection]],
        rng: np.random.Generator,
    ) -> StepStats:
        """The step with per-object classes: the one continuous belief is propagated, every
        detected object's class log-evidence moves by its share of the weight integral (Eq. 6
        with the objects' classes summed out one by one: log (1/S) Σ_s Π_{d of j} P(z_d | c,
        ψ_ds), the same draws as the joint path), then the geometric factors enter."""
        cont = self.hypotheses[0].continuous
        self._propagate(cont, frames, first)
        for f in frames:
            self.step_of[f.robot] = f.k
        for j in new_ids:
            self._object_index[j] = len(self.object_ids)
            self.object_ids.append(j)
        m = self.model.num_classes
        grown = np.zeros((len(self.object_ids), m))
        grown[: len(self.log_evidence)] = self.log_evidence
        self.log_evidence = grown
        if detections:
            rows, evidence = self._object_evidence(cont, detections, rng)
            self.log_evidence[rows] += evidence
            self._measure(cont, (), detections)
        self._relinearise_evidence()
        self._set_map_classes()
        return StepStats(1, 1, 1)

    def _object_evidence(
        self,
        cont: Continuous,
        detections: Sequence[tuple[SensorFrame, Detection]],
        rng: np.random.Generator,
    ) -> tuple[IntArray, Array]:
        """The detected objects' rows in ``object_ids`` (T,) and the class log-evidence (T, M)
        this step's detections give each: log Σ_s w_s Π_{d of j} P(z_d | c, ψ_ds), w_s the
        normalised sample weights (uniform for ``geo_conditioned``)."""
        terms = self._semantic_terms(detections)
        g = self._involved(cont, detections)
        if self.config.weight_estimator == "geo_conditioned":
            eps = rng.standard_normal((self.config.num_samples, len(g.info)))
            base_all, log_lik_all = geo_conditioned_batch([g], terms, self.model.classifier, eps)
            base, log_lik = base_all[0], log_lik_all[0]
        else:
            z_geo = np.array([d.z_geo for _, d in detections])
            geo_terms = (terms.robot_var, terms.object_var, z_geo, self._geo_cov)
            ev = paper_mc_samples(
                g, terms, geo_terms, self.model.classifier, self.config.num_samples, rng
            )
            base, log_lik = ev.base, ev.log_lik
        det_rows = np.array([self._object_index[d.object_id] for _, d in detections])
        rows, group = np.unique(det_rows, return_inverse=True)
        onehot = group.reshape(-1)[:, None] == np.arange(len(rows))[None, :]  # (D, T)
        per_object = np.einsum("sdm,dt->stm", log_lik, onehot.astype(float))  # (S, T, M)
        log_w = base - logsumexp(base)  # (S,)
        evidence = logsumexp(per_object + log_w[:, None, None], axis=0)
        if not np.isfinite(evidence).all():
            raise FloatingPointError("a detection has zero likelihood under every class")
        return rows.astype(np.int64), np.asarray(evidence)

    def _set_map_classes(self) -> None:
        """Per-object classes: the one hypothesis carries every object's most probable class
        (what snapshots and plots show as its realisation)."""
        h = self.hypotheses[0]
        h.classes = tuple(np.argmax(self.class_log_posterior(), axis=1).tolist())
        h.log_weight = 0.0
        self._class_rows = None

    def _relinearise_evidence(self) -> None:
        """Move every hypothesis' weight by the change of its semantic evidence since the
        weights last saw its continuous belief's estimate (``estimator.ledger``)."""
        if self.per_object:
            ledger = self.hypotheses[0].continuous.ledger
            if ledger is not None and self.object_ids:
                cont = self.hypotheses[0].continuous
                model = self.model.classifier
                if isinstance(cont.isam, WindowedISAM2):
                    oldest = cont.isam.oldest_kept()
                    ledger.retire(pose_steps(ledger.robot_key_array()) >= oldest)
                self._since_refresh += 1
                if self._since_refresh < self.config.ledger_every:
                    ledger.settle(cont.pose, model)
                    return
                self._since_refresh = 0
                self.log_evidence += ledger.refresh(cont.estimate, model, self._object_index)
            return
        conts, which = distinct_continuous(self.hypotheses)
        if not self.object_ids or all(c.ledger is None for c in conts):
            return
        classes = self.class_matrix()
        columns = np.arange(len(self.object_ids))
        for g, c in enumerate(conts):
            if c.ledger is None:
                continue
            change = c.ledger.refresh(c.estimate, self.model.classifier, self._object_index)
            rows = np.flatnonzero(which == g)
            moved = change[columns[None, :], classes[rows]].sum(axis=1)
            for i, delta in zip(rows, moved, strict=True):
                self.hypotheses[i].log_weight += float(delta)

    def _evidence(
        self,
        parents: Sequence[Hypothesis],
        conts: Sequence[Continuous],
        which: IntArray,
        detections: Sequence[tuple[SensorFrame, Detection]],
        new_ids: Sequence[int],
        rng: np.random.Generator,
    ) -> _Evidence:
        """The weight integral of every parent's children (Eq. 6), reduced to what branching
        needs. The integrals are evaluated once per continuous belief ``conts`` (``which`` (P,)
        maps the parents onto them), in chunks, vectorised within a chunk."""
        terms = self._semantic_terms(detections)
        parent_cls = self._classes_of(parents)
        per_cont = len(detections) * self.config.num_samples * self.model.num_classes
        size = max(1, _EVIDENCE_CHUNK // max(per_cont, 1))
        accs, margs, lts = [], [], []
        order = []
        eps = None  # the draws every parent shares (``geo_conditioned_batch``)
        for start in range(0, len(conts), size):
            chunk = conts[start : start + size]
            gs = [self._involved(c, detections) for c in chunk]
            if self.config.weight_estimator == "geo_conditioned":
                if eps is None:
                    eps = rng.standard_normal((self.config.num_samples, len(gs[0].info)))
                base, log_lik = geo_conditioned_batch(gs, terms, self.model.classifier, eps)
            else:
                z_geo = np.array([d.z_geo for _, d in detections])
                geo_terms = (terms.robot_var, terms.object_var, z_geo, self._geo_cov)
                evs = [
                    paper_mc_samples(
                        g, terms, geo_terms, self.model.classifier, self.config.num_samples, rng
                    )
                    for g in gs
                ]
                base = np.stack([ev.base for ev in evs])
                log_lik = np.stack([ev.log_lik for ev in evs])
            members = np.flatnonzero((which >= start) & (which < start + len(chunk)))
            acc, marg, lt = self._reduce(
                parent_cls[members],
                which[members] - start,
                base,
                log_lik,
                detections,
                new_ids,
            )
            accs.append(acc)
            margs.append(marg)
            lts.append(lt)
            order.append(members)
        acc = np.empty((len(parents), accs[0].shape[1]))
        acc[np.concatenate(order)] = np.concatenate(accs)
        return _Evidence(acc, np.concatenate(margs), np.concatenate(lts), which)

    def _reduce(
        self,
        parent_cls: IntArray,
        which: IntArray,
        base: Array,
        log_lik: Array,
        detections: Sequence[tuple[SensorFrame, Detection]],
        new_ids: Sequence[int],
    ) -> tuple[Array, Array, Array]:
        """Per-sample evidence for :meth:`_branch`: base (G, S) and semantic log-likelihoods
        (G, S, D, M) of G continuous beliefs, and the parents that use them (``which`` (P,)),
        with their classes ``parent_cls`` (P, n) →
        ``acc`` (P, S) per parent, with every new object's class summed out under its prior,
        ``marg`` (G, T, S) those sums per new object, and ``lt`` (G, T, M, S) Σ log P(z_d | c)
        over each new object's detections."""
        log_prior = self._log_prior
        new_col = {j: t for t, j in enumerate(new_ids)}
        dets_of: list[list[int]] = [[] for _ in new_ids]
        old_cols: list[int] = []
        old_index: list[int] = []
        for col, (_, d) in enumerate(detections):
            if d.object_id in new_col:
                dets_of[new_col[d.object_id]].append(col)
            else:
                old_cols.append(col)
                old_index.append(self._object_index[d.object_id])
        g, samples = base.shape
        m = self.model.num_classes
        lt = np.empty((g, len(new_ids), m, samples))
        marg = np.empty((g, len(new_ids), samples))
        for t, cols in enumerate(dets_of):
            summed = log_lik[:, :, cols, :].sum(axis=2)  # (G, S, M)
            lt[:, t] = np.swapaxes(summed, 1, 2)
            marg[:, t] = logsumexp(summed + log_prior, axis=2)
        acc = base[which] + marg.sum(axis=1)[which]
        if old_cols:
            cls = parent_cls[:, old_index]
            old = np.ascontiguousarray(np.moveaxis(log_lik[:, :, old_cols, :], 1, 3))  # (G,D,M,S)
            det = np.arange(len(old_cols))
            # Parents in slices, so that the gathered (P', D_old, S) stays within the chunk.
            rows = max(1, _EVIDENCE_CHUNK // max(1, len(old_cols) * samples))
            for first in range(0, len(parent_cls), rows):
                part = slice(first, first + rows)
                picked = old[which[part, None], det[None, :], cls[part]]  # (P', D_old, S)
                acc[part] += picked.sum(axis=1)
        return acc, marg, lt

    def _branch(
        self, parents: Sequence[Hypothesis], evidence: _Evidence, new_ids: Sequence[int]
    ) -> _Beam:
        """Children of every parent over the classes of the new objects (Eq. 6), assigned one
        object at a time and pruned between objects, so that a step's cost grows linearly with the
        number of new objects instead of as M^|new|.

        A partial child's weight has the classes of the objects not yet assigned summed out under
        their prior, with the same Monte Carlo samples as its completions: it is exactly the sum of
        its completions' weights, so pruning a partial child prunes nothing it would have kept
        for a reason the full children could reverse."""
        log_prior = self._log_prior
        acc, marg, lt_all = evidence.acc, evidence.marg, evidence.lt
        samples = acc.shape[1]
        parent_lw = np.array([h.log_weight for h in parents])
        parent_cls = self._classes_of(parents)
        beam = _Beam(
            np.arange(len(parents)),
            np.zeros((len(parents), 0), dtype=np.int64),
            np.zeros(len(parents)),
            acc,
            parent_lw + logsumexp(acc, axis=1) - np.log(samples),
            len(parents),
        )
        if not new_ids:
            kept, lw = self._prune(beam.log_weight, parent_cls)
            return beam.keep(kept, lw)
        m = self.model.num_classes
        which = evidence.which
        for t in range(len(new_ids)):
            g = which[beam.parent]
            lt = lt_all[g, t]  # (K, M, S)
            grown = beam.acc[:, None, :] - marg[g, t][:, None, :] + lt
            grown = np.where(np.isnan(grown), -np.inf, grown)  # −inf − (−inf): a dead sample
            prior = beam.log_prior[:, None] + log_prior[None, :]
            lw = parent_lw[beam.parent][:, None] + prior + logsumexp(grown, axis=2)
            lw -= np.log(samples)
            k = len(beam.parent)
            classes = np.concatenate(
                [np.repeat(beam.classes, m, axis=0), np.tile(np.arange(m), k)[:, None]], axis=1
            )
            beam = _Beam(
                np.repeat(beam.parent, m),
                classes,
                prior.reshape(-1),
                grown.reshape(k * m, samples),
                lw.reshape(-1),
                beam.weighed + k * m,
            )
            full = np.concatenate([parent_cls[beam.parent], beam.classes], axis=1)
            if t < len(new_ids) - 1:
                reference = self._greedy_completion(beam, evidence, parent_lw, t)
                beam = beam.keep(self._select(beam.log_weight, full, reference))
            else:
                beam = beam.keep(*self._prune(beam.log_weight, full))
        if len(beam.parent) == 0:
            raise FloatingPointError(
                "every hypothesis has zero likelihood for this step's measurements"
            )
        return beam

    def _check_frames(self, frames: Sequence[SensorFrame]) -> None:
        seen = set()
        for f in frames:
            if f.robot not in self._slot:
                raise ValueError(f"frame of unknown robot {f.robot!r}")
            if f.robot in seen:
                raise ValueError(f"two frames of robot {f.robot!r} in one step")
            if f.k != self.step_of[f.robot] + 1:
                raise ValueError(
                    f"robot {f.robot!r} is at step {self.step_of[f.robot]}, got frame {f.k}"
                )
            for d in f.detections:
                if np.shape(d.z_geo) != (self._kind.dim,):
                    raise ValueError(
                        f"frame {f.k} of {f.robot!r}: object {d.object_id}'s z_geo has "
                        f"{np.size(d.z_geo)} numbers, this belief's {self._kind.name} objects "
                        f"{self._kind.dim}"
                    )
            seen.add(f.robot)
        window = self.config.window
        if window is not None and len(self.robots) > 1:
            # the window marginalises every pose older than the newest step less a window: a
            # robot further behind would lose the pose its next frame continues
            after = {**self.step_of, **{f.robot: f.k for f in frames}}
            lead = max(after, key=after.__getitem__)
            lag = min(after, key=after.__getitem__)
            if after[lead] - after[lag] > window:
                raise ValueError(
                    f"robot {lag!r} would be {after[lead] - after[lag]} steps behind {lead!r}: a "
                    f"window of {window} poses needs the robots of one belief to step within a "
                    "window of each other (window=None keeps every pose)"
                )

    @property
    def relinearize_threshold(self) -> float:
        """iSAM2's relinearisation threshold (``BeliefConfig.relinearize_threshold``)."""
        if self.config.relinearize_threshold is not None:
            return self.config.relinearize_threshold
        return float(np.min(self.model.odometry_noise.sigmas)) / 3.0

    def _isam_params(self) -> gtsam.ISAM2Params:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.relinearize_threshold)
        params.relinearizeSkip = self.config.relinearize_skip
        params.enablePartialRelinearizationCheck = self.config.partial_relinearization
        return params

    def _propagate(
        self,
        h: Continuous,
        frames: Sequence[SensorFrame],
        first: Mapping[int, tuple[SensorFrame, Detection]],
    ) -> None:
        """Motion factors and the priors of newly seen objects (class-independent)."""
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        new_pose: dict[str, gtsam.Pose2] = {}
        for f in frames:
            prev, cur = self.pose_key(f.robot, f.k - 1), self.pose_key(f.robot, f.k)
            u = gtsam.Pose2(*f.odometry)
            graph.add(gtsam.BetweenFactorPose2(prev, cur, u, self._odometry_noise))
            new_pose[f.robot] = h.pose2(prev).compose(u)
            values.insert(cur, new_pose[f.robot])
        for j, (f, d) in first.items():
            o = self._kind.place(_xytheta(new_pose[f.robot]), d.z_geo)
            graph.add(object_prior(object_key(j), o, self._object_prior))
            values.insert(object_key(j), object_value(o))
            h.object_priors[j] = o
        h.isam.update(graph, values)
        h.updated()

    def _semantic_terms(self, detections: Sequence[tuple[SensorFrame, Detection]]) -> SemanticTerms:
        """The step's semantic measurements, indexed like :meth:`_involved`'s variables."""
        index: dict[int, int] = {}
        robot_var: list[int] = []
        object_var: list[int] = []
        for f, d in detections:
            for key, out in (
                (self.pose_key(f.robot, f.k), robot_var),
                (object_key(d.object_id), object_var),
            ):
                out.append(index.setdefault(key, len(index)))
        z = np.array([d.z_sem for _, d in detections])
        return SemanticTerms(np.array(robot_var), np.array(object_var), z)

    def _involved(
        self, h: Continuous, detections: Sequence[tuple[SensorFrame, Detection]]
    ) -> InvolvedGaussian:
        """``h``'s propagated belief over the involved variables (this step's robot poses and the
        detected objects, in order of first appearance) and the linearised geometric factors."""
        keys: list[int] = []
        for f, d in detections:
            for key in (self.pose_key(f.robot, f.k), object_key(d.object_id)):
                if key not in keys:
                    keys.append(key)
        n = 3 * len(keys)
        at = h.values(keys)
        dim = self._kind.dim
        rows, rhs = [], []
        for f, d in detections:
            xk, oj = self.pose_key(f.robot, f.k), object_key(d.object_id)
            factor = detection_factor(xk, oj, d.z_geo, self._geometric_noise)
            a, b = factor.linearize(at).jacobian()
            rv, ov = keys.index(xk), keys.index(oj)
            row = np.zeros((dim, n))
            row[:, 3 * rv : 3 * rv + 3] = a[:, :3]
            row[:, 3 * ov : 3 * ov + dim] = a[:, 3 : 3 + dim]
            rows.append(row)
            rhs.append(b)
        joint = h.isam.jointMarginalInformation(gtsam.KeyVector(keys))
        info = np.asarray(joint.fullMatrix())  # blocks in the order of ``keys``
        lin = np.array(
            [self._kind.as_pose(h.pose(key)) if is_object_key(key) else h.pose(key) for key in keys]
        )
        if dim != 3:
            info = _as_pose_blocks(info, [is_object_key(k) for k in keys])
        return InvolvedGaussian(
            lin, info, np.vstack(rows), np.concatenate(rhs), len(detections) * self._geo_log_norm
        )

    def _select(
        self, log_weights: Array, classes: IntArray, reference: float | None = None
    ) -> IntArray:
        """Indices of the candidates to keep (``estimator.pruning.select``): log-weights (K,) of
        candidates with class realisations (K, n)."""
        rule = self.config.rule(self.information_sources())
        return select(log_weights, classes, self.model.num_classes, rule, reference)

    def _prune(self, log_weights: Array, classes: IntArray) -> tuple[IntArray, Array]:
        """The final pruning of a step or fusion: the kept indices and their log-weights, which the
        ``"marginal"`` rule adjusts so that the kept realisations keep every object's class
        marginals of the candidates (``estimator.pruning.match_marginals``)."""
        kept = self._select(log_weights, classes)
        if self.config.pruning != "marginal" or len(kept) == len(log_weights):
            return kept, log_weights[kept]
        w = np.exp(log_weights - np.max(log_weights))
        target = class_marginals(w / w.sum(), classes, self.model.num_classes)
        lw = match_marginals(log_weights[kept], classes[kept], target)
        return kept, lw + float(logsumexp(log_weights[kept]))

    def _greedy_completion(
        self, beam: _Beam, evidence: _Evidence, parent_lw: Array, t: int
    ) -> float:
        """The log-weight of one full child: the heaviest partial child after object ``t``,
        completed with each remaining object's most probable class on its own. Every full child
        the ratio rule keeps is within the ratio of the heaviest full child, hence of this one's
        lower bound."""
        b = int(np.argmax(beam.log_weight))
        p = int(beam.parent[b])
        g = int(evidence.which[p])
        rest = evidence.lt[g, t + 1 :]  # (T', M, S)
        log_prior = self._log_prior
        best = np.argmax(log_prior[None, :] + logsumexp(rest, axis=2), axis=1)  # (T',)
        acc = beam.acc[b] - evidence.marg[g, t + 1 :].sum(axis=0)
        acc = acc + rest[np.arange(len(best)), best].sum(axis=0)
        samples = len(acc)
        lw = parent_lw[p] + beam.log_prior[b] + log_prior[best].sum()
        return float(lw + logsumexp(acc) - np.log(samples))

    def _materialise(
        self,
        parents: Sequence[Hypothesis],
        beam: _Beam,
        detections: Sequence[tuple[SensorFrame, Detection]],
    ) -> list[Hypothesis]:
        """The kept children, with the step's factors added once per distinct continuous belief:
        children of parents that share one share one, unless ``semantic_poses`` gives them
        different semantic factors (different classes of the detected objects)."""
        semantic = self.config.semantic_poses
        detected = [self._object_index[d.object_id] for _, d in detections]
        groups: dict[tuple[int, tuple[int, ...]], list[int]] = {}
        child_classes = []
        parent_of = beam.parent.tolist()
        for i, (p, grown) in enumerate(zip(parent_of, beam.classes.tolist(), strict=True)):
            parent = parents[p]
            classes = parent.classes + tuple(grown)
            child_classes.append(classes)
            factors = tuple(classes[j] for j in detected) if semantic else ()
            groups.setdefault((id(parent.continuous), factors), []).append(i)
        last_group = {}
        for key in groups:
            last_group[key[0]] = key
        source = {id(h.continuous): h.continuous for h in parents}
        log_weight_of = beam.log_weight.tolist()
        children: dict[int, Hypothesis] = {}
        made = []
        for key, members in groups.items():
            base = source[key[0]]
            # Every other group copies its parent's iSAM2 first; the last takes it over.
            cont = base if last_group[key[0]] == key else base.copy()
            made.append((cont, child_classes[members[0]]))
            for i in members:
                used_phi = dict(parents[parent_of[i]].used_phi)
                children[i] = Hypothesis(child_classes[i], cont, log_weight_of[i], used_phi)
        for cont, classes in made:
            self._measure(cont, classes, detections)
        return [children[i] for i in range(len(beam.parent))]

    def _measure(
        self,
        h: Continuous,
        classes: tuple[int, ...],
        detections: Sequence[tuple[SensorFrame, Detection]],
    ) -> None:
        """Add the geometric factors of this step's detections (Eq. 5), and with
        ``semantic_poses`` the semantic factors of ``classes``."""
        graph = gtsam.NonlinearFactorGraph()
        point = self._kind is not POSE
        for f, d in detections:
            xk, oj = self.pose_key(f.robot, f.k), object_key(d.object_id)
            graph.add(detection_factor(xk, oj, d.z_geo, self._geometric_noise))
            if h.ledger is not None:
                h.ledger.add(xk, d.object_id, d.z_sem)
            if self.config.semantic_poses:
                c = classes[self._object_index[d.object_id]]
                psi0 = float(viewpoint(h.pose(xk), self._kind.as_pose(h.pose(oj))))
                graph.add(semantic_factor(self.model.classifier, c, d.z_sem, xk, oj, psi0, point))
        h.isam.update(graph, gtsam.Values())
        for _ in range(self.config.extra_updates):
            h.isam.update()
        h.updated()

    def _normalise(self) -> None:
        lw = np.array([h.log_weight for h in self.hypotheses])
        total = float(np.logaddexp.reduce(lw))
        for h in self.hypotheses:
            h.log_weight -= total
