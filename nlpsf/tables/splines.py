"""Piecewise cubics: coefficients computed with scipy when a table is written, evaluated with numpy.

The slopes are interpolated with scipy's not-a-knot ``CubicSpline`` of slope / flux in flux.
Building it needs scipy (0.5 s to import); evaluating it is a piecewise cubic. So the coefficients
are computed with scipy when a table is written (``storage.write_companion``) and evaluated here,
which keeps ``nlpsf solve`` and the service's start free of scipy and astropy. The tests check this
evaluation against scipy's on every shipped table.
"""

from __future__ import annotations

import numpy as np


def spline_coefficients(flux: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Coefficients (4, n - 1) of scipy's CubicSpline of values / flux in flux (flux ascending)."""
    from scipy.interpolate import CubicSpline

    return np.asarray(CubicSpline(flux, values / flux).c, dtype=np.float64)


def evaluate_cubic(breaks: np.ndarray, coefficients: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Evaluate a piecewise cubic (scipy's PPoly layout: highest power first) at ``x``."""
    index = np.clip(np.searchsorted(breaks, x, side="right") - 1, 0, breaks.size - 2)
    d = x - breaks[index]
    c = coefficients[:, index]
    return ((c[0] * d + c[1]) * d + c[2]) * d + c[3]
