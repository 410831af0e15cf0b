"""Many cubic splines, one per field-grid node, evaluated at once.

A field grid's node splines have different knots (each node's own flux grid), so scipy cannot
evaluate them as one object; calling 25 of them one by one cost most of a default solve over an
SCA. This evaluates the same piecewise polynomials with the same interval rule and the same sum as
scipy's PPoly (``scipy/interpolate/_ppoly.pyx``: ``evaluate_poly1`` adds c_last + c_(last-1) s +
c_(last-2) s^2 + ... in that order, s = x - knot), so each node's value is bit for bit its own
CubicSpline's inside its range (tests/library/test_shipped_field_grid.py checks it). Kept here by
hand because no maintained library evaluates a batch of splines with different knots.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def stack(splines: Sequence[Sequence]) -> tuple[np.ndarray, np.ndarray]:
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


def evaluate(knots: np.ndarray, coefficients: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Every node's polynomial at its own ``x`` (n, n, ...): the interval k with knot_k <= x <
    knot_(k+1) (the last one at a node's last knot and beyond, the first below its first), as
    scipy extrapolates."""
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
