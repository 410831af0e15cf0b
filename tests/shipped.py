"""The shipped slope table read directly: astropy's ECSV reader and scipy's CubicSpline, sharing no
code with ``nlpsf.slopes.tables`` (its companion file, its spline coefficients, its look-ups). Tests check
the solver's answers against these numbers, not against the table object the solver itself reads.

Only the relations the tables are defined by are used here: slopes are scipy's not-a-knot cubic
spline of slope / flux in flux; the flux and the star's peak charge are proportional to
10^(-0.4 m) times the exposure; the star saturates where its peak charge reaches the full well.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np

import nlpsf

ECSV = Path(nlpsf.__file__).resolve().parent / "data" / "tables" / "slopes.ecsv"


@cache
def _table():
    from astropy.table import Table

    return Table.read(ECSV, format="ascii.ecsv")


@cache
def _rows(band: str, sca: int) -> dict[str, np.ndarray]:
    table = _table()
    rows = table[(table["band"] == band) & (table["sca"] == sca)]
    rows.sort("flux_electrons")
    return {name: np.asarray(rows[name], dtype=np.float64) for name in rows.colnames if name != "band"}


def exptime_s() -> float:
    """The exposure the table was simulated at [s]."""
    return float(_table().meta["settings"]["exptime_s"])


def _flux_scale(band: str, sca: int, magnitude, exptime: float | None) -> np.ndarray:
    """flux(magnitude, exptime) / flux of the faintest row: 10^(-0.4 (m - m_row)) T / T_table."""
    rows = _rows(band, sca)
    ratio = 1.0 if exptime is None else exptime / exptime_s()
    return 10 ** (-0.4 * (np.asarray(magnitude, dtype=np.float64) - rows["magnitude"][0])) * ratio


def flux(band: str, sca: int, magnitude, exptime: float | None = None) -> np.ndarray:
    """The star's electrons over the exposure [e-]."""
    return _rows(band, sca)["flux_electrons"][0] * _flux_scale(band, sca, magnitude, exptime)


def peak_electrons(band: str, sca: int, magnitude, exptime: float | None = None) -> np.ndarray:
    """The star's brightest pixel [e-, per fine pixel x oversampling^2, the table's unit]."""
    return _rows(band, sca)["peak_electrons"][0] * _flux_scale(band, sca, magnitude, exptime)


def slope(band: str, sca: int, metric: str, mode: str, magnitude) -> np.ndarray:
    """The tabulated slope (``mode`` "bias" or "scatter", ``metric`` "size", "e1" or "e2") at the
    table's own exposure: the not-a-knot cubic of slope / flux in flux, times the flux; fainter than
    the grid slope / flux stays at its faintest value (the linear regime), brighter has none (NaN)."""
    from scipy.interpolate import CubicSpline

    rows = _rows(band, sca)
    fluxes = rows["flux_electrons"]
    at = flux(band, sca, magnitude)
    spline = CubicSpline(fluxes, rows[f"{mode}_{metric}"] / fluxes)
    value = spline(np.clip(at, fluxes[0], fluxes[-1])) * at
    return np.where(at > fluxes[-1] * (1 + 1e-9), np.nan, value)


def saturation_magnitude(band: str, sca: int, full_well: float, exptime: float | None = None) -> float:
    """Where the peak charge reaches ``full_well`` [e-]: peak is proportional to 10^(-0.4 m)."""
    rows = _rows(band, sca)
    ratio = 1.0 if exptime is None else exptime / exptime_s()
    return float(rows["magnitude"][0] + 2.5 * np.log10(rows["peak_electrons"][0] * ratio / full_well))
