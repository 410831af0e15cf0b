"""Slope tables over the field: the candidate Roman default scene, a grid of positions per SCA, and
interpolation across it.

The scene is the Roman default's (``nlpsf.roman_default``: its optics at the star's position,
the official pupil scale, a K0V star, jitter, charge diffusion, IPC, the background and the HLWAS
ramp), one table per grid node.

The grid. GalSim interpolates the Zernikes of an SCA *bilinearly* between its four corner field
points (``galsim.roman.roman_psfs._interp_aberrations_bilinear``, mirrored by
``roman.aberrations``), so the optics over an SCA are a smooth function of the fractional position
(fx, fy) on the square the corners span. A slope is a smooth but not bilinear function of the
Zernikes, so the tables sit on an n x n grid of pixel positions spanning the SCA (pixels 1 ... 4088
each axis, n odd so the centre is a node) and are interpolated across it by one of
:data:`SCHEMES`: ``bilinear`` (within the grid cell, GalSim's scheme for the Zernikes applied to the
slopes) or ``lagrange`` (the tensor-product polynomial through every node, biquadratic on 3 x 3).
``scripts/field_interpolation_error.py`` measures both against fresh simulations at random positions.

The runtime format is one ``.npz`` (numpy only): per (band, SCA) the node positions, each node's
magnitude grid and its slope columns in float32, and the metadata as JSON.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import roman
from .checks import InputError, check_integer

#: Interpolation schemes across the field grid.
SCHEMES: tuple[str, ...] = ("bilinear", "lagrange")
#: Grid sizes a build accepts (2: the corners only; odd sizes have the SCA centre as a node).
GRID_SIZES: tuple[int, ...] = (2, 3, 5, 7, 9)
#: The scene names a table build understands ("paper": the shipped tables' idealised scene).
TABLE_SCENES: tuple[str, ...] = ("paper", "roman")
#: Runtime format tag of a field-grid file.
FORMAT = "nlpsf-field-grid-1"


def check_grid(n: int) -> int:
    check_integer(n, "grid", 2, max(GRID_SIZES))
    if n not in GRID_SIZES:
        raise InputError("grid", f"the field grid is n x n with n one of {', '.join(map(str, GRID_SIZES))}, got {n}")
    return int(n)


def grid_axis(n: int) -> np.ndarray:
    """Pixel coordinates of the n nodes along one axis (1 and 4088 included, centre for odd n)."""
    return np.linspace(1.0, float(roman.SCA_PIXELS), check_grid(n))


def grid_positions(n: int) -> list[tuple[int, int, tuple[float, float]]]:
    """Every node (i along x, j along y, (x, y) pixels) of the n x n grid, the same on every SCA."""
    axis = grid_axis(n)
    return [(i, j, (float(axis[i]), float(axis[j]))) for j in range(n) for i in range(n)]


# --- interpolation across the grid -----------------------------------------------------------


def _lagrange_weights(axis: np.ndarray, x: float) -> np.ndarray:
    weights = np.ones(axis.size)
    for k in range(axis.size):
        for m in range(axis.size):
            if m != k:
                weights[k] *= (x - axis[m]) / (axis[k] - axis[m])
    return weights


def _bilinear_weights(axis: np.ndarray, x: float) -> np.ndarray:
    weights = np.zeros(axis.size)
    k = int(np.clip(np.searchsorted(axis, x) - 1, 0, axis.size - 2))
    t = (x - axis[k]) / (axis[k + 1] - axis[k])
    weights[k], weights[k + 1] = 1.0 - t, t
    return weights


def weights(n: int, position: tuple[float, float], scheme: str = "lagrange") -> np.ndarray:
    """(n, n) weights [j (y), i (x)] of the grid nodes for a value at ``position`` (pixels)."""
    if scheme not in SCHEMES:
        raise InputError("scheme", f"must be one of {', '.join(SCHEMES)}, got {scheme!r}")
    axis = grid_axis(n)
    x, y = (float(v) for v in position)
    for v in (x, y):
        if not (1.0 <= v <= roman.SCA_PIXELS):
            raise InputError("position", f"position must lie in [1, {roman.SCA_PIXELS}] pixels, got {position!r}")
    rule = _lagrange_weights if scheme == "lagrange" else _bilinear_weights
    return np.outer(rule(axis, y), rule(axis, x))


def interpolate(values: np.ndarray, position: tuple[float, float], scheme: str = "lagrange") -> np.ndarray:
    """Interpolate node values ``values[j, i, ...]`` (j along y, i along x) to ``position``."""
    values = np.asarray(values, dtype=np.float64)
    n = values.shape[0]
    if values.shape[1] != n:
        raise InputError("values", f"need an n x n grid of values, got shape {values.shape}")
    w = weights(n, position, scheme)
    return np.tensordot(w, values, axes=([0, 1], [0, 1]))


# --- the runtime file ------------------------------------------------------------------------


#: Columns a field-grid file keeps per node (the slope columns of ``nlpsf.tables``; their errors).
def _slope_columns() -> list[str]:
    from .tables import COLUMN_METRICS, MODES

    return [f"{mode}_{metric}{suffix}" for metric in COLUMN_METRICS for mode in MODES for suffix in ("", "_err")]


def write_grid(tables: list, destination: Path | str, dtype=np.float32) -> Path:
    """Pack per-node tables (``tablebuild.compute_table`` with a ``grid_node``) into one ``.npz``.

    Per (band, SCA): ``{key}/positions`` (n, n, 2), ``{key}/magnitude`` and ``{key}/flux`` (n, n, M)
    in float64 (M the longest node grid, NaN-padded; magnitudes are labels, flux the spline's
    abscissa) and ``{key}/values`` (n, n, M, C) in ``dtype`` for the slope columns.
    """
    columns = _slope_columns()
    groups: dict[tuple[str, int], list] = {}
    for t in tables:
        groups.setdefault((t.meta["band"], int(t.meta["sca"])), []).append(t)
    arrays: dict[str, np.ndarray] = {}
    meta: dict = {"format": FORMAT, "columns": columns, "tables": {}, "value_dtype": np.dtype(dtype).name}
    for (band, sca), group in sorted(groups.items()):
        n = int(group[0].meta["grid_node"][0])
        if len(group) != n * n:
            raise InputError("tables", f"{band} SCA {sca}: {len(group)} node tables for a {n} x {n} grid")
        length = max(len(t) for t in group)
        magnitude = np.full((n, n, length), np.nan)
        flux = np.full((n, n, length), np.nan)
        values = np.full((n, n, length, len(columns)), np.nan)
        positions = np.zeros((n, n, 2))
        for t in group:
            _, i, j = t.meta["grid_node"]
            rows = len(t)
            magnitude[j, i, :rows] = t["magnitude"]
            flux[j, i, :rows] = t["flux_electrons"]
            values[j, i, :rows] = np.stack([np.asarray(t[c], dtype=np.float64) for c in columns], axis=-1)
            positions[j, i] = t.meta["position"]
        key = f"{band}_{sca:02d}"
        arrays[f"{key}/positions"] = positions
        arrays[f"{key}/magnitude"] = magnitude
        arrays[f"{key}/flux"] = flux
        arrays[f"{key}/values"] = values.astype(dtype)
        meta["tables"][key] = {
            "band": band,
            "sca": sca,
            "grid": n,
            "settings": group[0].meta["settings"],
            "fingerprint": group[0].meta["fingerprint"],
            "saturation_magnitude": [[None] * n for _ in range(n)],
        }
        for t in group:
            _, i, j = t.meta["grid_node"]
            meta["tables"][key]["saturation_magnitude"][j][i] = float(t.meta["saturation_magnitude"])
    destination = Path(destination)
    destination.parent.mkdir(parents=True, exist_ok=True)
    arrays["meta"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
    with open(destination, "wb") as handle:
        np.savez_compressed(handle, **arrays)
    return destination


@dataclass(frozen=True, eq=False)
class FieldGrid:
    """One field-grid file, read: slopes at any position and magnitude of its (band, SCA)s."""

    meta: dict
    arrays: dict

    @classmethod
    def load(cls, path: Path | str) -> FieldGrid:
        with np.load(path) as data:
            arrays = {k: data[k] for k in data.files}
        meta = json.loads(arrays.pop("meta").tobytes().decode())
        if meta.get("format") != FORMAT:
            raise InputError("field grid", f"{path}: not a {FORMAT} file")
        return cls(meta, arrays)

    def keys(self) -> list[str]:
        return sorted(self.meta["tables"])

    def node_values(self, band: str, sca: int, column: str, magnitude: float) -> np.ndarray:
        """(n, n) slopes of ``column`` at ``magnitude`` at every node: a cubic spline of slope / flux
        in flux along each node's magnitude grid, as ``nlpsf.tables`` reads a table."""
        from scipy.interpolate import CubicSpline

        key = f"{band}_{int(sca):02d}"
        if key not in self.meta["tables"]:
            raise InputError("band", f"no field grid for {band} SCA {sca} in this file")
        index = self.meta["columns"].index(column)
        flux = self.arrays[f"{key}/flux"]
        mags = self.arrays[f"{key}/magnitude"]
        values = self.arrays[f"{key}/values"][..., index].astype(np.float64)
        n = flux.shape[0]
        out = np.full((n, n), np.nan)
        for j in range(n):
            for i in range(n):
                ok = np.isfinite(flux[j, i]) & np.isfinite(values[j, i])
                f, q, m = flux[j, i][ok], values[j, i][ok] / flux[j, i][ok], mags[j, i][ok]
                order = np.argsort(f)
                target = f[order][0] * 10 ** (-0.4 * (magnitude - m[order][0]))
                if not (f[order][0] <= target <= f[order][-1]):
                    continue  # outside this node's grid: no extrapolation across the field
                out[j, i] = CubicSpline(f[order], q[order])(target) * target
        return out

    def slope(
        self,
        band: str,
        sca: int,
        position: tuple[float, float],
        magnitude: float,
        column: str = "bias_size",
        scheme: str = "lagrange",
    ) -> float:
        """The slope at ``position`` (pixels) and ``magnitude``, interpolated across the field."""
        return float(interpolate(self.node_values(band, sca, column, magnitude), position, scheme))
