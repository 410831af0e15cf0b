"""The cubics of ``nlpsf.slopes.tables.splines``: the field grid's, built with numpy, are the public
``CubicSpline`` to the last bit, on analytic data of every shape the shipped files hold (uneven
knots, steep and flat stretches) and on every series of the shipped field grid; a table's are that
spline's public ``x`` and ``c``; and no module of the project uses a private name of scipy."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from scipy.interpolate import CubicSpline, PPoly

from nlpsf.slopes import fieldgrid
from nlpsf.slopes.tables.splines import evaluate_cubic, not_a_knot_coefficients, not_a_knot_spline, sum_of_powers

ROOT = Path(__file__).resolve().parents[2]


def test_random_series_give_scipys_coefficients_bit_for_bit():
    rng = np.random.default_rng(25)
    for length in (4, 5, 9, 40, 74):
        x = np.sort(rng.uniform(1.0, 1e6, size=(30, length)), axis=1) * np.geomspace(1, 1e3, length)
        y = rng.normal(size=(30, length)) * np.geomspace(1e-3, 1e3, length)
        ours = not_a_knot_coefficients(x, y)
        for row in range(x.shape[0]):
            assert np.array_equal(ours[:, row], CubicSpline(x[row], y[row]).c), (length, row)


def test_a_tables_spline_is_scipys_public_ppoly():
    flux = np.geomspace(10.0, 1e7, 23)
    values = 3e-4 * flux * (1 + 0.2 * np.sin(np.log(flux)))
    breaks, coefficients = not_a_knot_spline(flux, values)
    truth = CubicSpline(flux, values / flux)
    assert np.array_equal(breaks, truth.x) and np.array_equal(coefficients, truth.c)
    probe = np.concatenate([np.geomspace(flux[0], flux[-1], 501), flux])
    np.testing.assert_allclose(evaluate_cubic(breaks, coefficients, probe), PPoly(coefficients, breaks)(probe), rtol=1e-13)


def test_the_sum_of_powers_is_the_sum_written_out_from_zero():
    # c3 + c2 s + c1 s^2 + c0 s^3 added from 0 with the powers from 1, in that order: the sum the
    # stacked readers share, its first operations (0 + c * 1, 1 * s) left out without changing a bit.
    rng = np.random.default_rng(7)
    read = rng.normal(size=(4, 6, 5)) * np.geomspace(1e-6, 1e3, 5)
    read[3, 0, :] = -0.0  # a constant -0.0: the sum from 0 makes it +0.0
    s = rng.uniform(-2e5, 2e5, size=(6, 5))
    s[0, :] = 0.0
    value, power = np.zeros((6, 5)), np.ones((6, 5))
    for k in range(4):
        value = value + read[3 - k] * power
        power = power * s
    ours = sum_of_powers(read, s)
    assert np.array_equal(ours, value) and np.array_equal(np.signbit(ours), np.signbit(value))


#: Where the project's code lives (the web layer, scripts and benchmarks included).
CODE = [ROOT / "nlpsf", ROOT / "app", ROOT / "scripts", ROOT / "benchmarks"]
#: A private name of scipy: a module or attribute path with a part starting with "_" (scipy.x._y,
#: ``from scipy.x import _y``, ``from scipy.x._y import z``), dunders aside.
PRIVATE = re.compile(r"scipy(\.\w+)*\._(?!_)\w*|from\s+scipy[\w.]*\s+import\s+\(?\s*(\w+\s*,\s*)*_(?!_)")


def test_no_module_uses_scipys_private_names():
    found = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for folder in CODE
        if folder.is_dir()
        for path in sorted(folder.rglob("*.py"))
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if PRIVATE.search(line)
    ]
    assert not found, found
    assert PRIVATE.search("from scipy.interpolate._ppoly import evaluate") and PRIVATE.search("scipy.linalg._flapack")
    assert PRIVATE.search("from scipy.interpolate import _ppoly") and not PRIVATE.search("scipy.interpolate.CubicSpline")


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
