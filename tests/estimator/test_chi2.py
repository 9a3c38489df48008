"""The gates' χ² quantiles equal scipy.stats.chi2's to the bit (estimator/chi2.py)."""

from __future__ import annotations

import pytest
from scipy.stats import chi2

from estimator.chi2 import chi2_isf, chi2_ppf

ALPHAS = (0.5, 0.1, 0.05, 0.02, 0.01, 0.0027, 1e-3, 1e-4, 1e-6, 1e-9)


@pytest.mark.parametrize("dof", [1, 2, 3, 4, 6, 9, 13, 24, 39])
def test_quantiles_are_scipy_stats_own(dof: int) -> None:
    for alpha in ALPHAS:
        assert chi2_ppf(1.0 - alpha, dof) == float(chi2.ppf(1.0 - alpha, dof))
        assert chi2_isf(alpha, dof) == float(chi2.isf(alpha, dof))
    # and they are quantiles: ppf and isf of complementary levels agree, growing with the level
    assert chi2_ppf(0.99, dof) == pytest.approx(chi2_isf(0.01, dof), rel=1e-12)
    assert chi2_ppf(0.5, dof) < chi2_ppf(0.9, dof) < chi2_ppf(0.999, dof)


def test_an_agent_never_imports_scipy_stats() -> None:
    import subprocess
    import sys

    code = "import sys, deploy.cli.main, agents.runtime; print('scipy.stats' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
