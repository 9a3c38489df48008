"""A classifier model learned from detector scores: Eq. 1's ``h_c(ψ)``, ``Σ_c(ψ)`` by GP regression.

Every function of ψ here is the posterior mean of a Gaussian process with the periodic kernel
``k(ψ, ψ') = a² κ_ℓ(ψ − ψ')``, ``κ_ℓ(d) = exp(−2 sin²(d/2) / ℓ²)`` (period 2π), written on a
grid of inducing viewpoints ``g_1..g_G``: ``f(ψ) = offset + Σ_j w_j κ_ℓ(ψ − g_j)``
(:class:`PeriodicGP`). Per class c:

- ``h_c(ψ)``: one such function per score component (its own ℓ);
- ``Σ_c(ψ) = exp(s_c(ψ)) · S_c``: a constant residual covariance ``S_c`` (dim × dim, the
  correlations between components) scaled by ``exp`` of a GP ``s_c`` on log residual variances.

The fit (scikit-learn, ``deploy.study.classifier_fit``) only chooses the numbers; evaluating them is
numpy. :meth:`LearnedClassifier.from_arrays` validates the arrays of a model file and names the
field at fault; nothing else may escape it.

Over 300 lines for a reason: the model and the validation of its file are one contract (every
field :meth:`LearnedClassifier.to_arrays` writes is checked by ``_parse``, in the same words),
and a model file is untrusted input; split, a field could be written that nothing checks.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from estimator.models.classifier import OBJECT_TO_CAMERA, VIEWPOINTS, check_viewpoint, view_offset

Array = NDArray[np.float64]

FORMAT_NAME = "semfleet-learned-classifier"
FORMAT_VERSION = 1
MAX_CLASSES = 64
MAX_INDUCING = 1024
MIN_LENGTH_SCALE, MAX_LENGTH_SCALE = 1e-3, 1e3
# |s_c(ψ)| ≤ |offset| + Σ|w| is bounded so exp(s_c) and Σ_c(ψ) stay finite and positive definite.
MAX_LOG_SCALE = 30.0
_LOG_2PI = math.log(2.0 * math.pi)


class LearnedModelError(ValueError):
    """The arrays of a learned model are invalid; ``field`` names the one at fault."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field}: {reason}")
        self.field = field
        self.reason = reason


def periodic_kernel(d: ArrayLike, length_scale: ArrayLike) -> Array:
    """κ_ℓ(d) = exp(−2 sin²(d/2)/ℓ²) = exp((cos d − 1)/ℓ²), broadcast over ``d`` and ``ℓ``."""
    return np.asarray(np.exp((np.cos(d) - 1.0) / np.square(length_scale)))


@dataclass(frozen=True, eq=False)
class PeriodicGP:
    """K functions of ψ sharing inducing viewpoints: ``f_k(ψ) = offset_k + Σ_j w_kj κ_ℓk(ψ − g_j)``.

    ``inducing`` (G,), ``weights`` (K, G), ``length_scale`` (K,), ``offset`` (K,).
    """

    inducing: Array
    weights: Array
    length_scale: Array
    offset: Array

    def _kernel(self, psi: ArrayLike) -> tuple[Array, Array]:
        """κ (..., K, G) and ψ − g (..., 1, G)."""
        d = np.asarray(psi, dtype=float)[..., None, None] - self.inducing
        return periodic_kernel(d, self.length_scale[:, None]), d

    def __call__(self, psi: ArrayLike) -> Array:
        """f(ψ): ψ (...) → (..., K)."""
        kappa, _ = self._kernel(psi)
        return np.asarray(np.einsum("...kg,kg->...k", kappa, self.weights) + self.offset)

    def dpsi(self, psi: ArrayLike) -> Array:
        """df/dψ: ψ (...) → (..., K); dκ_ℓ(d)/dd = −sin(d)/ℓ² · κ_ℓ(d)."""
        kappa, d = self._kernel(psi)
        slope = kappa * np.sin(d)
        inv_l2 = 1.0 / np.square(self.length_scale)
        return np.asarray(-np.einsum("...kg,kg->...k", slope, self.weights) * inv_l2)

    @classmethod
    def regression(
        cls,
        inputs: ArrayLike,
        targets: ArrayLike,
        inducing: ArrayLike,
        length_scale: float,
        amplitude: float,
        noise_var: float,
        offset: float,
    ) -> PeriodicGP:
        """The posterior mean of a GP (kernel ``amplitude² κ_ℓ``, white noise ``noise_var``,
        prior mean ``offset``) given ``targets`` (N,) at ``inputs`` (N,), projected on the
        ``inducing`` grid (G,) — the subset-of-regressors (DTC) mean
        ``f(ψ) = offset + k_ψG (σ² K_GG + K_GN K_NG)⁻¹ K_GN (y − offset)``; one function."""
        x = np.asarray(inputs, dtype=float)
        y = np.asarray(targets, dtype=float) - offset
        g = np.asarray(inducing, dtype=float)
        a2 = amplitude * amplitude
        k_gg = a2 * periodic_kernel(g[:, None] - g[None, :], length_scale)
        k_gn = a2 * periodic_kernel(g[:, None] - x[None, :], length_scale)
        b = noise_var * k_gg + k_gn @ k_gn.T
        b += 1e-10 * np.trace(b) / len(g) * np.eye(len(g))  # jitter: the grid can be redundant
        w = np.asarray(a2 * np.linalg.solve(b, k_gn @ y), dtype=float)
        return cls(g.copy(), w[None, :], np.array([length_scale]), np.array([offset]))


@dataclass(frozen=True, eq=False)
class LearnedClassifier:
    """``h_c(ψ) = means[c](ψ)`` (dim functions), ``Σ_c(ψ) = exp(log_scales[c](ψ))·noise_cov[c]``.

    ``means``: M :class:`PeriodicGP` of K = dim; ``log_scales``: M of K = 1; ``noise_cov``
    (M, dim, dim) symmetric positive definite. Build it with :meth:`from_arrays` to validate.
    ``viewpoint``: the convention of the ψ it was learned at (the samples'); every method takes
    semfleet's ψ (object → camera) and evaluates a camera → object model at ψ + π.
    """

    means: tuple[PeriodicGP, ...]
    log_scales: tuple[PeriodicGP, ...]
    noise_cov: Array
    viewpoint: str = OBJECT_TO_CAMERA
    _inv_chol: Array = field(init=False, repr=False)
    _log_det: Array = field(init=False, repr=False)

    def __post_init__(self) -> None:
        check_viewpoint(self.viewpoint)
        chol = np.linalg.cholesky(self.noise_cov)  # (M, dim, dim), S_c = L Lᵀ
        object.__setattr__(self, "_inv_chol", np.linalg.inv(chol))
        log_det = 2.0 * np.sum(np.log(np.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)
        object.__setattr__(self, "_log_det", log_det)

    @property
    def num_classes(self) -> int:
        return len(self.means)

    @property
    def dim(self) -> int:
        return int(self.noise_cov.shape[-1])

    def _check_class(self, c: int) -> int:
        if not 0 <= int(c) < self.num_classes:
            raise ValueError(f"class {c} out of range 0..{self.num_classes - 1}")
        return int(c)

    def _own(self, psi: ArrayLike) -> ArrayLike:
        """semfleet's ψ in the model's own convention."""
        offset = view_offset(self.viewpoint)
        return psi if offset == 0.0 else np.asarray(psi, dtype=float) + offset

    def mean(self, c: int, psi: ArrayLike) -> Array:
        return self.means[self._check_class(c)](self._own(psi))

    def mean_dpsi(self, c: int, psi: ArrayLike) -> Array:
        return self.means[self._check_class(c)].dpsi(self._own(psi))

    def scale(self, c: int, psi: ArrayLike) -> Array:
        """exp(s_c(ψ)), the factor of ``S_c`` in Σ_c(ψ): ψ (...) → (...)."""
        return np.asarray(np.exp(self.log_scales[self._check_class(c)](self._own(psi))[..., 0]))

    def cov(self, c: int, psi: ArrayLike) -> Array:
        return np.asarray(self.scale(c, psi)[..., None, None] * self.noise_cov[c])

    def log_likelihood(self, z: ArrayLike, c: int, psi: ArrayLike) -> Array:
        # Σ = e^s S, S = L Lᵀ: log N = −½ e^{−s} ‖L⁻¹ r‖² − (dim/2) s − ½ log det S − (dim/2) log 2π
        c = self._check_class(c)
        white = (np.asarray(z, dtype=float) - self.mean(c, psi)) @ self._inv_chol[c].T
        quad = np.sum(white * white, axis=-1)
        s = self.log_scales[c](self._own(psi))[..., 0]
        log_det, d = float(self._log_det[c]), self.dim
        return np.asarray(-0.5 * np.exp(-s) * quad - 0.5 * d * s - 0.5 * (log_det + d * _LOG_2PI))

    def to_arrays(self) -> dict[str, Array]:
        """The arrays of a model file (format :data:`FORMAT_VERSION`); :meth:`from_arrays` reads
        them back into an equal model."""
        return {
            "format": np.array(FORMAT_NAME),
            "version": np.array(FORMAT_VERSION),
            "mean_inducing": np.stack([gp.inducing for gp in self.means]),
            "mean_weights": np.stack([gp.weights for gp in self.means]),
            "mean_length_scale": np.stack([gp.length_scale for gp in self.means]),
            "mean_offset": np.stack([gp.offset for gp in self.means]),
            "noise_cov": np.array(self.noise_cov),
            "scale_inducing": np.stack([gp.inducing for gp in self.log_scales]),
            "scale_weights": np.stack([gp.weights[0] for gp in self.log_scales]),
            "scale_length_scale": np.array([gp.length_scale[0] for gp in self.log_scales]),
            "scale_offset": np.array([gp.offset[0] for gp in self.log_scales]),
            "viewpoint": np.array(self.viewpoint),
        }

    @classmethod
    def from_arrays(cls, arrays: Mapping[str, Any]) -> LearnedClassifier:
        """Validate the arrays of a model file; :class:`LearnedModelError` naming the field."""
        return _parse(arrays)


_FIELDS = (
    "format",
    "version",
    "mean_inducing",
    "mean_weights",
    "mean_length_scale",
    "mean_offset",
    "noise_cov",
    "scale_inducing",
    "scale_weights",
    "scale_length_scale",
    "scale_offset",
)
# Optional: a file without it was learned at object → camera ψ (files before the field).
_OPTIONAL = ("viewpoint",)


def _parse(arrays: Mapping[str, Any]) -> LearnedClassifier:
    missing = [f for f in _FIELDS if f not in arrays]
    if missing:
        raise LearnedModelError(missing[0], "missing (not a learned classifier model file?)")
    unknown = sorted(set(arrays) - set(_FIELDS) - set(_OPTIONAL))
    if unknown:
        allowed = ", ".join((*_FIELDS, *_OPTIONAL))
        raise LearnedModelError(unknown[0], f"unknown field (allowed: {allowed})")
    fmt = np.asarray(arrays["format"])
    if fmt.shape != () or fmt.dtype.kind != "U" or str(fmt) != FORMAT_NAME:
        raise LearnedModelError("format", f"expected the string {FORMAT_NAME!r}")
    version = np.asarray(arrays["version"])
    if version.shape != () or version.dtype.kind not in "iu":
        raise LearnedModelError("version", "expected one integer")
    if int(version) != FORMAT_VERSION:
        raise LearnedModelError(
            "version", f"unsupported version {int(version)} (this semfleet reads {FORMAT_VERSION})"
        )
    inducing = _inducing(arrays, "mean_inducing", None)
    m, g = inducing.shape
    weights = _floats(arrays, "mean_weights", 3)
    dim = weights.shape[1]
    _shape(weights, "mean_weights", (m, dim, g))
    if dim != m:
        raise LearnedModelError("mean_weights", f"scores of {dim} components for {m} classes")
    length = _length_scales(arrays, "mean_length_scale", (m, dim))
    offset = _floats(arrays, "mean_offset", 2, (m, dim))
    noise = _floats(arrays, "noise_cov", 3, (m, dim, dim))
    for c in range(m):
        _check_covariance(noise[c], f"noise_cov[{c}]")
    s_inducing = _inducing(arrays, "scale_inducing", m)
    gs = s_inducing.shape[1]
    s_weights = _floats(arrays, "scale_weights", 2, (m, gs))
    s_length = _length_scales(arrays, "scale_length_scale", (m,))
    s_offset = _floats(arrays, "scale_offset", 1, (m,))
    bound = np.abs(s_offset) + np.sum(np.abs(s_weights), axis=1)
    if np.any(bound > MAX_LOG_SCALE):
        c = int(np.argmax(bound))
        raise LearnedModelError(
            "scale_weights",
            f"class {c + 1}: |scale_offset| + Σ|scale_weights| = {bound[c]:.3g}, beyond ±30",
        )
    means = tuple(PeriodicGP(inducing[c], weights[c], length[c], offset[c]) for c in range(m))
    scales = tuple(
        PeriodicGP(s_inducing[c], s_weights[c][None, :], s_length[c : c + 1], s_offset[c : c + 1])
        for c in range(m)
    )
    return LearnedClassifier(means, scales, noise, _viewpoint(arrays))


def _viewpoint(arrays: Mapping[str, Any]) -> str:
    if "viewpoint" not in arrays:
        return OBJECT_TO_CAMERA
    v = np.asarray(arrays["viewpoint"])
    if v.shape != () or v.dtype.kind != "U" or str(v) not in VIEWPOINTS:
        raise LearnedModelError("viewpoint", f"expected one of the strings {', '.join(VIEWPOINTS)}")
    return str(v)


def _inducing(arrays: Mapping[str, Any], name: str, m: int | None) -> Array:
    """(M, G) inducing viewpoints; ``m`` None: this field fixes M."""
    a = _floats(arrays, name, 2)
    classes, g = a.shape
    if m is None and not 2 <= classes <= MAX_CLASSES:
        raise LearnedModelError(name, f"{classes} classes, expected 2..{MAX_CLASSES}")
    if m is not None and classes != m:
        raise LearnedModelError(name, f"{classes} classes, the model has {m}")
    if not 1 <= g <= MAX_INDUCING:
        raise LearnedModelError(name, f"{g} inducing points, expected 1..{MAX_INDUCING}")
    return a


def _length_scales(arrays: Mapping[str, Any], name: str, shape: tuple[int, ...]) -> Array:
    a = _floats(arrays, name, len(shape), shape)
    if not np.all((a >= MIN_LENGTH_SCALE) & (a <= MAX_LENGTH_SCALE)):
        bounds = f"{MIN_LENGTH_SCALE:g}..{MAX_LENGTH_SCALE:g}"
        raise LearnedModelError(name, f"every length scale must be in {bounds} rad")
    return a


def _floats(
    arrays: Mapping[str, Any], name: str, ndim: int, shape: tuple[int, ...] | None = None
) -> Array:
    raw = np.asarray(arrays[name])
    if raw.dtype.kind not in "fiu":
        raise LearnedModelError(name, f"expected numbers, got dtype {raw.dtype}")
    if raw.ndim != ndim:
        raise LearnedModelError(name, f"expected {ndim} dimensions, got shape {raw.shape}")
    if shape is not None:
        _shape(raw, name, shape)
    a = raw.astype(float)
    if not np.all(np.isfinite(a)):
        raise LearnedModelError(name, "contains a NaN or an infinity")
    a.setflags(write=False)
    return a


def _shape(a: Array, name: str, shape: tuple[int, ...]) -> None:
    if a.shape != shape:
        raise LearnedModelError(name, f"expected shape {shape}, got {a.shape}")


def _check_covariance(s: Array, name: str) -> None:
    if not np.allclose(s, s.T, rtol=1e-9, atol=1e-12):
        raise LearnedModelError(name, "not symmetric")
    eig = np.linalg.eigvalsh(s)
    if not eig[0] > 1e-12 * eig[-1] > 0:
        raise LearnedModelError(name, "not positive definite (or conditioned worse than 1e12)")
