"""Piecewise cubics: knot derivatives solved with scipy when a table is written, the cubics built
and evaluated with numpy.

The slopes are interpolated with scipy's not-a-knot ``CubicSpline`` of slope / flux in flux. That
spline is a cubic Hermite interpolant: once its derivatives at the knots are known (one banded
solve, scipy/LAPACK), its coefficients are four elementwise numpy expressions of them and the data
(scipy's own ``CubicHermiteSpline``, repeated in :func:`hermite_coefficients`). So a table file
stores the knot derivatives (``knot_derivatives``, at write time, checked bit for bit against
scipy's coefficients there) -- a quarter of what the coefficients took -- and ``nlpsf solve`` and
the service build the coefficients without scipy or astropy. The tests check the evaluation
against scipy's on the shipped tables.
"""

from __future__ import annotations

import numpy as np


def knot_derivatives(flux: np.ndarray, values: np.ndarray) -> np.ndarray:
    """d(values / flux)/d flux at each knot of scipy's not-a-knot CubicSpline (flux ascending).

    Taken from the spline scipy builds (the derivatives it hands to ``CubicHermiteSpline``), and
    checked: :func:`hermite_coefficients` of them must equal that spline's coefficients bit for bit."""
    from scipy.interpolate import CubicHermiteSpline, CubicSpline

    seen: dict[str, np.ndarray] = {}

    class _Hermite(CubicHermiteSpline):
        def __init__(self, x, y, dydx, axis=0, extrapolate=None):
            seen["dydx"] = np.array(dydx, dtype=np.float64)
            super().__init__(x, y, dydx, axis=axis, extrapolate=extrapolate)

    class _Spline(CubicSpline, _Hermite):  # CubicSpline's super().__init__ reaches _Hermite first
        pass

    spline = _Spline(flux, values / flux)
    derivatives = seen["dydx"]
    if not np.array_equal(hermite_coefficients(flux, values, derivatives), spline.c):
        raise ArithmeticError("the cubic's coefficients from its knot derivatives differ from scipy's")
    return derivatives


def hermite_coefficients(flux: np.ndarray, values: np.ndarray, derivatives: np.ndarray) -> np.ndarray:
    """Coefficients (4, n - 1) of the cubic Hermite interpolant of values / flux in flux with these
    knot derivatives: scipy's ``CubicHermiteSpline`` arithmetic, operation for operation, so the
    result is bit for bit scipy's ``CubicSpline(flux, values / flux).c``."""
    x = np.asarray(flux, dtype=np.float64)
    y = np.asarray(values / flux, dtype=np.float64)
    dydx = np.asarray(derivatives, dtype=np.float64)
    dx = np.diff(x)
    slope = np.diff(y, axis=0) / dx
    t = (dydx[:-1] + dydx[1:] - 2 * slope) / dx
    return np.stack((t / dx, (slope - dydx[:-1]) / dx - t, dydx[:-1], y[:-1]))


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
