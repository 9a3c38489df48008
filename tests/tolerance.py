"""The one numeric tolerance helper every test uses."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

# Default tolerances for float64 maths that should agree to rounding error.
RTOL = 1e-9
ATOL = 1e-9


def assert_close(
    actual: ArrayLike, expected: ArrayLike, rtol: float = RTOL, atol: float = ATOL, what: str = ""
) -> None:
    """``numpy.testing.assert_allclose`` with the project's defaults and a label in the message."""
    np.testing.assert_allclose(
        np.asarray(actual, dtype=float),
        np.asarray(expected, dtype=float),
        rtol=rtol,
        atol=atol,
        err_msg=what,
    )


def assert_angles_close(
    actual: ArrayLike, expected: ArrayLike, atol: float = ATOL, what: str = ""
) -> None:
    """Angles agree modulo 2π."""
    diff = (np.asarray(actual, float) - np.asarray(expected, float) + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(diff, 0.0, atol=atol, err_msg=what)
