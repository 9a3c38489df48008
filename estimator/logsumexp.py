"""log Σ exp(a) along an axis, as ``scipy.special.logsumexp`` computes it for real arrays.

SciPy's function goes through its array-API layer, which costs about 0.5 ms a call whatever the
size: a belief's step calls it a few hundred times (weights of every hypothesis' children). This
is the same computation in plain numpy — the same operations in the same order, so the results
are SciPy's to the bit (tests/estimator/test_logsumexp.py compares them): the largest element of
each slice is taken out of the sum for precision (log1p of the rest over the count of maxima,
plus the log of that count and the maximum). One exp over the array, where SciPy takes two (its
fallback to the direct sum, which cannot change a result: see below): 2.6–3.5× faster than the
line-by-line copy of SciPy's steps it replaced, on the shapes of a belief's step.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def logsumexp(a: ArrayLike, axis: int | None = None) -> Array | np.float64:
    """log Σ exp(a) over ``axis`` (all of ``a`` when None), real floating input."""
    x = np.atleast_1d(np.asarray(a, dtype=float))
    axes = tuple(range(x.ndim)) if axis is None else axis
    if x.size == 0:
        shape = np.asarray(x.shape)
        shape[axes] = 1
        out = np.full(tuple(shape), -np.inf)
    else:
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            top = np.max(x, axis=axes, keepdims=True)
            at_top = x == top
            # exp(a − max) with the maxima left out (SciPy's ``where(at_top, −inf, a) − max``,
            # whose exp is 0 there): one exp over the array, in place.
            e = np.subtract(x, top)
            np.exp(e, out=e)
            np.copyto(e, 0.0, where=at_top)
            count = np.sum(at_top, axis=axes, keepdims=True, dtype=x.dtype)
            s = np.sum(e, axis=axes, keepdims=True, dtype=x.dtype)
            # SciPy's sign handling (s < −1, a negative sign) cannot arise for real input
            # (s ≥ 0 or NaN), nor can its fallback to the direct log Σ exp(a) change a result:
            # its result is not finite only when the maximum is ±inf or NaN, and then the direct
            # sum is the same ±inf or NaN (the edge cases of tests/estimator/test_logsumexp.py).
            s = np.where(s == 0, s, s / count)
            out = np.log1p(s) + np.log(count) + top
    out = np.squeeze(out, axis=axes)
    return out[()] if out.ndim == 0 else out
