"""Piecewise cubics in scipy's public ``PPoly`` layout (breakpoints x, coefficients c (4, x.size - 1),
highest power first), evaluated with numpy.

The slopes are interpolated with scipy's not-a-knot ``CubicSpline`` of slope / flux in flux. A
paper table's runtime file stores each spline's ``x`` and ``c`` as ``CubicSpline`` returned them
when it was written (:func:`not_a_knot_spline`), and :func:`evaluate_cubic` reads them (Horner's
form, the order the tables' readers have always used: the answers are bit for bit what they were;
scipy's ``PPoly.__call__`` sums the powers in another order and can differ in the last bit).

The field grid (``nlpsf.slopes.fieldgrid``) stores its nodes' values, not their coefficients (every
node's 18 columns as float64 coefficients would make its file about twelve times larger), and builds
its nodes' not-a-knot cubics when a (band, SCA) is first read, every node at once, with numpy
(:func:`not_a_knot_coefficients`: the spline's tridiagonal system, solved by Gaussian elimination
with partial pivoting), and evaluates them all at once (:func:`evaluate_stacked_cubics`). The tests
check both against the public ``CubicSpline`` built from the same points, on every shipped series.
"""

from __future__ import annotations

import numpy as np


def not_a_knot_spline(flux: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, c): scipy's not-a-knot ``CubicSpline`` of values / flux in flux (flux ascending), its
    public breakpoints and coefficients -- how a table's runtime file stores a slope column's
    interpolant (scipy where a table is written, or read from an ECSV alone)."""
    from scipy.interpolate import CubicSpline

    flux = np.asarray(flux, dtype=np.float64)
    spline = CubicSpline(flux, np.asarray(values, dtype=np.float64) / flux)
    return spline.x, spline.c


def evaluate_cubic(breaks: np.ndarray, coefficients: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Evaluate a piecewise cubic (scipy's PPoly layout: highest power first) at ``x``."""
    index = np.minimum(np.maximum(np.searchsorted(breaks, x, side="right") - 1, 0), breaks.size - 2)
    d = x - breaks[index]
    c = coefficients[:, index]
    return ((c[0] * d + c[1]) * d + c[2]) * d + c[3]


def evaluate_stacked_cubics(knots: np.ndarray, coefficients: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Every node's polynomial at its own ``x`` (n, n, ...), at once (a field grid's nodes have
    different knots, so one ``PPoly`` cannot hold them, and calling them one by one cost most of a
    default solve over an SCA). The interval k with knot_k <= x < knot_(k+1) (the last at a node's
    last knot and beyond, the first below its first) and the sum of the powers c_last + c_(last-1) s
    + c_(last-2) s^2 + ..., in that order, s = x - knot (the grid's answers have been this sum since
    it shipped; ``tests/library/test_shipped_field_grid.py`` finds it equal to each node's public
    ``CubicSpline`` called at the same points, bit for bit) -- unlike :func:`evaluate_cubic`'s
    Horner form, which the paper tables' readers have always used."""
    return evaluate_stacked_columns(knots, [coefficients], x)[0]


def evaluate_stacked_columns(knots: np.ndarray, coefficients: list[np.ndarray], x: np.ndarray) -> list[np.ndarray]:
    """:func:`evaluate_stacked_cubics` of several columns that share their knots: the interval of
    every x found once."""
    n = knots.shape[0]
    flat = x.reshape(n, n, -1)
    last = np.sum(np.isfinite(knots), axis=-1)[..., None] - 2
    interval = np.minimum(np.maximum((knots[:, :, None, :] <= flat[..., None]).sum(axis=-1) - 1, 0), last)
    node = np.arange(n * n).reshape(n, n, 1)  # each x's node, then its interval there, as flat indices
    s = flat - np.take(knots, node * knots.shape[-1] + interval)
    if len({c.shape for c in coefficients}) > 1:
        return [out for c in coefficients for out in evaluate_stacked_columns(knots, [c], x)]
    # Every column at once, the same sum element by element: (order, [columns,] n, n, x's).
    order, size = coefficients[0].shape[0], coefficients[0].shape[-1]
    at = node * size + interval
    if len(coefficients) == 1:
        read = np.take(coefficients[0].reshape(order, -1), at, axis=1)
    else:
        read = np.take(np.stack(coefficients, axis=1).reshape(order, len(coefficients), -1), at, axis=2)
    value = sum_of_powers(read, s)
    return [value.reshape(x.shape)] if len(coefficients) == 1 else [v.reshape(x.shape) for v in value]


def sum_of_powers(read: np.ndarray, s: np.ndarray) -> np.ndarray:
    """c_last + c_(last-1) s + c_(last-2) s^2 + ..., in that order, of the coefficients ``read``
    (order first, highest power first) at ``s``: the stacked evaluators' sum (:func:`evaluate_stacked_cubics`),
    kept in one place so that every reader of the field grid adds in the same order, bit for bit."""
    order = read.shape[0]
    # The sum from 0 with the first power 1: 0 + c_last * 1 is c_last + 0.0 (a -0.0 made +0.0, as
    # that sum makes it) and 1 * s is s, so those operations are left out (the same numbers).
    value = read[order - 1] + 0.0
    power = s
    for k in range(1, order):
        value = value + read[order - 1 - k] * power
        if k < order - 1:
            power = power * s
    return value


def not_a_knot_coefficients(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Coefficients (4, S, M - 1) of the not-a-knot cubic spline through each row of ``y`` (S, M) at
    the abscissae ``x`` (S, M) of the same row (ascending, M >= 4), in scipy's PPoly layout: every
    row at once, with numpy alone (:func:`not_a_knot_derivatives`, then the Hermite form).

    The knot derivatives solve the not-a-knot system (:func:`not_a_knot_derivatives`), and the
    coefficients are the cubic Hermite form of them and the data. A row's coefficients equal the
    public ``CubicSpline(x, y).c`` built from the same points on every shipped series
    (``tests/library/test_splines.py``; to the last bit where the LAPACK scipy calls computes without
    fused multiply-adds, within a few units of the last place otherwise)."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    dx = np.diff(x, axis=1)
    slope = np.diff(y, axis=1) / dx
    return _hermite_rows(y, not_a_knot_derivatives(x, y), dx, slope)


def not_a_knot_derivatives(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(S, M) knot derivatives of the not-a-knot cubic spline through each row of ``y`` at ``x``
    (ascending, M >= 4): the tridiagonal system of the derivatives (the first and last rows the
    not-a-knot conditions), solved by :func:`_tridiagonal_solve`."""
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
    return _tridiagonal_solve(dl, d, du, b)


def _tridiagonal_solve(dl: np.ndarray, d: np.ndarray, du: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve each row's tridiagonal system (one right-hand side): Gaussian elimination with partial
    pivoting by row interchanges, then back substitution (the textbook algorithm, as LAPACK's
    ``dgtsv`` states it)."""
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
    """(4, S, M - 1) coefficients of every row's cubic Hermite interpolant with knot derivatives ``dydx``
    (highest power first, each interval's own origin)."""
    t = (dydx[:, :-1] + dydx[:, 1:] - 2 * slope) / dx
    return np.stack((t / dx, (slope - dydx[:, :-1]) / dx - t, dydx[:, :-1], y[:, :-1]))
