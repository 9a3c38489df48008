"""Semantic relations between landmarks (design doc §6): labels, filter-level groups and the
threshold detector.

A group is a structural fact of the world — landmarks sharing x, sharing y, or lying on one line —
kept once for the whole filter, never per particle, so every particle evaluates the same
pseudo-measurement rows and the weights stay comparable.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from estimator.ufastslam.models import RELATION_KINDS

Array = NDArray[np.float64]

RELATION_SOURCES = ("off", "labels", "threshold")
RELATION_MODES = ("once", "every")
_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_CHI2_1DOF_99 = 6.635


class RelationError(ValueError):
    """A relation label or relation setting is malformed; the message names it and says why."""


@dataclass(frozen=True, slots=True)
class GroupLabel:
    """A front-end label ``KIND:NAME``: the landmark belongs to group NAME of kind x, y or col."""

    kind: str
    name: str

    @property
    def key(self) -> str:
        return f"{self.kind}:{self.name}"


def parse_label(text: object) -> GroupLabel:
    """``"x:west-wall"`` → GroupLabel("x", "west-wall"); anything malformed → RelationError."""
    if not isinstance(text, str):
        raise RelationError(f"relation label {text!r}: expected a string KIND:NAME")
    kind, sep, name = text.partition(":")
    if not sep:
        raise RelationError(f"relation label {text!r}: expected KIND:NAME, e.g. 'x:west-wall'")
    if kind not in RELATION_KINDS:
        raise RelationError(
            f"relation label {text!r}: unknown kind {kind!r} (known: {', '.join(RELATION_KINDS)})"
        )
    if not _NAME.match(name):
        raise RelationError(
            f"relation label {text!r}: group name {name!r} must be 1–64 of A–Z a–z 0–9 _ . -"
        )
    return GroupLabel(kind, name)


@dataclass(frozen=True, slots=True)
class RelationConfig:
    """Where relations come from and how they are applied.

    ``source``: ``off``, ``labels`` (given with each observation; ground truth in simulation) or
    ``threshold`` (detected on the weighted-mean map). ``mode``: ``once`` applies a relation when
    its landmark is first mapped (default: its error is a static property of the world, re-applying
    it double-counts); ``every`` re-applies it at every observation with ``every_std``. ``std`` is
    σ_s in metres. Detection: same-x/same-y within ``line_threshold`` m; collinear within
    ``collinear_threshold`` m of a line with a baseline ≥ ``collinear_min_baseline`` m and a
    direction ≥ ``collinear_min_axis_angle_deg`` from both axes; all behind a Mahalanobis ``gate``.
    """

    source: str = "off"
    mode: str = "once"
    std: float = 0.05
    every_std: float = 0.15
    line_threshold: float = 0.4
    collinear_threshold: float = 0.25
    collinear_min_baseline: float = 2.0
    collinear_min_axis_angle_deg: float = 10.0
    gate: float = _CHI2_1DOF_99

    def __post_init__(self) -> None:
        if self.source not in RELATION_SOURCES:
            raise RelationError(
                f"relations.source {self.source!r} (known: {', '.join(RELATION_SOURCES)})"
            )
        if self.mode not in RELATION_MODES:
            raise RelationError(
                f"relations.mode {self.mode!r} (known: {', '.join(RELATION_MODES)})"
            )
        for name in ("std", "every_std", "line_threshold", "collinear_threshold", "gate"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise RelationError(f"relations.{name} must be finite and > 0, got {value}")
        if not (math.isfinite(self.collinear_min_baseline) and self.collinear_min_baseline >= 0):
            raise RelationError("relations.collinear_min_baseline must be finite and ≥ 0")
        if not 0 <= self.collinear_min_axis_angle_deg < 45:
            raise RelationError("relations.collinear_min_axis_angle_deg must be in [0, 45)")

    @property
    def row_std(self) -> float:
        """σ_s of one pseudo-measurement row in this mode."""
        return self.std if self.mode == "once" else self.every_std


@dataclass(slots=True)
class Group:
    """Landmarks (filter indices) related by one fact: kind ``x``, ``y`` or ``col``."""

    kind: str
    name: str
    members: list[int] = field(default_factory=list)


@dataclass(frozen=True, slots=True)
class Row:
    """One pseudo-measurement row 0 = c(m_landmark; refs) + n_s for group ``group``."""

    kind: str
    group: int
    landmark: int
    refs: tuple[int, ...]


@dataclass(frozen=True, slots=True)
class MapView:
    """The weighted-mean map the detector tests against: ``mean`` (L, 2) and ``cov`` (L, 2, 2) of
    the landmarks mapped before this step (filter indices 0..L−1)."""

    mean: Array
    cov: Array


def references(kind: str, members: list[int], view: MapView) -> tuple[int, ...]:
    """The anchor of a row: the least uncertain mapped member (x, y), or the two most separated
    mapped members (col); () when there are not enough. ``members`` are all mapped."""
    if kind in ("x", "y"):
        if not members:
            return ()
        traces = np.trace(view.cov[members], axis1=-2, axis2=-1)
        return (members[int(np.argmin(traces))],)
    if len(members) < 2:
        return ()
    pts = view.mean[members]
    dist = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)
    i, j = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return (members[int(i)], members[int(j)])


@dataclass(frozen=True, slots=True)
class Candidate:
    """A detected relation of a new landmark: join group ``group``, or (group None) found a new
    group with the mapped landmarks ``partners``. ``score`` is the Mahalanobis distance²."""

    kind: str
    group: int | None
    partners: tuple[int, ...]
    score: float


def detect(
    p_hat: Array,
    p_cov: Array,
    view: MapView,
    groups: list[Group],
    covisible: list[int],
    config: RelationConfig,
) -> list[Candidate]:
    """Relations of a new landmark whose inverse-observed position is ``p_hat`` (2,) with
    covariance ``p_cov`` (2, 2): at most one same-x, one same-y and one collinear candidate, each
    the best by Mahalanobis distance among those within the geometric threshold and the gate.
    New collinear groups are only founded from ``covisible`` landmarks (seen in the same frame,
    as a camera sees three aligned landmarks in one image); existing groups may be joined from
    anywhere."""
    mapped = len(view.mean)
    out = []
    for axis, kind in ((0, "x"), (1, "y")):
        best = _line_candidate(axis, kind, p_hat, p_cov, view, groups, mapped, config)
        if best is not None:
            out.append(best)
    col = _collinear_candidate(p_hat, p_cov, view, groups, covisible, mapped, config)
    if col is not None:
        out.append(col)
    return out


def _line_candidate(
    axis: int,
    kind: str,
    p_hat: Array,
    p_cov: Array,
    view: MapView,
    groups: list[Group],
    mapped: int,
    config: RelationConfig,
) -> Candidate | None:
    values: list[float] = []
    variances: list[float] = []
    # Every mapped member must be within the threshold too, not just the group's mean: the row
    # is referenced to one member, and a loose test lets one false member chain in others.
    worst: list[float] = []
    targets: list[tuple[int | None, tuple[int, ...]]] = []
    grouped: set[int] = set()
    for g, group in enumerate(groups):
        if group.kind != kind:
            continue
        members = [m for m in group.members if m < mapped]
        grouped.update(group.members)
        if members:
            coords = view.mean[members, axis]
            values.append(float(coords.mean()))
            variances.append(float(view.cov[members, axis, axis].mean()))
            worst.append(float(np.max(np.abs(p_hat[axis] - coords))))
            targets.append((g, ()))
    for k in range(mapped):
        if k not in grouped:
            values.append(float(view.mean[k, axis]))
            variances.append(float(view.cov[k, axis, axis]))
            worst.append(abs(float(p_hat[axis] - view.mean[k, axis])))
            targets.append((None, (k,)))
    if not values:
        return None
    d = p_hat[axis] - np.asarray(values)
    score = d**2 / (p_cov[axis, axis] + np.asarray(variances) + config.std**2)
    ok = (np.asarray(worst) < config.line_threshold) & (score < config.gate)
    if not ok.any():
        return None
    i = int(np.argmin(np.where(ok, score, np.inf)))
    return Candidate(kind, targets[i][0], targets[i][1], float(score[i]))


def _collinear_candidate(
    p_hat: Array,
    p_cov: Array,
    view: MapView,
    groups: list[Group],
    covisible: list[int],
    mapped: int,
    config: RelationConfig,
) -> Candidate | None:
    pairs: list[tuple[int, int]] = []
    targets: list[tuple[int | None, tuple[int, ...]]] = []
    joined: set[frozenset[int]] = set()
    for g, group in enumerate(groups):
        if group.kind != "col":
            continue
        members = [m for m in group.members if m < mapped]
        refs = references("col", members, view)
        if refs:
            pairs.append((refs[0], refs[1]))
            targets.append((g, ()))
        joined.update(frozenset(p) for p in _all_pairs(members))
    seen = sorted(k for k in set(covisible) if k < mapped)
    for a, b in _all_pairs(seen):
        if frozenset((a, b)) not in joined:
            pairs.append((a, b))
            targets.append((None, (a, b)))
    if not pairs:
        return None
    ia = np.array([p[0] for p in pairs])
    ib = np.array([p[1] for p in pairs])
    a, b = view.mean[ia], view.mean[ib]
    base = b - a
    length = np.hypot(base[:, 0], base[:, 1])
    angle = np.degrees(np.arctan2(np.abs(base[:, 1]), np.abs(base[:, 0])))
    off_axis = np.minimum(angle, 90.0 - angle) >= config.collinear_min_axis_angle_deg
    unit = base / np.maximum(length, 1e-12)[:, None]
    normal = np.column_stack([-unit[:, 1], unit[:, 0]])
    dist = np.einsum("ni,ni->n", normal, p_hat - a)
    line_var = 0.5 * (
        np.einsum("ni,nij,nj->n", normal, view.cov[ia], normal)
        + np.einsum("ni,nij,nj->n", normal, view.cov[ib], normal)
    )
    p_var = np.einsum("ni,ij,nj->n", normal, p_cov, normal)
    score = dist**2 / (p_var + line_var + config.std**2)
    ok = (
        (length >= config.collinear_min_baseline)
        & off_axis
        & (np.abs(dist) < config.collinear_threshold)
        & (score < config.gate)
    )
    if not ok.any():
        return None
    i = int(np.argmin(np.where(ok, score, np.inf)))
    return Candidate("col", targets[i][0], targets[i][1], float(score[i]))


def _all_pairs(items: list[int]) -> list[tuple[int, int]]:
    return [(a, b) for i, a in enumerate(items) for b in items[i + 1 :]]
