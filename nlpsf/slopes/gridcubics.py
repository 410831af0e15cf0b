"""A field grid's nodes' cubics, built with numpy for every node and column of a (band, SCA) at
once (``nlpsf.slopes.fieldgrid.FieldGrid`` builds them when a (band, SCA) is first read and keeps
them): each node's finite rows of a column as column / flux in flux, and scipy's not-a-knot
``CubicSpline`` of them, bit for bit (``tables.splines.not_a_knot_coefficients``)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .tables.splines import not_a_knot_coefficients, sum_of_powers


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


class Group(NamedTuple):
    """Columns of a (band, SCA) that share their knots, ready to read (:func:`prepare`)."""

    #: Where each column of the group stands among the columns asked for.
    chosen: tuple[int, ...]
    knots: np.ndarray  # (n, n, L)
    last: np.ndarray  # (n, n, 1): each node's last interval
    node_knots: np.ndarray  # (n, n, 1): each node's first knot as a flat index
    node_coefficients: np.ndarray  # (n, n, 1): each node's first interval as a flat index
    #: (order, [columns,] n n (L - 1)): the group's coefficients, flat over the nodes (one column: no column axis).
    coefficients: np.ndarray
    low: np.ndarray  # (n, n): each node's flux range
    high: np.ndarray
    low_edge: np.ndarray  # the range widened by 1e-12 relative: inside it a node answers
    high_edge: np.ndarray


def prepare(stacked: list[tuple[np.ndarray, ...]]) -> list[Group]:
    """The groups of ``stacked`` (``FieldGrid._stacked_splines`` of each column asked for) whose
    knots are one array (built together: shared), each with what every read of it needs, computed
    once: ``splines.evaluate_stacked_columns``' own intermediate arrays (columns whose coefficients
    differ in shape read one by one, as it reads them)."""
    groups = []
    for knots_id in dict.fromkeys(id(s[0]) for s in stacked):
        chosen = [c for c, s in enumerate(stacked) if id(s[0]) == knots_id]
        knots, _, low, high = stacked[chosen[0]]
        shapes = {stacked[c][1].shape for c in chosen}
        for part in [chosen] if len(shapes) == 1 else [[c] for c in chosen]:
            coefficients = [stacked[c][1] for c in part]
            n, order, size = knots.shape[0], coefficients[0].shape[0], coefficients[0].shape[-1]
            node = np.arange(n * n).reshape(n, n, 1)
            flat = (
                coefficients[0].reshape(order, -1)
                if len(part) == 1
                else np.stack(coefficients, axis=1).reshape(order, len(part), -1)
            )
            last = np.sum(np.isfinite(knots), axis=-1)[..., None] - 2
            edges = low * (1 - 1e-12), high * (1 + 1e-12)
            groups.append(Group(tuple(part), knots, last, node * knots.shape[-1], node * size, flat, low, high, *edges))
    return groups


def read(groups: list[Group], count: int, target: np.ndarray, extra: tuple) -> list[np.ndarray]:
    """The ``count`` columns of ``groups`` at the nodes' fluxes ``target`` (n, n, ...; ``extra``
    spreads a node's range over the rest), NaN outside a node's range: each value
    ``splines.evaluate_stacked_columns``' sum, operation for operation (the same numbers)."""
    out: list[np.ndarray] = [None] * count  # type: ignore[list-item]
    for group in groups:
        inside = (target >= group.low_edge[extra]) & (target <= group.high_edge[extra])
        clipped = np.minimum(np.maximum(target, group.low[extra]), group.high[extra])  # np.clip, without its dtype checks
        # Every column of the group at once: (columns, n, n, ...), the same operations element by element.
        values = np.where(inside, _evaluate(group, clipped) * target, np.nan)
        for k, c in enumerate(group.chosen):
            out[c] = values[k]
    return out


def _evaluate(group: Group, x: np.ndarray) -> np.ndarray:
    """``splines.evaluate_stacked_columns(group's knots, its coefficients, x)``, on the prepared
    arrays: (columns, *x.shape)."""
    knots = group.knots
    n = knots.shape[0]
    flat = x.reshape(n, n, -1)
    interval = np.minimum(np.maximum((knots[:, :, None, :] <= flat[..., None]).sum(axis=-1) - 1, 0), group.last)
    # ndarray.take: np.take's own call, without its wrapper's dispatch (the same elements).
    s = flat - knots.take(group.node_knots + interval)
    coefficients = group.coefficients
    read = coefficients.take(group.node_coefficients + interval, axis=coefficients.ndim - 1)
    return sum_of_powers(read, s).reshape(len(group.chosen), *x.shape)
