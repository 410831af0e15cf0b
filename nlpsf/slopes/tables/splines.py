"""Piecewise cubics: knot derivatives solved with scipy when a table is written, the cubics built
and evaluated with numpy.

The slopes are interpolated with scipy's not-a-knot ``CubicSpline`` of slope / flux in flux. That
spline is a cubic Hermite interpolant: once its derivatives at the knots are known (one
tridiagonal solve), its coefficients are four elementwise expressions of them and the data (scipy's
own ``CubicHermiteSpline``, repeated in :func:`hermite_coefficients`). The solve is done here with
numpy as scipy does it (its system, LAPACK ``gtsv``'s elimination: :func:`not_a_knot_derivatives`),
many splines at once and bit for bit scipy's public ``CubicSpline(...).c`` (checked where a table is
written, and by the tests on every shipped series) -- no scipy at run time and nothing of scipy but
its public results. A paper table's file stores the knot derivatives (``knot_derivatives``), a
quarter of what the coefficients took; the field grid (``nlpsf.slopes.fieldgrid``) builds its
nodes' cubics from its values when a (band, SCA) is first read (:func:`not_a_knot_coefficients`)
and evaluates them all at once, bit for bit as scipy evaluates each (:func:`evaluate_stacked_cubics`).
"""

from __future__ import annotations

import numpy as np


def knot_derivatives(flux: np.ndarray, values: np.ndarray) -> np.ndarray:
    """d(values / flux)/d flux at each knot of scipy's not-a-knot CubicSpline (flux ascending).

    Solved with numpy as scipy solves them (:func:`not_a_knot_derivatives`) and checked against
    scipy's public coefficients: :func:`hermite_coefficients` of them must equal
    ``CubicSpline(flux, values / flux).c`` bit for bit (scipy only where a table is written)."""
    from scipy.interpolate import CubicSpline

    flux = np.asarray(flux, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    derivatives = not_a_knot_derivatives(flux[None], (values / flux)[None])[0]
    if not np.array_equal(hermite_coefficients(flux, values, derivatives), CubicSpline(flux, values / flux).c):
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


def evaluate_cubic(breaks: np.ndarray, coefficients: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Evaluate a piecewise cubic (scipy's PPoly layout: highest power first) at ``x``."""
    index = np.minimum(np.maximum(np.searchsorted(breaks, x, side="right") - 1, 0), breaks.size - 2)
    d = x - breaks[index]
    c = coefficients[:, index]
    return ((c[0] * d + c[1]) * d + c[2]) * d + c[3]


def evaluate_stacked_cubics(knots: np.ndarray, coefficients: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Every node's polynomial at its own ``x`` (n, n, ...), at once (a field grid's nodes have
    different knots, so scipy cannot evaluate them as one object, and calling them one by one cost
    most of a default solve over an SCA). The interval k with knot_k <= x < knot_(k+1) (the last at
    a node's last knot and beyond, the first below its first) and the sum scipy's PPoly forms
    (``_ppoly.pyx`` ``evaluate_poly1``: c_last + c_(last-1) s + c_(last-2) s^2 + ..., in that order,
    s = x - knot), so a node's value is bit for bit its CubicSpline's -- unlike
    :func:`evaluate_cubic`'s Horner form, which the paper tables' readers have always used."""
    return evaluate_stacked_columns(knots, [coefficients], x)[0]


def evaluate_stacked_columns(knots: np.ndarray, coefficients: list[np.ndarray], x: np.ndarray) -> list[np.ndarray]:
    """:func:`evaluate_stacked_cubics` of several columns that share their knots: the interval of
    every x found once."""
    n = knots.shape[0]
    flat = x.reshape(n, n, -1)
    last = np.sum(np.isfinite(knots), axis=-1)[..., None] - 2
    interval = np.minimum(np.maximum(np.sum(knots[:, :, None, :] <= flat[..., None], axis=-1) - 1, 0), last)
    rows, columns = np.arange(n)[:, None, None], np.arange(n)[None, :, None]
    s = flat - knots[rows, columns, interval]
    out = []
    for stacked in coefficients:
        order = stacked.shape[0]
        value = np.zeros_like(flat)
        power = np.ones_like(flat)
        for k in range(order):
            value = value + stacked[order - 1 - k][rows, columns, interval] * power
            if k < order - 1:
                power = power * s
        out.append(value.reshape(x.shape))
    return out


def not_a_knot_coefficients(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Coefficients (4, S, M - 1) of the not-a-knot cubic spline through each row of ``y`` (S, M) at
    the abscissae ``x`` (S, M) of the same row (ascending, M >= 4), in scipy's PPoly layout: every
    row at once, with numpy alone (:func:`not_a_knot_derivatives`, then the Hermite form).

    The knot derivatives solve scipy's ``CubicSpline`` system (its right-hand side, operation for
    operation) by LAPACK ``gtsv``'s elimination with its row interchanges, and the coefficients are
    :func:`hermite_coefficients`' arithmetic; so a row's coefficients are scipy's
    ``CubicSpline(x, y).c`` to the last bit wherever scipy's LAPACK computes without fused
    multiply-adds, and within a few units of the last place otherwise
    (``tests/library/test_tables.py`` checks them against scipy)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    dx = np.diff(x, axis=1)
    slope = np.diff(y, axis=1) / dx
    return _hermite_rows(y, not_a_knot_derivatives(x, y), dx, slope)


def not_a_knot_derivatives(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(S, M) knot derivatives of the not-a-knot cubic spline through each row of ``y`` at ``x``
    (ascending, M >= 4): scipy's ``CubicSpline`` system, solved as its LAPACK ``gtsv`` solves it."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.ndim != 2 or x.shape != y.shape or x.shape[1] < 4:
        raise ValueError(f"need (S, M) abscissae and values with M >= 4, got {x.shape} and {y.shape}")
    dx = np.diff(x, axis=1)
    slope = np.diff(y, axis=1) / dx
    n = x.shape[1]
    # The tridiagonal system of the knot derivatives s: sub-diagonal dl, diagonal d, super-diagonal du.
    d = np.empty_like(x)
    du = np.empty((x.shape[0], n - 1))
    dl = np.empty((x.shape[0], n - 1))
    b = np.empty_like(x)
    d[:, 1:-1] = 2 * (dx[:, :-1] + dx[:, 1:])
    du[:, 1:] = dx[:, :-1]
    dl[:, :-1] = dx[:, 1:]
    b[:, 1:-1] = 3 * (dx[:, 1:] * slope[:, :-1] + dx[:, :-1] * slope[:, 1:])
    start = x[:, 2] - x[:, 0]
    d[:, 0], du[:, 0] = dx[:, 1], start
    b[:, 0] = ((dx[:, 0] + 2 * start) * dx[:, 1] * slope[:, 0] + dx[:, 0] ** 2 * slope[:, 1]) / start
    end = x[:, -1] - x[:, -3]
    d[:, -1], dl[:, -1] = dx[:, -2], end
    b[:, -1] = (dx[:, -1] ** 2 * slope[:, -2] + (2 * end + dx[:, -1]) * dx[:, -2] * slope[:, -1]) / end
    return _gtsv(dl, d, du, b)


def _gtsv(dl: np.ndarray, d: np.ndarray, du: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve each row's tridiagonal system as LAPACK ``dgtsv`` does (one right-hand side): Gaussian
    elimination with partial pivoting by row interchanges, then back substitution."""
    dl, d, du, b = (np.array(a, dtype=np.float64) for a in (dl, d, du, b))
    n = d.shape[1]
    du2 = np.zeros_like(dl)  # the second super-diagonal the interchanges fill
    for i in range(n - 1):
        keep = np.abs(d[:, i]) >= np.abs(dl[:, i])
        with np.errstate(divide="ignore", invalid="ignore"):
            fact_keep = dl[:, i] / d[:, i]
            fact_swap = d[:, i] / dl[:, i]
        next_d, next_b, this_du = d[:, i + 1].copy(), b[:, i + 1].copy(), du[:, i].copy()
        # No interchange: eliminate the sub-diagonal.
        d_keep = next_d - fact_keep * this_du
        b_keep = next_b - fact_keep * b[:, i]
        # Interchange rows i and i + 1.
        d_swap = this_du - fact_swap * next_d
        b_swap = b[:, i] - fact_swap * next_b
        d[:, i] = np.where(keep, d[:, i], dl[:, i])
        if i < n - 2:
            next_du = du[:, i + 1].copy()
            du2[:, i] = np.where(keep, 0.0, next_du)
            du[:, i + 1] = np.where(keep, next_du, -fact_swap * next_du)
        du[:, i] = np.where(keep, this_du, next_d)
        d[:, i + 1] = np.where(keep, d_keep, d_swap)
        b[:, i + 1] = np.where(keep, b_keep, b_swap)
        b[:, i] = np.where(keep, b[:, i], next_b)
    out = np.empty_like(b)
    out[:, -1] = b[:, -1] / d[:, -1]
    out[:, -2] = (b[:, -2] - du[:, -1] * out[:, -1]) / d[:, -2]
    for i in range(n - 3, -1, -1):
        out[:, i] = (b[:, i] - du[:, i] * out[:, i + 1] - du2[:, i] * out[:, i + 2]) / d[:, i]
    return out


def _hermite_rows(y: np.ndarray, dydx: np.ndarray, dx: np.ndarray, slope: np.ndarray) -> np.ndarray:
    """:func:`hermite_coefficients` of every row: (4, S, M - 1)."""
    t = (dydx[:, :-1] + dydx[:, 1:] - 2 * slope) / dx
    return np.stack((t / dx, (slope - dydx[:, :-1]) / dx - t, dydx[:, :-1], y[:, :-1]))
