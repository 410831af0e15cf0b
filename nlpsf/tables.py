"""Precomputed slope tables: what the calculator reads instead of simulating.

For every SCA (1-18) and imaging band, on a magnitude grid from 1.5 mag brighter than saturation
to m = 28 in steps of 0.25 mag (0.125 mag up to a magnitude fainter than saturation), the table
holds at the paper's defaults (168.1 s, beta0 = 5e-7, N = 3, 96 x 96, 100 centroid realizations,
seed 1, weight cut rho^2 = 25):

- bias slopes d(Delta R/R)/d beta, d(Delta e1)/d beta, d(Delta e2)/d beta at beta0 (paper Fig. 3),
- scatter slopes sigma(metric)/sigma_beta for independent per-pixel beta (paper Fig. 5),

each with the standard error of its mean over the centroid realizations. They are computed with
the linear response at beta0 (exact derivatives of the converged moments at the NL-distorted
image, ``experiment.slopes(method="linear")``), which the tests check against the paper's Monte
Carlo finite differences.

Reading the tables at other conditions is exact, not an approximation: the metrics depend on beta
and flux only through beta * flux, so for exposure t and beta0

    slope(m; t, beta0) = (beta0_table / beta0) * slope_table(m - 2.5 log10(beta0 t / (beta0_table t_table)))

and the same for the scatter slopes; the full well only moves the saturation magnitude. Between
grid points slope / flux is interpolated with a cubic spline (it is smooth and nearly constant at
the faint end); the interpolation error, estimated by leaving each grid point out in turn
(``tablebuild.interpolation_error_estimate``), is stored with the table and added to the stated
uncertainty. Fainter than the grid the slopes follow the linear regime exactly (slope
proportional to flux); brighter than the grid there is no answer.

A second file (``field_slopes.ecsv.gz``, ``nlpsf tables build --field``) holds the same tables at
each SCA's four corner field points, keyed (band, SCA, field point): ``TableSet.at_point`` gives the
tables at one corner keyed like the centre's, which is how ``solver.solve`` reads them for a star at
a corner (``solve_over_field`` asks for every corner).
"""

from __future__ import annotations

import gzip
import json
import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field, replace
from functools import lru_cache
from importlib import resources
from pathlib import Path
from threading import Lock
from typing import Any

import numpy as np

from . import __version__, defaults, roman
from .checks import InputError, check_beta0, check_choice, check_exptime, check_full_well

METRICS = defaults.METRICS
MODES = defaults.MODES
#: Table columns of the three measured metrics (the modulus "e" is derived from e1 and e2).
COLUMN_METRICS = {"size": "dR_over_R", "e1": "de1", "e2": "de2"}
#: The grid starts this far brighter than saturation (in beta0 x flux).
BRIGHT_MARGIN_MAG = 1.5
#: Columns holding slopes (each has ``_err`` and ``_interp`` companions).
SLOPE_COLUMNS: tuple[str, ...] = tuple(f"{mode}_{metric}" for metric in COLUMN_METRICS for mode in MODES)
#: Version of the binary companion's layout.
COMPANION_FORMAT = 1


def shipped_table_path() -> Path:
    return Path(str(resources.files("nlpsf") / "data" / "tables" / "slopes.ecsv"))


def field_table_path() -> Path:
    """The shipped tables at each SCA's four corner field points (``nlpsf solve --over-field``)."""
    return Path(str(resources.files("nlpsf") / "data" / "tables" / "field_slopes.ecsv.gz"))


def table_key(band: str, sca: int, point: int | None = None) -> str:
    """How one table is named in a file's metadata: "H158 18", or "H158 18 p2" at field point 2."""
    return f"{band} {int(sca)}" + (f" p{int(point)}" if point else "")


def companion_path(path: Path) -> Path:
    """The binary companion of an ECSV table file (``.ecsv`` or gzipped ``.ecsv.gz``): the same
    numbers, read without astropy/scipy."""
    name = path.name.removesuffix(".gz").removesuffix(".ecsv")
    return path.with_name(name + ".npz")


# --- piecewise cubics: stored coefficients, evaluated with numpy alone ----------------------------
#
# The slopes are interpolated with scipy's not-a-knot CubicSpline of slope / flux in flux. Building
# it needs scipy (0.5 s to import); evaluating it is a piecewise cubic. So the coefficients are
# computed with scipy when a table is written (``write_companion``) and evaluated here, which keeps
# ``nlpsf solve`` and the service's start free of scipy and astropy. The tests check this evaluation
# against scipy's on every shipped table.


def _spline_coefficients(flux: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Coefficients (4, n - 1) of scipy's CubicSpline of values / flux in flux (flux ascending)."""
    from scipy.interpolate import CubicSpline

    return np.asarray(CubicSpline(flux, values / flux).c, dtype=np.float64)


def _evaluate_cubic(breaks: np.ndarray, coefficients: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Evaluate a piecewise cubic (scipy's PPoly layout: highest power first) at ``x``."""
    index = np.clip(np.searchsorted(breaks, x, side="right") - 1, 0, breaks.size - 2)
    d = x - breaks[index]
    c = coefficients[:, index]
    return ((c[0] * d + c[1]) * d + c[2]) * d + c[3]


# --- reading ----------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SlopeTable:
    """One (band, SCA) table with its interpolants (cubic splines of slope / flux in flux)."""

    band: str
    sca: int
    magnitudes: np.ndarray
    flux_electrons: np.ndarray
    peak_electrons: np.ndarray
    columns: dict[str, np.ndarray]
    settings: dict
    saturation_magnitude: float
    peak_fraction: float
    #: (4, n - 1) piecewise-cubic coefficients per slope column, flux ascending (see above).
    splines: dict[str, np.ndarray]
    #: Corner field point (1-4, ``roman.field_points``) and its pixel position; None: the SCA centre.
    field_point: int | None = None
    position: tuple[float, float] | None = None
    _interpolants: dict = field(default_factory=dict, repr=False)

    @property
    def position_pixels(self) -> tuple[float, float]:
        """Where on the SCA the table's star is (the centre unless it is a field-point table)."""
        return self.position if self.position is not None else (roman.SCA_PIXELS / 2, roman.SCA_PIXELS / 2)

    @property
    def exptime_s(self) -> float:
        return float(self.settings["exptime_s"])

    @property
    def beta0(self) -> float:
        return float(self.settings["beta0"])

    @property
    def throughput(self) -> str:
        """Throughput data the table was built with (tables from before it was a setting: GalSim 2021)."""
        return str(self.settings.get("throughput", "galsim-2021"))

    def _interpolant(self, name: str):
        """(flux ascending, slope/flux evaluator, relative statistical error, interpolation error/flux)."""
        if name not in self._interpolants:
            order = np.argsort(self.flux_electrons)
            flux = self.flux_electrons[order]
            value = self.columns[name][order]
            relative = np.abs(self.columns[f"{name}_err"][order] / np.where(value != 0, value, np.inf))
            interp = self.columns[f"{name}_interp"][order] / flux
            coefficients = self.splines[name]

            def spline(x, flux=flux, coefficients=coefficients):
                return _evaluate_cubic(flux, coefficients, np.asarray(x, dtype=np.float64))

            self._interpolants[name] = (flux, spline, relative, interp)
        return self._interpolants[name]

    def flux_at(self, magnitude) -> np.ndarray:
        return self.flux_electrons[0] * 10 ** (-0.4 * (np.asarray(magnitude, dtype=float) - self.magnitudes[0]))

    def values(self, metric: str, mode: str, magnitude: np.ndarray) -> np.ndarray:
        """Slopes only (no uncertainties), NaN brighter than the grid: for scans."""
        if metric == "e":
            return np.hypot(self.values("e1", mode, magnitude), self.values("e2", mode, magnitude))
        fluxes, spline, _, _ = self._interpolant(f"{mode}_{metric}")
        flux = self.flux_at(magnitude)
        value = spline(np.clip(flux, fluxes[0], fluxes[-1])) * flux
        return np.where(flux > fluxes[-1] * (1 + 1e-9), np.nan, value)

    def lookup(self, metric: str, mode: str, magnitude) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(slope, uncertainty, region) at table conditions; region: -1 brighter than the grid
        (no value), 0 inside, +1 fainter (linear-regime extrapolation: slope / flux constant)."""
        m = np.atleast_1d(np.asarray(magnitude, dtype=float))
        if metric == "e":
            s1, e1, region = self.lookup("e1", mode, m)
            s2, e2, _ = self.lookup("e2", mode, m)
            value = np.hypot(s1, s2)
            with np.errstate(invalid="ignore", divide="ignore"):
                error = np.where(value > 0, np.hypot(s1 * e1, s2 * e2) / value, np.hypot(e1, e2))
            return value, error, region
        fluxes, spline, relative, interp = self._interpolant(f"{mode}_{metric}")
        flux = self.flux_at(m)
        region = np.where(flux > fluxes[-1] * (1 + 1e-9), -1, np.where(flux < fluxes[0] * (1 - 1e-9), 1, 0))
        clipped = np.clip(flux, fluxes[0], fluxes[-1])
        value = spline(clipped) * flux
        statistical = np.interp(clipped, fluxes, relative) * np.abs(value)
        interpolation = np.interp(clipped, fluxes, interp) * flux
        error = np.hypot(statistical, interpolation)
        value = np.where(region < 0, np.nan, value)
        error = np.where(region < 0, np.nan, error)
        return value, error, region

    def slope(
        self, metric: str, mode: str, magnitude, exptime_s: float | None = None, beta0: float | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Slope at other conditions, by the exact beta-flux scaling (see the module docstring)."""
        shift = self.magnitude_shift(exptime_s, beta0)
        value, error, region = self.lookup(metric, mode, np.asarray(magnitude, dtype=float) - shift)
        factor = self.beta0 / (self.beta0 if beta0 is None else beta0)
        return value * factor, error * abs(factor), region

    def magnitude_shift(self, exptime_s: float | None = None, beta0: float | None = None) -> float:
        """How far the table's magnitude axis moves for this exposure and beta0."""
        exptime_s = self.exptime_s if exptime_s is None else exptime_s
        beta0 = self.beta0 if beta0 is None else beta0
        return 2.5 * math.log10((beta0 * exptime_s) / (self.beta0 * self.exptime_s))

    def saturation(self, exptime_s: float | None = None, full_well_e: float | None = None) -> float:
        """Magnitude at which the brightest pixel reaches the full well, at these conditions."""
        exptime_s = self.exptime_s if exptime_s is None else exptime_s
        full_well_e = float(self.settings["full_well_e"]) if full_well_e is None else full_well_e
        # Flux scales with exposure and the limit with the full well: a shift of the table's own.
        shift = 2.5 * math.log10(exptime_s / self.exptime_s) - 2.5 * math.log10(full_well_e / float(self.settings["full_well_e"]))
        return self.saturation_magnitude + shift

    def grid_range(self, exptime_s: float | None = None, beta0: float | None = None) -> tuple[float, float]:
        """Magnitudes the grid covers at these conditions."""
        shift = self.magnitude_shift(exptime_s, beta0)
        return float(self.magnitudes[0] + shift), float(self.magnitudes[-1] + shift)


class TableSet:
    """All tables of one file, keyed by (band, SCA) -- or (band, SCA, field point) in a file of
    field-point tables; each is read on first use (``load_all`` reads all)."""

    def __init__(self, keys: list[tuple], meta: dict, reader):
        self._keys = sorted(keys, key=lambda k: (defaults.BANDS.index(k[0]), *k[1:]))
        self.meta = meta
        self._reader = reader
        self._tables: dict[tuple, SlopeTable] = {}
        # Threads of one service worker may ask for the same table at once: read it once.
        self._lock = Lock()

    def get(self, band: str, sca: int, point: int | None = None) -> SlopeTable:
        key = (roman.check_band(band), roman.check_sca(sca)) + ((int(point),) if point else ())
        table = self._tables.get(key)
        if table is None:
            if key not in self._keys:
                where = f"{key[0]} SCA {key[1]}" + (f" field point {point}" if point else "")
                raise InputError("band", f"no table for {where} in this table set")
            with self._lock:
                table = self._tables.get(key)
                if table is None:
                    table = self._tables[key] = self._reader(key)
        return table

    def load_all(self) -> TableSet:
        """Read every table now (a service does this at start, so no request pays for it)."""
        for key in self._keys:
            self.get(*key)
        return self

    @property
    def tables(self) -> dict[tuple, SlopeTable]:
        """Every table, read now if it was not yet."""
        return {key: self.get(*key) for key in self._keys}

    @property
    def bands(self) -> list[str]:
        return sorted({k[0] for k in self._keys}, key=defaults.BANDS.index)

    @property
    def scas(self) -> list[int]:
        return sorted({k[1] for k in self._keys})

    @property
    def points(self) -> list[int]:
        """The field points this set holds tables at ([] for SCA-centre tables)."""
        return sorted({k[2] for k in self._keys if len(k) > 2})

    def at_point(self, point: int) -> TableSet:
        """The tables at one corner field point, as a set keyed by (band, SCA) like the centre's."""
        keys = [k[:2] for k in self._keys if len(k) > 2 and k[2] == point]
        if not keys:
            raise InputError("point", f"this table set holds no tables at field point {point!r}")
        return TableSet(keys, {**self.meta, "field_point": int(point)}, lambda key: self.get(key[0], key[1], point))


_META_KEYS = ("settings", "fingerprint", "method", "data_version", "code_version")


def write_companion(table, path: Path) -> Path:
    """Write the binary companion of a merged astropy table (written as ECSV to ``path``).

    Layout: ``meta`` (JSON text: the ECSV's metadata, column names, spline columns), and per
    (band, SCA) ``{band}_{sca}`` (rows x columns, magnitude ascending) and ``{band}_{sca}_spline``
    (slope columns x 4 x rows - 1); in a field-point file ``{band}_{sca}_p{point}`` and its
    ``_spline``. The fingerprint ties it to the ECSV it came from.
    """
    names = [n for n in table.colnames if n not in _KEY_COLUMNS]
    arrays: dict[str, np.ndarray] = {}
    keys = []
    for key, rows in _groups(table):
        data = np.column_stack([np.asarray(table[n][rows], dtype=np.float64) for n in names])
        data = data[np.argsort(data[:, names.index("magnitude")])]
        flux = data[:, names.index("flux_electrons")]
        order = np.argsort(flux)
        arrays[_array_name(key)] = data
        arrays[f"{_array_name(key)}_spline"] = np.stack(
            [_spline_coefficients(flux[order], data[order, names.index(c)]) for c in SLOPE_COLUMNS]
        )
        keys.append(list(key))
    meta = {k: table.meta[k] for k in (*_META_KEYS, "per_table") if k in table.meta}
    meta.update(columns=names, spline_columns=list(SLOPE_COLUMNS), keys=keys, companion_format=COMPANION_FORMAT)
    destination = companion_path(Path(path))
    temporary = destination.with_name(destination.name + ".tmp.npz")
    np.savez_compressed(temporary, meta=np.array(json.dumps(meta)), **arrays)
    temporary.replace(destination)
    return destination


#: Columns that say which table a row belongs to.
_KEY_COLUMNS = ("band", "sca", "field_point")


def _groups(table) -> list[tuple[tuple, np.ndarray]]:
    """(key, row mask) of every table in a merged file: (band, SCA) or (band, SCA, field point)."""
    columns = [np.asarray(table["band"]).astype(str), np.asarray(table["sca"], dtype=int)]
    if "field_point" in table.colnames:
        columns.append(np.asarray(table["field_point"], dtype=int))
    labels = np.rec.fromarrays(columns)
    keys, inverse = np.unique(labels, return_inverse=True)
    out = [((str(key[0]), *(int(v) for v in tuple(key)[1:])), inverse.ravel() == k) for k, key in enumerate(keys)]
    return sorted(out, key=lambda item: item[0])


def _array_name(key: tuple) -> str:
    return "_".join(str(part) if k < 2 else f"p{part}" for k, part in enumerate(key))


def _table_from_arrays(key: tuple, data: np.ndarray, splines: np.ndarray, meta: dict) -> SlopeTable:
    names = meta["columns"]
    column = {name: data[:, k].copy() for k, name in enumerate(names) if name not in _KEY_COLUMNS}
    info = meta["per_table"][table_key(*key)]
    return SlopeTable(
        band=key[0],
        sca=key[1],
        magnitudes=column["magnitude"],
        flux_electrons=column["flux_electrons"],
        peak_electrons=column["peak_electrons"],
        columns={n: v for n, v in column.items() if n.startswith(("bias_", "scatter_"))},
        settings=dict(meta["settings"]),
        saturation_magnitude=float(info["saturation_magnitude"]),
        peak_fraction=float(info["peak_fraction"]),
        splines=dict(zip(meta["spline_columns"], splines, strict=True)),
        field_point=int(key[2]) if len(key) > 2 else None,
        position=tuple(float(v) for v in info["position"]) if "position" in info else None,
    )


def _public_meta(meta: dict, source: Path) -> dict:
    out = {k: meta[k] for k in _META_KEYS if k in meta}
    # The file's name only: a server must not disclose where it is installed.
    out["source"] = source.name
    return out


@lru_cache(maxsize=4)
def load_tables(path: str | None = None) -> TableSet:
    """Open a table file (the shipped one by default). Cached: the calculator never re-reads.

    Reads the binary companion (numpy alone, milliseconds) when it is there and matches the ECSV's
    fingerprint; otherwise parses the ECSV with astropy and builds the splines with scipy.
    """
    source = Path(path) if path is not None else shipped_table_path()
    if not source.exists():
        raise InputError("tables", f"no table file named {source.name}; build one with `nlpsf tables build`")
    companion = companion_path(source)
    if companion.exists():
        archive = np.load(companion, allow_pickle=False)
        meta = json.loads(str(archive["meta"]))
        if meta.get("companion_format") == COMPANION_FORMAT and _ecsv_fingerprint(source) == meta.get("fingerprint"):
            keys = [(str(k[0]), *map(int, k[1:])) for k in meta["keys"]]

            def read(key: tuple) -> SlopeTable:
                name = _array_name(key)
                return _table_from_arrays(key, archive[name], archive[f"{name}_spline"], meta)

            return TableSet(keys, _public_meta(meta, source), read)
    return _load_ecsv(source)


def _ecsv_fingerprint(path: Path) -> str | None:
    """The ``fingerprint`` in an ECSV file's YAML header, read without parsing the file."""
    pattern = re.compile(r"^#\s*-?\s*\{?\s*fingerprint:\s*['\"]?([0-9a-f]+)")
    opener = gzip.open if path.name.endswith(".gz") else open
    with opener(path, "rt") as handle:
        for line in handle:
            if not line.startswith("#"):
                break
            match = pattern.match(line)
            if match:
                return match.group(1)
    return None


def _load_ecsv(source: Path) -> TableSet:
    from astropy.table import Table

    table = Table.read(source, format="ascii.ecsv")
    per_table = table.meta["per_table"]
    names = [n for n in table.colnames if n not in _KEY_COLUMNS]
    meta: dict[str, Any] = {k: table.meta[k] for k in _META_KEYS if k in table.meta}
    meta.update(columns=names, spline_columns=list(SLOPE_COLUMNS), per_table=per_table)
    out = {}
    for key, rows in _groups(table):
        key = (str(key[0]), *map(int, key[1:]))
        data = np.column_stack([np.asarray(table[n][rows], dtype=np.float64) for n in names])
        data = data[np.argsort(data[:, names.index("magnitude")])]
        flux = data[:, names.index("flux_electrons")]
        order = np.argsort(flux)
        splines = np.stack([_spline_coefficients(flux[order], data[order, names.index(c)]) for c in SLOPE_COLUMNS])
        out[key] = _table_from_arrays(key, data, splines, meta)
    return TableSet(list(out), _public_meta(meta, source), out.__getitem__)


#: Largest relative change of the slopes from reading a table with another throughput's photometry
#: (``with_throughput``) instead of rebuilding it, per band: (size, ellipticity against |c_e|). It is
#: the achromatic PSF's effective wavelength, which moves with the curve's shape. Measured by
#: relabelling the shipped roman-2024 tables to galsim-2021 against a full galsim-2021 build (all
#: 18 SCAs, m = 19, 20 and 22, bias and scatter); the saturation magnitudes agreed to 0.012 mag.
RELABEL_ERROR: dict[str, tuple[float, float]] = {
    "R062": (0.002, 0.005),
    "Z087": (0.001, 0.008),
    "Y106": (0.010, 0.034),
    "J129": (0.017, 0.031),
    "H158": (0.015, 0.033),
    "F184": (0.009, 0.018),
    "W146": (0.016, 0.028),
    "K213": (0.018, 0.046),
}


def with_throughput(table: SlopeTable, throughput: str) -> tuple[SlopeTable, float]:
    """The table read with another throughput's photometry, and the magnitude shift that takes.

    The slopes depend on the star only through its electrons (and the PSF), so each row keeps its
    flux and slopes and is relabelled with the magnitude that gives that flux under ``throughput``:
    m_new = m_table - 2.5 log10(rate_table / rate_new), rates the e-/s of an m = 0 star on this
    SCA. What it does not change is the achromatic PSF's wavelength (the band's effective
    wavelength under the table's curve): see ``RELABEL_ERROR``.
    """
    from . import photometry  # astropy units: only a relabelled read needs them

    roman.check_throughput(throughput)
    if throughput == table.throughput:
        return table, 0.0
    ours = photometry.electrons_per_second_at_zero_magnitude(table.band, sca=table.sca, throughput=table.throughput)
    theirs = photometry.electrons_per_second_at_zero_magnitude(table.band, sca=table.sca, throughput=throughput)
    shift = 2.5 * math.log10(ours / theirs)
    relabelled = replace(
        table,
        magnitudes=table.magnitudes - shift,
        settings={**table.settings, "throughput": throughput, "relabelled_from": table.throughput},
        saturation_magnitude=table.saturation_magnitude - shift,
        _interpolants=table._interpolants,  # same fluxes, same splines
    )
    return relabelled, shift


def check_metric_mode(metric: str, mode: str) -> tuple[str, str]:
    return check_choice(metric, "metric", METRICS), check_choice(mode, "mode", MODES)


def curve(
    band: str,
    sca: int = 18,
    metric: str = "size",
    mode: str = "bias",
    exptime: float = defaults.EXPTIME_S,
    beta0: float = defaults.BETA0,
    full_well: float = defaults.FULL_WELL_E,
    step: float = 0.25,
    tables: TableSet | None = None,
) -> dict:
    """Slope vs magnitude for plotting (the paper's Figs. 3 and 5), at the given conditions."""
    check_metric_mode(metric, mode)
    exptime = check_exptime(exptime)
    beta0 = check_beta0(beta0)
    full_well = check_full_well(full_well)
    table = (tables or load_tables()).get(band, sca)
    lo, hi = table.grid_range(exptime, beta0)
    m = np.round(np.arange(math.ceil(lo / step) * step, hi + step / 2, step), 6)
    value, error, _ = table.slope(metric, mode, m, exptime, beta0)
    ok = np.isfinite(value)
    return {
        "band": table.band,
        "sca": table.sca,
        "metric": metric,
        "mode": mode,
        "magnitude": m[ok].tolist(),
        "slope": value[ok].tolist(),
        "uncertainty": error[ok].tolist(),
        "saturation_magnitude": table.saturation(exptime, full_well),
        "conditions": _conditions(table, exptime, beta0, full_well),
    }


def _conditions(table: SlopeTable, exptime: float, beta0: float, full_well: float) -> dict:
    s = table.settings
    return {
        "band": table.band,
        "sca": table.sca,
        "exptime_s": exptime,
        "beta0": beta0,
        "full_well_e": full_well,
        "oversampling": s["oversampling"],
        "stamp": s["stamp"],
        "realizations": s["realizations"],
        "seed": s["seed"],
        "weight_cut_rho2": s["weight_cut_rho2"],
        "pupil_scale": s["pupil_scale"],
        "throughput": table.throughput,
        "throughput_version": roman.THROUGHPUT_VERSIONS[table.throughput],
        "fidelity": "table",
        "table_conditions": {"exptime_s": s["exptime_s"], "beta0": s["beta0"]},
        "data_version": roman.DATA_VERSION,
        "code_version": __version__,
    }


def table_rows(band: str | None = None, sca: int | None = None, tables: TableSet | None = None) -> list[dict]:
    """Flat rows of the shipped tables (for JSON or CSV download), optionally one band/SCA."""
    tables = tables or load_tables()
    rows = []
    for key, table in tables.tables.items():
        b, s = key[:2]
        if (band is not None and b != roman.check_band(band)) or (sca is not None and s != roman.check_sca(sca)):
            continue
        for k, m in enumerate(table.magnitudes):
            row = {
                "band": b,
                "sca": s,
                **({"field_point": table.field_point} if table.field_point else {}),
                "magnitude": float(m),
                "flux_electrons": float(table.flux_electrons[k]),
                "peak_electrons": float(table.peak_electrons[k]),
                "saturated": bool(table.peak_electrons[k] > table.settings["full_well_e"]),
            }
            for name, values in table.columns.items():
                row[name] = float(values[k])
            rows.append(row)
    if not rows:
        raise InputError("band" if band is not None else "sca", "no table matches")
    return rows


# --- power-law fits (the paper's Table 2) ------------------------------------------------------

PAPER_FIT_RANGE = (18.3, 22.0)


def powerlaw_fit(table: SlopeTable, mode: str = "bias", metric: str = "size", magnitude_range=PAPER_FIT_RANGE) -> dict:
    """slope = A 10^(B (m - 20)) fitted in log10 over the paper's magnitude range.

    The slopes are known far better (1e-5) than a power law describes them (the nonlinearity bends
    the curve near saturation), so the fit is unweighted and A, B carry the uncertainty the
    residuals imply, not the slopes' own.
    """
    m = np.arange(magnitude_range[0], magnitude_range[1] + 1e-9, 0.1)
    value, _, _ = table.slope(metric, mode, m)
    y = np.log10(np.abs(value))
    design = np.vstack([np.ones_like(m), m - 20.0]).T
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    model = design @ coef
    variance = float(np.sum((y - model) ** 2) / (m.size - 2))
    cov = variance * np.linalg.inv(design.T @ design)
    residual = 10 ** (y - model) - 1.0
    return {
        "band": table.band,
        "sca": table.sca,
        "mode": mode,
        "metric": metric,
        "A": float(10 ** coef[0]),
        "A_err": float(10 ** coef[0] * math.log(10) * math.sqrt(cov[0, 0])),
        "B": float(coef[1]),
        "B_err": float(math.sqrt(cov[1, 1])),
        "max_relative_residual": float(np.abs(residual).max()),
        "rms_relative_residual": float(np.sqrt(np.mean(residual**2))),
        "magnitude_range": list(magnitude_range),
    }


def powerlaw_fits(
    bands: Iterable[str] | None = None, scas: Iterable[int] | None = None, tables: TableSet | None = None
) -> list[dict]:
    """Table 2 fits for size bias and size scatter, every band and SCA requested."""
    tables = tables or load_tables()
    bands = list(bands) if bands is not None else tables.bands
    scas = list(scas) if scas is not None else tables.scas
    return [powerlaw_fit(tables.get(b, s), mode) for b in bands for s in scas for mode in MODES]


def paper_data() -> dict:
    """The paper's own published figure data (Figs. 2, 3, 5 and Table 2; Cycle-5 optics)."""
    path = Path(str(resources.files("nlpsf") / "data" / "paper" / "published_data.json"))
    return json.loads(path.read_text())


def table2_comparison(tables: TableSet | None = None, sca: int = 18) -> list[dict]:
    """Our Table 2 beside the paper's, with the ratio of A split into its two causes.

    A = slope at m = 20 = flux(20) x (slope per electron). The flux part is the throughput change
    (the table's effective areas vs the paper's Cycle 5); what remains is the optics (Cycle-9 vs Cycle-5
    PSF shape), the same 5.7 % drop for every band only if the optics did not change.
    """
    from . import photometry  # astropy units: only this comparison needs them

    tables = tables or load_tables()
    paper = paper_data()
    table2 = paper["table2_powerlaw"]
    # Paper Table 1: baseline electrons at m = 18.3 in 168.1 s (Cycle-5 throughput, GalSim 1.3).
    paper_flux_183 = {"Y106": 2.7621e5, "J129": 2.8267e5, "H158": 2.7922e5, "F184": 1.8346e5}
    rows = []
    for band in ("Y106", "J129", "H158", "F184"):
        table = tables.get(band, sca)
        ours = {mode: powerlaw_fit(table, mode) for mode in MODES}
        flux = photometry.magnitude_to_electrons(18.3, band, defaults.EXPTIME_S, sca=sca, throughput=table.throughput)
        flux_ratio = float(flux) / paper_flux_183[band]
        for mode in MODES:
            a_paper, b_paper = table2[mode][band]
            ratio = ours[mode]["A"] / a_paper
            rows.append(
                {
                    "band": band,
                    "sca": sca,
                    "mode": mode,
                    "A_ours": ours[mode]["A"],
                    "A_err": ours[mode]["A_err"],
                    "B_ours": ours[mode]["B"],
                    "B_err": ours[mode]["B_err"],
                    "A_paper": a_paper,
                    "B_paper": b_paper,
                    "A_ratio": ratio,
                    "throughput_ratio": flux_ratio,
                    "optics_ratio": ratio / flux_ratio,
                    "max_relative_residual": ours[mode]["max_relative_residual"],
                }
            )
    return rows


def table2_markdown(sca: int = 18) -> str:
    rows = table2_comparison(sca=sca)
    lines = [
        "| band | fit | A (nlpsf) | B (nlpsf) | A (paper) | B (paper) | A ratio | throughput | optics | max residual |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['band']} | size {r['mode']} | {r['A_ours']:.0f} ± {r['A_err']:.0f} | {r['B_ours']:.4f} ± {r['B_err']:.4f} | "
            f"{r['A_paper']:.0f} | {r['B_paper']:.4f} | {r['A_ratio']:.3f} | {r['throughput_ratio']:.3f} | "
            f"{r['optics_ratio']:.3f} | "
            f"{100 * r['max_relative_residual']:.2f} % |"
        )
    return "\n".join(lines)
