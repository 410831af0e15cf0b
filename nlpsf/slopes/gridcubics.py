"""A field grid's nodes' cubics, built with numpy for every node and column of a (band, SCA) at
once (``nlpsf.slopes.fieldgrid.FieldGrid`` builds them when a (band, SCA) is first read and keeps
them): each node's finite rows of a column as column / flux in flux, and scipy's not-a-knot
``CubicSpline`` of them, bit for bit (``tables.splines.not_a_knot_coefficients``)."""

from __future__ import annotations

import numpy as np

from .tables.splines import not_a_knot_coefficients


def node_series(grid, key: str, index: int, j: int, i: int) -> tuple[np.ndarray, np.ndarray]:
    """(flux ascending, column / flux) of one node's finite rows of column ``index``."""
    flux = grid.arrays[f"{key}/flux"][j, i]
    values = grid.arrays[f"{key}/values"][j, i, :, index].astype(np.float64)
    ok = np.isfinite(flux) & np.isfinite(values)
    f, q = flux[ok], values[ok] / flux[ok]
    order = np.argsort(f)
    return f[order], q[order]


def build_stacked(grid, key: str, columns: list[str]) -> list[tuple[np.ndarray, ...]]:
    """Every node's cubic of each of ``columns`` of ``key`` as padded arrays: ``FieldGrid._stacked_splines``' layout."""
    n = grid.arrays[f"{key}/flux"].shape[0]
    series = {
        (c, j, i): node_series(grid, key, grid.meta["columns"].index(name), j, i)
        for c, name in enumerate(columns)
        for j in range(n)
        for i in range(n)
    }
    # Every node's coefficients, the series of one length at a time.
    coefficients_of: dict[tuple, np.ndarray] = {}
    for length in sorted({f.size for f, _ in series.values()}):
        keys = [k for k, (f, _) in series.items() if f.size == length]
        x = np.stack([series[k][0] for k in keys])
        y = np.stack([series[k][1] for k in keys])
        if length >= 4:
            built = not_a_knot_coefficients(x, y)
        else:  # too short for the not-a-knot system: scipy's own special cases
            from scipy.interpolate import CubicSpline

            built = np.stack([CubicSpline(a, b).c for a, b in zip(x, y, strict=True)], axis=1)
        for k, index in zip(keys, range(len(keys)), strict=True):
            coefficients_of[k] = built[:, index]
    out: list[tuple[np.ndarray, ...]] = []
    for c in range(len(columns)):
        size = max(series[(c, j, i)][0].size for j in range(n) for i in range(n))
        order = coefficients_of[(c, 0, 0)].shape[0]
        knots = np.full((n, n, size), np.inf)
        coefficients = np.zeros((order, n, n, size - 1))
        low, high = np.empty((n, n)), np.empty((n, n))
        for j in range(n):
            for i in range(n):
                f = series[(c, j, i)][0]
                knots[j, i, : f.size] = f
                coefficients[:, j, i, : f.size - 1] = coefficients_of[(c, j, i)]
                low[j, i], high[j, i] = f[0], f[-1]
        same = next(
            (o for o in out if np.array_equal(o[0], knots) and np.array_equal(o[2], low) and np.array_equal(o[3], high)), None
        )
        if same is not None:  # the same knots as a column before: shared, so they are read together
            knots, low, high = same[0], same[2], same[3]
        out.append((knots, coefficients, low, high))
    return out
