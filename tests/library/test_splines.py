"""The not-a-knot cubics built with numpy (``nlpsf.slopes.tables.splines``) are scipy's
``CubicSpline`` to the last bit: on analytic data of every shape the shipped files hold (uneven
knots, steep and flat stretches) and on every series of the shipped field grid."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from nlpsf.slopes import fieldgrid
from nlpsf.slopes.tables.splines import hermite_coefficients, knot_derivatives, not_a_knot_coefficients


def test_random_series_give_scipys_coefficients_bit_for_bit():
    rng = np.random.default_rng(25)
    for length in (4, 5, 9, 40, 74):
        x = np.sort(rng.uniform(1.0, 1e6, size=(30, length)), axis=1) * np.geomspace(1, 1e3, length)
        y = rng.normal(size=(30, length)) * np.geomspace(1e-3, 1e3, length)
        ours = not_a_knot_coefficients(x, y)
        for row in range(x.shape[0]):
            assert np.array_equal(ours[:, row], CubicSpline(x[row], y[row]).c), (length, row)


def test_a_tables_knot_derivatives_rebuild_scipys_spline():
    flux = np.geomspace(10.0, 1e7, 23)
    values = 3e-4 * flux * (1 + 0.2 * np.sin(np.log(flux)))
    derivatives = knot_derivatives(flux, values)
    assert np.array_equal(hermite_coefficients(flux, values, derivatives), CubicSpline(flux, values / flux).c)


@pytest.mark.skipif(fieldgrid.shipped_grid() is None, reason="no shipped field grid")
def test_every_series_of_the_shipped_grid_is_scipys_spline():
    grid = fieldgrid.shipped_grid()
    for key in grid.keys()[::9]:
        n = grid.arrays[f"{key}/flux"].shape[0]
        for column in grid.meta["columns"][::4]:
            knots, coefficients, low, high = grid._stacked_splines(key, column)
            for j in range(n):
                for i in range(n):
                    node_low, node_high, spline = grid._spline(key, column, j, i)
                    size = spline.x.size
                    assert np.array_equal(knots[j, i, :size], spline.x) and np.all(np.isinf(knots[j, i, size:]))
                    assert np.array_equal(coefficients[:, j, i, : size - 1], spline.c), (key, column, j, i)
                    assert (low[j, i], high[j, i]) == (node_low, node_high)
