"""Fit a :class:`~estimator.models.learned.LearnedClassifier` to score samples (docs/models.md).

Per class c and score component i, scikit-learn's Gaussian-process regression chooses the
hyperparameters of ``a² κ_ℓ(ψ − ψ') + σ² δ`` (periodic kernel, period 2π; maximum marginal
likelihood) for the scores about their mean; the posterior mean is then written on a grid of
inducing viewpoints (numpy, :meth:`PeriodicGP.regression`). The residual covariance comes from
leave-one-out residuals ``r_n`` (exact for a GP, and not shrunk by the fit itself):
``Σ_c(ψ) = exp(s_c(ψ)) S_c`` with ``s_c`` a GP on ``log(r_nᵀ S_c⁻¹ r_n / dim)`` corrected by
the mean of a log χ²/dim variable, then ``S_c`` re-estimated given ``s_c``. scikit-learn is
imported by :func:`fit_classifier` only; the model it returns needs numpy alone.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.special import digamma

from deploy.base.errors import UsageError
from deploy.study.classifier_samples import ScoreSamples
from estimator.chi2 import chi2_ppf
from estimator.models import ClassifierModel
from estimator.models.learned import LearnedClassifier, PeriodicGP, periodic_kernel

Array = NDArray[np.float64]

MIN_PER_CLASS = 10
# Hyperparameters and leave-one-out residuals cost O(n³): beyond this many samples of a class
# they use a seeded random subset; the posterior means use every sample (O(n G²)).
MAX_GP_SAMPLES = 1500
LENGTH_SCALE_BOUNDS = (0.3, 20.0)  # rad; the lower bound keeps the inducing grid small
_GRID_PER_LENGTH = 3.0  # inducing points per length scale
_GRID_LIMITS = (16, 128)


@dataclass(frozen=True)
class ComponentFit:
    """The GP of one score component: length scale ℓ [rad], signal std a, noise std σ, and the
    RMS of the leave-one-out residuals."""

    length_scale: float
    amplitude: float
    noise_std: float
    loo_rmse: float


@dataclass(frozen=True)
class ClassFit:
    """How one class was fitted: ``count`` samples; per component its :class:`ComponentFit`;
    the range of the covariance scale exp(s_c(ψ)) over ψ; the mean leave-one-out log-likelihood
    per sample; the share of leave-one-out residuals inside the model's 95 % ellipse."""

    count: int
    components: tuple[ComponentFit, ...]
    scale_range: tuple[float, float]
    loo_log_likelihood: float
    coverage95: float


@dataclass(frozen=True)
class Fit:
    model: LearnedClassifier
    classes: tuple[ClassFit, ...]


def fit_classifier(samples: ScoreSamples, seed: int = 0) -> Fit:
    """The learned model of ``samples`` and how well it fits; deterministic for a ``seed``."""
    regressor = _gaussian_process_regressor()
    m = samples.num_classes
    for c in range(m):
        count = int(np.sum(samples.classes == c))
        if count < MIN_PER_CLASS:
            raise UsageError(f"class {c + 1} has {count} samples, at least {MIN_PER_CLASS} needed")
    rng = np.random.default_rng(seed)
    gps = [_ClassGP.fit(*samples.of_class(c), regressor, rng, seed) for c in range(m)]
    mean_grid = _grid(min(min(g.lengths) for g in gps))
    scale_grid = _grid(min(g.scale_hyper[0] for g in gps))
    means, scales, covs, fits = [], [], [], []
    for g in gps:
        means.append(g.mean(mean_grid))
        log_scale = g.log_scale(scale_grid)
        scale = np.exp(log_scale(g.psi[g.idx])[:, 0])
        cov = (g.resid / scale[:, None]).T @ g.resid / len(g.resid)  # S_c given s_c
        cov = 0.5 * (cov + cov.T)
        scales.append(log_scale)
        covs.append(cov)
        fits.append(_quality(g, log_scale, cov))
    model = LearnedClassifier(tuple(means), tuple(scales), np.stack(covs))
    return Fit(LearnedClassifier.from_arrays(model.to_arrays()), tuple(fits))


@dataclass(frozen=True)
class _ClassGP:
    """One class's samples (ψ (n,), z (n, dim)), the subset ``idx`` its hyperparameters and
    leave-one-out residuals ``resid`` (len(idx), dim) use, and the hyperparameters: per
    component (ℓ, a, σ, offset); for the log scale (ℓ, a, σ), its offset and targets."""

    psi: Array
    z: Array
    idx: NDArray[np.int64]
    resid: Array
    lengths: tuple[float, ...]
    amps: tuple[float, ...]
    noises: tuple[float, ...]
    offsets: tuple[float, ...]
    scale_hyper: tuple[float, float, float]
    scale_offset: float
    log_q: Array

    @classmethod
    def fit(
        cls, psi: Array, z: Array, regressor: Any, rng: np.random.Generator, seed: int
    ) -> _ClassGP:
        n, dim = z.shape
        idx = np.sort(rng.choice(n, MAX_GP_SAMPLES, replace=False)) if n > MAX_GP_SAMPLES else None
        idx = np.arange(n) if idx is None else idx
        hyper, offsets = [], []
        resid = np.empty((len(idx), dim))
        for i in range(dim):
            offset = float(np.mean(z[:, i]))
            y = z[idx, i] - offset
            length, amp, noise = _hyperparameters(regressor, psi[idx], y, seed)
            resid[:, i] = _loo_residuals(psi[idx], y, length, amp, noise)
            hyper.append((length, amp, noise))
            offsets.append(offset)
        log_q = _log_scale_targets(resid)
        s_off = float(np.mean(log_q))
        scale_hyper = _hyperparameters(regressor, psi[idx], log_q - s_off, seed)
        lengths, amps, noises = (tuple(h) for h in zip(*hyper, strict=True))
        return cls(
            psi, z, idx, resid, lengths, amps, noises, tuple(offsets), scale_hyper, s_off, log_q
        )

    def mean(self, grid: Array) -> PeriodicGP:
        """h_c on the inducing ``grid``: every sample's posterior mean, one per component."""
        weights = [
            PeriodicGP.regression(self.psi, self.z[:, i], grid, ln, a, s * s, o).weights
            for i, (ln, a, s, o) in enumerate(
                zip(self.lengths, self.amps, self.noises, self.offsets, strict=True)
            )
        ]
        return PeriodicGP(
            grid, np.concatenate(weights), np.array(self.lengths), np.array(self.offsets)
        )

    def log_scale(self, grid: Array) -> PeriodicGP:
        length, amp, noise = self.scale_hyper
        x = self.psi[self.idx]
        return PeriodicGP.regression(x, self.log_q, grid, length, amp, noise**2, self.scale_offset)


def _gaussian_process_regressor() -> Any:
    try:
        from sklearn.gaussian_process import GaussianProcessRegressor
    except ImportError:
        raise UsageError(
            "classifier fit needs scikit-learn: pip install 'semfleet[learn]'"
        ) from None
    return GaussianProcessRegressor


def _hyperparameters(regressor: Any, x: Array, y: Array, seed: int) -> tuple[float, float, float]:
    """(ℓ, a, σ) of ``a² κ_ℓ + σ² δ`` maximising the marginal likelihood of ``y`` (n,)."""
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.gaussian_process.kernels import ConstantKernel, ExpSineSquared, WhiteKernel

    spread = max(float(np.var(y)), 1e-12)
    kernel = ConstantKernel(spread, (1e-6 * spread, 1e3 * spread)) * ExpSineSquared(
        1.0, 2.0 * math.pi, LENGTH_SCALE_BOUNDS, "fixed"
    ) + WhiteKernel(0.5 * spread, (1e-8 * spread, 1e2 * spread))
    gp = regressor(kernel=kernel, normalize_y=False, n_restarts_optimizer=2, random_state=seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)  # a bound reached is reported, fine
        gp.fit(x[:, None], y)
    k = gp.kernel_
    return (
        float(k.k1.k2.length_scale),
        math.sqrt(float(k.k1.k1.constant_value)),
        math.sqrt(float(k.k2.noise_level)),
    )


def _loo_residuals(x: Array, y: Array, length: float, amp: float, noise: float) -> Array:
    """Leave-one-out residuals of the exact GP: r_n = [Q y]_n / Q_nn, Q = (K + σ²I)⁻¹."""
    k = amp * amp * periodic_kernel(x[:, None] - x[None, :], length) + noise * noise * np.eye(
        len(x)
    )
    q = np.linalg.inv(k)
    return np.asarray(q @ y / np.diag(q))


def _log_scale_targets(resid: Array) -> Array:
    """log(rᵀS⁻¹r / dim) − E[log χ²_dim / dim] with S = mean r rᵀ: unbiased for s(ψ) when
    r ~ N(0, e^s S)."""
    n, dim = resid.shape
    s = resid.T @ resid / n
    q = np.einsum("ni,ij,nj->n", resid, np.linalg.inv(s), resid) / dim
    bias = float(digamma(dim / 2.0)) + math.log(2.0 / dim)
    return np.asarray(np.log(np.maximum(q, 1e-12)) - bias)


def _grid(length_scale: float) -> Array:
    lo, hi = _GRID_LIMITS
    g = int(min(hi, max(lo, math.ceil(_GRID_PER_LENGTH * 2.0 * math.pi / length_scale))))
    return np.asarray(-math.pi + 2.0 * math.pi * np.arange(g) / g)


def _quality(g: _ClassGP, log_scale: PeriodicGP, cov: Array) -> ClassFit:
    psi, resid = g.psi[g.idx], g.resid
    dim = resid.shape[1]
    rmse = np.sqrt(np.mean(resid * resid, axis=0))
    comps = tuple(
        ComponentFit(g.lengths[i], g.amps[i], g.noises[i], float(rmse[i])) for i in range(dim)
    )
    over_psi = np.exp(log_scale(np.linspace(-math.pi, math.pi, 361))[:, 0])
    scale = np.exp(log_scale(psi)[:, 0])
    maha = np.einsum("ni,ij,nj->n", resid, np.linalg.inv(cov), resid) / scale
    _, logdet = np.linalg.slogdet(cov)
    log_lik = -0.5 * (maha + dim * np.log(scale) + logdet + dim * math.log(2.0 * math.pi))
    return ClassFit(
        len(g.psi),
        comps,
        (float(over_psi.min()), float(over_psi.max())),
        float(np.mean(log_lik)),
        float(np.mean(maha <= chi2_ppf(0.95, dim))),
    )


@dataclass(frozen=True)
class TruthGap:
    """How far a learned model is from the model that generated its samples, over ψ: the largest
    |h_c − h_c^true| (any component), and the mean and largest KL(true ‖ learned) [nats]."""

    max_mean_error: float
    mean_kl: float
    max_kl: float


def truth_gap(model: ClassifierModel, truth: ClassifierModel, points: int = 360) -> list[TruthGap]:
    """Per class, the :class:`TruthGap` of ``model`` against ``truth`` on ``points`` viewpoints."""
    psi = -math.pi + 2.0 * math.pi * np.arange(points) / points
    gaps = []
    for c in range(truth.num_classes):
        mu0, s0 = truth.mean(c, psi), truth.cov(c, psi)
        mu1, s1 = model.mean(c, psi), model.cov(c, psi)
        inv1 = np.linalg.inv(s1)
        d = mu1 - mu0
        kl = 0.5 * (
            np.einsum("nij,nji->n", inv1, s0)
            + np.einsum("ni,nij,nj->n", d, inv1, d)
            - truth.dim
            + np.linalg.slogdet(s1)[1]
            - np.linalg.slogdet(s0)[1]
        )
        gaps.append(TruthGap(float(np.abs(d).max()), float(kl.mean()), float(kl.max())))
    return gaps
