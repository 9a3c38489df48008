"""χ² quantiles for the gates, from ``scipy.special`` — the functions ``scipy.stats.chi2``'s
``ppf`` and ``isf`` call, so the values are the same to the bit (tests/estimator/test_chi2.py).

``scipy.stats`` takes about half of an agent's start-up imports (≈ 0.6 s of CPU on this machine,
every agent process; issue 47): fifty agents starting on two cores spent half a minute on it.
"""

from __future__ import annotations

from scipy.special import chdtri, gammaincinv


def chi2_ppf(q: float, dof: int) -> float:
    """The ``q``-quantile of χ² with ``dof`` degrees of freedom (``scipy.stats.chi2.ppf``)."""
    return float(2.0 * gammaincinv(dof / 2.0, q))


def chi2_isf(p: float, dof: int) -> float:
    """The value χ² with ``dof`` degrees of freedom exceeds with probability ``p``
    (``scipy.stats.chi2.isf``)."""
    return float(chdtri(dof, p))
