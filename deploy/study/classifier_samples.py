"""Classifier score samples (class, ψ, score vector): drawn from a model, written and read as CSV.

The file is what ``semfleet classifier fit`` learns from (docs/models.md): a header
``class,psi,z1,…,zM`` and one sample per line, the class numbered 1..M as in scenario files, ψ in
radians, the M score components. Reading it checks every field and names the line at fault. ψ is
in the convention the writer and the reader state (``--viewpoint``; semfleet's own, object →
camera, by default): the model file learned from it records that convention.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from deploy.base.errors import UsageError
from estimator.models import ClassifierModel
from estimator.models.classifier import OBJECT_TO_CAMERA, view_offset

Array = NDArray[np.float64]

MAX_SAMPLES = 1_000_000


@dataclass(frozen=True)
class ScoreSamples:
    """``classes`` (n,) in 0..M−1, viewpoints ``psi`` (n,) [rad], scores ``z`` (n, M)."""

    classes: NDArray[np.int64]
    psi: Array
    z: Array

    @property
    def num_classes(self) -> int:
        return int(self.z.shape[1])

    def of_class(self, c: int) -> tuple[Array, Array]:
        """(ψ (n_c,), z (n_c, M)) of class ``c``'s samples."""
        mask = self.classes == c
        return self.psi[mask], self.z[mask]


def draw_samples(
    model: ClassifierModel, n: int, rng: np.random.Generator, viewpoint: str = OBJECT_TO_CAMERA
) -> ScoreSamples:
    """``n`` samples of ``model``: the classes as balanced as ``n`` allows (in random order), ψ
    uniform on [−π, π) in the ``viewpoint`` convention (semfleet's own, object → camera, by
    default; camera → object is semfleet's ψ + π), ``z ~ N(h_c(ψ), Σ_c(ψ))`` (Eq. 1, as the
    simulator draws them)."""
    m = model.num_classes
    classes = rng.permutation(np.arange(n) % m).astype(np.int64)
    psi = rng.uniform(-math.pi, math.pi, n)
    ours = psi - view_offset(viewpoint)  # the ψ the model takes
    eps = rng.standard_normal((n, model.dim))
    z = np.empty((n, model.dim))
    for c in range(m):
        idx = np.flatnonzero(classes == c)
        chol = np.linalg.cholesky(model.cov(c, ours[idx]))  # (n_c, dim, dim)
        z[idx] = model.mean(c, ours[idx]) + np.einsum("nij,nj->ni", chol, eps[idx])
    return ScoreSamples(classes, psi, z)


def write_samples(samples: ScoreSamples, path: Path) -> None:
    """Write ``samples`` as CSV (every number as the shortest text that reads back exactly)."""
    m = samples.num_classes
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as f:
        out = csv.writer(f)
        out.writerow(["class", "psi", *(f"z{i + 1}" for i in range(m))])
        for c, psi, z in zip(samples.classes, samples.psi, samples.z, strict=True):
            out.writerow([int(c) + 1, repr(float(psi)), *(repr(float(v)) for v in z)])


def read_samples(path: Path) -> ScoreSamples:
    """Read and check a samples file; a :class:`UsageError` naming the file, line and field."""
    try:
        with path.open(newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except FileNotFoundError:
        raise UsageError(f"{path}: no such samples file") from None
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise UsageError(f"{path}: cannot read: {exc}") from None
    if not rows:
        raise UsageError(f"{path}: empty (expected a header class,psi,z1,…,zM)")
    header = [h.strip() for h in rows[0]]
    m = len(header) - 2
    expected = ["class", "psi", *(f"z{i + 1}" for i in range(max(m, 0)))]
    if m < 2 or header != expected:
        raise UsageError(f"{path}: line 1: expected the header class,psi,z1,…,zM with M ≥ 2")
    body = rows[1:]
    if len(body) > MAX_SAMPLES:
        raise UsageError(f"{path}: {len(body)} samples, at most {MAX_SAMPLES} are read")
    classes = np.empty(len(body), dtype=np.int64)
    values = np.empty((len(body), m + 1))
    for i, row in enumerate(body):
        line = i + 2
        if len(row) != m + 2:
            raise UsageError(f"{path}: line {line}: {len(row)} fields, the header has {m + 2}")
        classes[i] = _class(path, line, row[0], m) - 1
        for j, text in enumerate(row[1:]):
            values[i, j] = _number(path, line, header[j + 1], text)
    return ScoreSamples(classes, values[:, 0], values[:, 1:])


def _class(path: Path, line: int, text: str, m: int) -> int:
    try:
        c = int(text)
    except ValueError:
        raise UsageError(f"{path}: line {line}: class: {text!r} is not an integer") from None
    if not 1 <= c <= m:
        raise UsageError(f"{path}: line {line}: class: {c} is out of range 1..{m}")
    return c


def _number(path: Path, line: int, name: str, text: str) -> float:
    try:
        x = float(text)
    except ValueError:
        raise UsageError(f"{path}: line {line}: {name}: {text!r} is not a number") from None
    if not math.isfinite(x):
        raise UsageError(f"{path}: line {line}: {name}: {text} is not a finite number")
    return x
