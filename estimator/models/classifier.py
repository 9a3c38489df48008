"""Viewpoint-dependent classifier models, Eq. 1: ``z_sem ~ N(h_c(ψ), Σ_c(ψ))``.

Classes are indexed 0..M−1 in code (scenario files and reports say 1..M, as the paper does).
ψ, as :func:`viewpoint` computes it everywhere in semfleet, is the azimuth of the camera seen from
the object frame (object → camera). A model states its own convention (``viewpoint``): a model
whose ψ is the direction from the camera to the object, in the object frame (camera → object, the
paper's "relative viewpoint from the camera to the object" and its authors' score generator),
is evaluated at ψ + π. The two conventions are the same model with every view turned by π.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.models import se2

Array = NDArray[np.float64]

_LOG_2PI = math.log(2.0 * math.pi)

# A classifier model's viewpoint convention: what its ψ is, in the object's frame.
OBJECT_TO_CAMERA = "object_to_camera"  # the azimuth of the camera seen from the object
CAMERA_TO_OBJECT = "camera_to_object"  # the direction from the camera to the object (ψ + π)
VIEWPOINTS = (OBJECT_TO_CAMERA, CAMERA_TO_OBJECT)


def check_viewpoint(convention: str) -> str:
    """``convention`` if it is one of :data:`VIEWPOINTS`, else ValueError."""
    if convention not in VIEWPOINTS:
        raise ValueError(f"viewpoint {convention!r} (known: {', '.join(VIEWPOINTS)})")
    return convention


def view_offset(convention: str) -> float:
    """What a model of this convention adds to semfleet's ψ (object → camera): 0 or π."""
    return math.pi if check_viewpoint(convention) == CAMERA_TO_OBJECT else 0.0


def viewpoint(robot: ArrayLike, obj: ArrayLike) -> Array:
    """ψ of the camera at ``robot`` (..., 3) seen from object pose ``obj`` (..., 3) → (...)."""
    p = se2.transform_to(obj, np.asarray(robot, dtype=float)[..., :2])
    return np.asarray(np.arctan2(p[..., 1], p[..., 0]))


@runtime_checkable
class ClassifierModel(Protocol):
    """A classifier model P(z_sem | c, ψ). Implementations must be vectorised over ψ."""

    @property
    def num_classes(self) -> int:
        """M, the number of classes."""
        ...

    @property
    def dim(self) -> int:
        """Length of a score vector z_sem."""
        ...

    def mean(self, c: int, psi: ArrayLike) -> Array:
        """h_c(ψ): ψ (...) → (..., dim)."""
        ...

    def mean_dpsi(self, c: int, psi: ArrayLike) -> Array:
        """dh_c/dψ: ψ (...) → (..., dim). Needed by the semantic factor's Jacobians."""
        ...

    def cov(self, c: int, psi: ArrayLike) -> Array:
        """Σ_c(ψ): ψ (...) → (..., dim, dim)."""
        ...

    def log_likelihood(self, z: ArrayLike, c: int, psi: ArrayLike) -> Array:
        """log N(z; h_c(ψ), Σ_c(ψ)) with all constants: z (dim,) or (..., dim), ψ (...) → (...)."""
        ...


def gaussian_log_likelihood(z: ArrayLike, mean: Array, cov: Array) -> Array:
    """log N(z; mean, cov) for stacks: z (..., d), mean (..., d), cov (..., d, d) → (...)."""
    r = np.asarray(z, dtype=float) - mean
    chol = np.linalg.cholesky(cov)
    white = np.linalg.solve(chol, r[..., None])[..., 0]
    log_det = 2.0 * np.sum(np.log(np.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)
    d = r.shape[-1]
    return np.asarray(-0.5 * np.sum(white * white, axis=-1) - 0.5 * log_det - 0.5 * d * _LOG_2PI)


@dataclass(frozen=True, eq=False)
class AliasedClassifier:
    """M-class model whose scores blur each class with an alias class away from its best view.

    ``h_c(ψ) = s_c(ψ)·e_c + (1 − s_c(ψ))·½(e_c + e_{alias[c]})`` with
    ``s_c(ψ) = ½(1 + cos(ψ − best_view[c]))``: at ψ = best_view[c] the mean score is the one-hot
    e_c; from the opposite side class c looks exactly half like its alias. The covariance is
    constant, ``Σ = (RᵀR)⁻¹`` with ``R = sqrt_info`` (dim × dim, upper triangular).
    The paper's crafted model (design doc §1) is the case M = 2, alias = (1, 0),
    best_view = (π/2, π/2), R = [[1.5, −0.75], [0, 1.5]].

    ``best_view`` is in the model's own ``viewpoint`` convention; every method takes ψ in
    semfleet's (object → camera) and compares it with the best view in that convention
    (``best_view`` + π for a camera → object model).
    """

    alias: tuple[int, ...]
    best_view: tuple[float, ...]
    sqrt_info: Array = field(repr=False)
    viewpoint: str = OBJECT_TO_CAMERA
    _best: Array = field(init=False, repr=False)
    _best_floats: tuple[float, ...] = field(init=False, repr=False)  # for the scalar path
    _log_norm: float = field(init=False, repr=False)
    _blur: Array = field(init=False, repr=False)
    _sharp: Array = field(init=False, repr=False)

    def __post_init__(self) -> None:
        m = len(self.alias)
        if m < 2:
            raise ValueError("an aliased classifier needs at least two classes")
        if len(self.best_view) != m:
            raise ValueError(f"best_view has {len(self.best_view)} entries, expected {m}")
        for c, a in enumerate(self.alias):
            if not 0 <= a < m or a == c:
                raise ValueError(f"alias[{c}] = {a} must be another class in 0..{m - 1}")
        if not all(math.isfinite(b) for b in self.best_view):
            raise ValueError("best_view must be finite")
        # the best views as semfleet's ψ (object → camera) sees them
        best = np.asarray(self.best_view, dtype=float) + view_offset(self.viewpoint)
        best.setflags(write=False)
        object.__setattr__(self, "_best", best)
        object.__setattr__(self, "_best_floats", tuple(float(b) for b in best))
        r = np.array(self.sqrt_info, dtype=float)
        if r.shape != (m, m) or not np.all(np.isfinite(r)):
            raise ValueError(f"sqrt_info must be a finite ({m}, {m}) matrix")
        sign, log_abs_det = np.linalg.slogdet(r)
        if sign == 0 or not np.isfinite(log_abs_det):
            raise ValueError("sqrt_info must be invertible")
        r.setflags(write=False)
        object.__setattr__(self, "sqrt_info", r)
        # log N = −½‖R(z − h)‖² + log|det R| − (M/2) log 2π
        object.__setattr__(self, "_log_norm", float(log_abs_det) - 0.5 * m * _LOG_2PI)
        eye = np.eye(m)
        alias = eye[list(self.alias)]
        object.__setattr__(self, "_blur", 0.5 * (eye + alias))
        object.__setattr__(self, "_sharp", 0.5 * (eye - alias))

    @property
    def num_classes(self) -> int:
        return len(self.alias)

    @property
    def dim(self) -> int:
        return len(self.alias)

    def _check_class(self, c: int) -> None:
        if not 0 <= int(c) < self.num_classes:
            raise ValueError(f"class {c} out of range 0..{self.num_classes - 1}")

    def components(self, c: int) -> tuple[Array, Array, float]:
        """(blur, sharp, best view) of class ``c``: h_c(ψ) = blur + ½(1 + cos(ψ − best))·sharp,
        the best view in semfleet's ψ (object → camera) whatever the model's convention."""
        self._check_class(c)
        return self._blur[c].copy(), self._sharp[c].copy(), float(self._best[c])

    def sharpness(self, c: int, psi: ArrayLike) -> Array:
        """s_c(ψ) ∈ [0, 1]: ψ (...) → (...)."""
        self._check_class(c)
        return 0.5 * (1.0 + np.cos(np.asarray(psi, dtype=float) - self._best[c]))

    def mean(self, c: int, psi: ArrayLike) -> Array:
        # h_c = ½(e_c + e_alias) + s_c(ψ)·½(e_c − e_alias)
        self._check_class(c)
        if isinstance(psi, float | int):  # the scalar path taken inside GTSAM factor callbacks
            s = 0.5 * (1.0 + math.cos(psi - self._best_floats[c]))
            return np.asarray(self._blur[c] + s * self._sharp[c])
        return np.asarray(self._blur[c] + self.sharpness(c, psi)[..., None] * self._sharp[c])

    def mean_dpsi(self, c: int, psi: ArrayLike) -> Array:
        self._check_class(c)
        if isinstance(psi, float | int):
            return np.asarray(-0.5 * math.sin(psi - self._best_floats[c]) * self._sharp[c])
        ds = -0.5 * np.sin(np.asarray(psi, dtype=float) - self._best[c])
        return np.asarray(ds[..., None] * self._sharp[c])

    def cov(self, c: int, psi: ArrayLike) -> Array:
        self._check_class(c)
        info = self.sqrt_info.T @ self.sqrt_info
        shape = (*np.shape(psi), self.dim, self.dim)
        return np.broadcast_to(np.linalg.inv(info), shape).copy()

    def log_likelihood(self, z: ArrayLike, c: int, psi: ArrayLike) -> Array:
        r = np.asarray(z, dtype=float) - self.mean(c, psi)
        white = r @ self.sqrt_info.T
        return np.asarray(-0.5 * np.sum(white * white, axis=-1) + self._log_norm)

    def log_likelihoods(self, z: Array, psi: Array) -> Array:
        """log N(z_d; h_c(ψ), Σ) for every detection and class at once: z (D, dim), ψ (S, D) →
        (S, D, M). With a = R(z − blur_c) and b = R·sharp_c the whitened residual is a − s_c(ψ)·b,
        so ‖·‖² = a·a − 2 s a·b + s² b·b needs only the (S, D, M) sharpness per sample."""
        a = (z[:, None, :] - self._blur[None, :, :]) @ self.sqrt_info.T  # (D, M, dim)
        b = self._sharp @ self.sqrt_info.T  # (M, dim)
        aa = np.einsum("dci,dci->dc", a, a)
        ab = np.einsum("dci,ci->dc", a, b)
        bb = np.einsum("ci,ci->c", b, b)
        s = 0.5 * (1.0 + np.cos(psi[:, :, None] - self._best[None, None, :]))
        return np.asarray(-0.5 * (aa - 2.0 * s * ab + s * s * bb) + self._log_norm)

    @classmethod
    def random(
        cls, num_classes: int, rng: np.random.Generator, noise_std: float = 0.35
    ) -> AliasedClassifier:
        """A random model for generated worlds: a random alias per class, random best views,
        isotropic score noise ``noise_std``."""
        if num_classes < 2:
            raise ValueError("need at least two classes")
        alias = []
        for c in range(num_classes):
            others = [a for a in range(num_classes) if a != c]
            alias.append(int(others[rng.integers(len(others))]))
        best = tuple(float(b) for b in rng.uniform(-np.pi, np.pi, num_classes))
        return cls(tuple(alias), best, np.eye(num_classes) / noise_std)


PAPER_SQRT_INFO = np.array([[1.5, -0.75], [0.0, 1.5]])


def paper_classifier(viewpoint: str = OBJECT_TO_CAMERA) -> AliasedClassifier:
    """The paper's crafted two-class model (design doc §1), in the ``viewpoint`` convention."""
    return AliasedClassifier((1, 0), (math.pi / 2, math.pi / 2), PAPER_SQRT_INFO, viewpoint)


def all_log_likelihoods(model: ClassifierModel, z: Array, psi: Array) -> Array:
    """log P(z_d | c, ψ_sd) for every sample, detection and class: z (D, dim), ψ (S, D) →
    (S, D, M); vectorised over classes where the model offers it (``log_likelihoods``)."""
    if isinstance(model, AliasedClassifier):
        return model.log_likelihoods(z, psi)
    out = np.empty((*psi.shape, model.num_classes))
    for d in range(psi.shape[1]):
        for c in range(model.num_classes):
            out[:, d, c] = model.log_likelihood(z[d], c, psi[:, d])
    return out


@dataclass(frozen=True)
class FirstComponents:
    """The marginal of a model over the first M−1 score components.

    Real classifier outputs lie on the probability simplex, so their last component is determined by
    the others and a full-dimensional Gaussian would be degenerate; the marginal of the first M−1
    components is exact for a Gaussian model.
    """

    model: ClassifierModel

    @property
    def num_classes(self) -> int:
        return self.model.num_classes

    @property
    def dim(self) -> int:
        return self.model.dim - 1

    def mean(self, c: int, psi: ArrayLike) -> Array:
        return self.model.mean(c, psi)[..., :-1]

    def mean_dpsi(self, c: int, psi: ArrayLike) -> Array:
        return self.model.mean_dpsi(c, psi)[..., :-1]

    def cov(self, c: int, psi: ArrayLike) -> Array:
        return self.model.cov(c, psi)[..., :-1, :-1]

    def log_likelihood(self, z: ArrayLike, c: int, psi: ArrayLike) -> Array:
        return gaussian_log_likelihood(z, self.mean(c, psi), self.cov(c, psi))
