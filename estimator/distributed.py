"""The distributed belief D (Eq. 12, 17, 19, 20; design doc §6).

D is a hybrid belief over its owner's trajectory and every object it knows of, from its own data
or from other robots' slots. Integrating a newer version of robot i's slot multiplies in its ξ and
φ and divides out the version used before: the old ξ factor leaves iSAM2 (``downdate="remove"``) or
is cancelled by its negation (``"anti"``, DDF-SAM 2.0), and its log φ is subtracted. With
``fusion="double_count"`` neither happens: the paper's double-counting baseline.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.factors import object_key
from estimator.hybrid import BeliefConfig, BeliefModel, HybridBelief, Hypothesis, UsedSlot
from estimator.summary import LocalSummary, Realisation

Array = NDArray[np.float64]

log = logging.getLogger(__name__)

FUSIONS = ("consistent", "double_count")
DOWNDATES = ("remove", "anti")

# Between two slots of one batch the join keeps at most this many times max_hypotheses candidates;
# ratio pruning and the cap proper apply once, after the whole batch.
_JOIN_GUARD = 20


class SlotError(ValueError):
    """A slot cannot be integrated: it contradicts this belief (wrong class count, bad shapes)."""


@dataclass(frozen=True, slots=True)
class IncomingSlot:
    """Robot ``owner``'s summary at its step ``stamp``."""

    owner: str
    stamp: int
    summary: LocalSummary


@dataclass(frozen=True, slots=True)
class FusionStats:
    """What one integration did: slots integrated, slots skipped (empty join), hypotheses.

    ``empty_joins`` counts slots whose join with D's hypotheses was empty and ``rebuilds`` the
    times D was rebuilt from its local data and every held slot because of one."""

    integrated: tuple[str, ...]
    skipped: tuple[str, ...]
    candidates: int
    kept: int
    empty_joins: int = 0
    rebuilds: int = 0


@dataclass(frozen=True, slots=True)
class _Join:
    parent: int
    picks: tuple[tuple[int, int], ...]  # (slot index in the batch, realisation index)
    classes: tuple[int, ...]
    log_weight: float


def xi_factor(
    keys: Sequence[int], r: Realisation, sign: float = 1.0
) -> gtsam.LinearContainerFactor:
    """ξ of a realisation as a GTSAM factor on the object ``keys``: an n-key HessianFactor (summed
    from unary and pairwise pieces; Python constructors stop at three keys) wrapped in a
    LinearContainerFactor at ``r.lin``. ``sign = −1`` gives the anti-factor."""
    n = len(keys)
    info, eta = sign * r.info, sign * r.eta
    pieces = gtsam.GaussianFactorGraph()
    zero = np.zeros((3, 3))
    for i in range(n):
        bi = slice(3 * i, 3 * i + 3)
        pieces.add(gtsam.HessianFactor(keys[i], info[bi, bi], eta[bi], 0.0))
        for j in range(i + 1, n):
            bj = slice(3 * j, 3 * j + 3)
            pieces.add(
                gtsam.HessianFactor(
                    keys[i], keys[j], zero, info[bi, bj], np.zeros(3), zero, np.zeros(3), 0.0
                )
            )
    lin = gtsam.Values()
    for key, pose in zip(keys, r.lin, strict=True):
        lin.insert(key, gtsam.Pose2(*pose))
    return gtsam.LinearContainerFactor(gtsam.HessianFactor(pieces), lin)


class DistributedBelief(HybridBelief):
    """D of robot ``owner``: its own data, plus every other robot's latest slot (never its own)."""

    def __init__(
        self,
        model: BeliefModel,
        owner: str,
        start: ArrayLike,
        config: BeliefConfig | None = None,
        fusion: str = "consistent",
        downdate: str = "remove",
    ) -> None:
        if fusion not in FUSIONS:
            raise ValueError(f"fusion {fusion!r} (known: {', '.join(FUSIONS)})")
        if downdate not in DOWNDATES:
            raise ValueError(f"downdate {downdate!r} (known: {', '.join(DOWNDATES)})")
        super().__init__(model, {owner: start}, config)
        self.owner = owner
        self.fusion = fusion
        self.downdate = downdate
        self.stamps: dict[str, int] = {}

    def wants(self, owner: str, stamp: int) -> bool:
        """Whether a slot version is new to this belief (never its own slot)."""
        return owner != self.owner and stamp > self.stamps.get(owner, -1)

    def integrate(self, slots: Sequence[IncomingSlot], settle: bool = True) -> FusionStats:
        """Integrate every slot that is newer than the version used before (Eq. 12, 17).

        ``settle`` runs the configured extra iSAM2 updates after the fusion; a caller that steps
        D right away (the RobotNode) passes False, since that step updates iSAM2 again.
        """
        batch = [s for s in slots if self.wants(s.owner, s.stamp)]
        owners = [s.owner for s in batch]
        if len(set(owners)) != len(owners):
            raise SlotError(f"two versions of one robot's slot in one batch: {owners}")
        for s in batch:
            self.check(s)
        if not batch:
            return FusionStats((), (), 0, len(self.hypotheses))
        joins, order, skipped = self._join(batch)
        if not joins:
            return FusionStats((), tuple(owners), 0, len(self.hypotheses))
        kept = self._select([(j.parent, i, j.log_weight) for i, j in enumerate(joins)])
        used_batch = [s for i, s in enumerate(batch) if s.owner not in skipped]
        parents = self.hypotheses
        for j in order:
            self._object_index[j] = len(self.object_ids)
            self.object_ids.append(j)
        survivors = [joins[i] for _, i, _ in kept]
        last_child = {}
        for n, join in enumerate(survivors):
            last_child[join.parent] = n
        children = []
        for n, join in enumerate(survivors):
            child = parents[join.parent].branch(
                join.classes, join.log_weight, copy_isam=last_child[join.parent] != n
            )
            self._fuse(child, join, batch, order, settle)
            children.append(child)
        self.hypotheses = children
        self._normalise()
        for s in used_batch:
            self.stamps[s.owner] = s.stamp
        return FusionStats(
            tuple(s.owner for s in used_batch), tuple(sorted(skipped)), len(joins), len(children)
        )

    def check(self, s: IncomingSlot) -> None:
        """Raise :class:`SlotError` if a slot contradicts this belief's model."""
        m = self.model.num_classes
        n = len(s.summary.object_ids)
        if len(set(s.summary.object_ids)) != n:
            raise SlotError(f"slot of {s.owner}: duplicate object ids")
        for r in s.summary.realisations:
            if len(r.classes) != n or any(not 0 <= c < m for c in r.classes):
                raise SlotError(
                    f"slot of {s.owner}: realisation classes do not fit {n} objects, {m} classes"
                )
            if r.lin.shape != (n, 3) or r.info.shape != (3 * n, 3 * n) or r.eta.shape != (3 * n,):
                raise SlotError(f"slot of {s.owner}: ξ shapes do not fit {n} objects")

    def _join(self, batch: Sequence[IncomingSlot]) -> tuple[list[_Join], list[int], set[str]]:
        """Join D's hypotheses with every slot's realisations on shared objects (bookkeeping only:
        no iSAM2 is touched). Returns the joins, the ids of objects new to D in order, and the
        owners whose slot joined with nothing (skipped)."""
        known = dict(self._object_index)
        order: list[int] = []
        joins = [_Join(p, (), h.classes, h.log_weight) for p, h in enumerate(self.hypotheses)]
        skipped: set[str] = set()
        for b, s in enumerate(batch):
            ids = s.summary.object_ids
            shared = [(known[j], i) for i, j in enumerate(ids) if j in known]
            fresh = [i for i, j in enumerate(ids) if j not in known]
            extended = []
            for join in joins:
                old = self.hypotheses[join.parent].used.get(s.owner)
                divide = old is not None and self.fusion == "consistent"
                minus = old.realisation.log_phi if old is not None and divide else 0.0
                for r, real in enumerate(s.summary.realisations):
                    if any(join.classes[a] != real.classes[i] for a, i in shared):
                        continue
                    new_classes = tuple(real.classes[i] for i in fresh)
                    lw = join.log_weight + real.log_phi - minus
                    lw += float(sum(self._log_prior[c] for c in new_classes))
                    extended.append(
                        _Join(join.parent, (*join.picks, (b, r)), join.classes + new_classes, lw)
                    )
            if not extended:
                # Expected under double counting (D becomes overconfident and prunes what the
                # owner keeps); a sign of trouble under consistent fusion.
                level = logging.WARNING if self.fusion == "consistent" else logging.DEBUG
                log.log(
                    level,
                    "slot of %s (stamp %d) joins with no hypothesis: skipped",
                    s.owner,
                    s.stamp,
                )
                skipped.add(s.owner)
                continue
            guard = _JOIN_GUARD * self.config.max_hypotheses
            if len(extended) > guard:
                extended.sort(key=lambda j: -j.log_weight)
                extended = extended[:guard]
            joins = extended
            for i in fresh:
                known[ids[i]] = len(known)
                order.append(ids[i])
        return joins, order, skipped

    def _fuse(
        self,
        h: Hypothesis,
        join: _Join,
        batch: Sequence[IncomingSlot],
        order: Sequence[int],
        settle: bool,
    ) -> None:
        """Add the picked realisations' ξ factors and the priors of objects new to D, and divide
        out the versions used before (Eq. 12)."""
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        remove: list[int] = []
        new_objects = set(order)
        positions = []  # (slot, realisation, first and last graph position of its factors)
        for b, r in join.picks:
            s = batch[b]
            real = s.summary.realisations[r]
            ids = s.summary.object_ids
            first = graph.size()
            for i, j in enumerate(ids):
                if j in new_objects and j not in h.object_priors:
                    pose = gtsam.Pose2(*real.lin[i])
                    graph.add(gtsam.PriorFactorPose2(object_key(j), pose, self._object_prior))
                    values.insert(object_key(j), pose)
                    h.object_priors[j] = real.lin[i].copy()
            old = h.used.get(s.owner)
            carried: tuple[int, ...] = ()
            if old is not None:
                if self.fusion == "double_count":
                    carried = old.factor_indices
                elif self.downdate == "remove":
                    remove.extend(old.factor_indices)
                else:
                    carried = old.factor_indices
                    graph.add(
                        xi_factor([object_key(j) for j in old.object_ids], old.realisation, -1.0)
                    )
            start = graph.size()
            graph.add(xi_factor([object_key(j) for j in ids], real))
            positions.append((s, real, carried, first, start))
        result = h.isam.update(graph, values, remove)
        new_indices = list(result.getNewFactorsIndices())
        for s, real, carried, _, start in positions:
            anti = (
                (new_indices[start - 1],)
                if start > 0 and carried and self.fusion == "consistent"
                else ()
            )
            own = (*carried, *anti, new_indices[start])
            h.used[s.owner] = UsedSlot(s.stamp, s.summary.object_ids, real, own)
        for _ in range(self.config.extra_updates if settle else 0):
            h.isam.update()
        h.estimate = h.isam.calculateEstimate()
