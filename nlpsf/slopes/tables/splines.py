"""Piecewise cubics: knot derivatives solved with scipy when a table is written, the cubics built
and evaluated with numpy.

The slopes are interpolated with scipy's not-a-knot ``CubicSpline`` of slope / flux in flux. That
spline is a cubic Hermite interpolant: once its derivatives at the knots are known (one banded
solve, scipy/LAPACK), its coefficients are four elementwise numpy expressions of them and the data
(scipy's own ``CubicHermiteSpline``, repeated in :func:`hermite_coefficients`). So a table file
stores the knot derivatives (``knot_derivatives``, at write time, checked bit for bit against
scipy's coefficients there) -- a quarter of what the coefficients took -- and ``nlpsf solve`` and
the service build the coefficients without scipy or astropy. The tests check the evaluation
against scipy's on the shipped tables. The field grid's node splines (``nlpsf.slopes.fieldgrid``) are
evaluated all at once, bit for bit as scipy evaluates each (:func:`evaluate_stacked_cubics`).
"""

from __future__ import annotations

from collections.abc import Sequence

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


def stack_cubics(splines: Sequence[Sequence]) -> tuple[np.ndarray, np.ndarray]:
    """(n, n) scipy CubicSplines (or PPolys of one order) -> knots (n, n, L), +inf past a node's
    last, and coefficients (order, n, n, L - 1), zero past a node's last interval."""
    n = len(splines)
    size = max(spline.x.size for row in splines for spline in row)
    order = splines[0][0].c.shape[0]
    knots = np.full((n, n, size), np.inf)
    coefficients = np.zeros((order, n, n, size - 1))
    for j, row in enumerate(splines):
        for i, spline in enumerate(row):
            knots[j, i, : spline.x.size] = spline.x
            coefficients[:, j, i, : spline.x.size - 1] = spline.c
    return knots, coefficients


def evaluate_stacked_cubics(knots: np.ndarray, coefficients: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Every node's polynomial at its own ``x`` (n, n, ...), at once (a field grid's nodes have
    different knots, so scipy cannot evaluate them as one object, and calling them one by one cost
    most of a default solve over an SCA). The interval k with knot_k <= x < knot_(k+1) (the last at
    a node's last knot and beyond, the first below its first) and the sum scipy's PPoly forms
    (``_ppoly.pyx`` ``evaluate_poly1``: c_last + c_(last-1) s + c_(last-2) s^2 + ..., in that order,
    s = x - knot), so a node's value is bit for bit its CubicSpline's -- unlike
    :func:`evaluate_cubic`'s Horner form, which the paper tables' readers have always used."""
    n = knots.shape[0]
    flat = x.reshape(n, n, -1)
    last = np.sum(np.isfinite(knots), axis=-1)[..., None] - 2
    interval = np.clip(np.sum(knots[:, :, None, :] <= flat[..., None], axis=-1) - 1, 0, last)
    s = flat - np.take_along_axis(knots, interval, axis=-1)
    order = coefficients.shape[0]
    value = np.zeros_like(flat)
    power = np.ones_like(flat)
    for k in range(order):
        value = value + np.take_along_axis(coefficients[order - 1 - k], interval, axis=-1) * power
        if k < order - 1:
            power = power * s
    return value.reshape(x.shape)
