"""The table model: one (band, SCA) table of slopes and its interpolants, and a set of them.

``SlopeTable`` reads a slope at any magnitude, exposure and beta0 by the exact beta-flux scaling
(see the package docstring); ``TableSet`` holds a file's tables, each read on first use;
``with_throughput`` relabels a table's magnitudes with another throughput's photometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from threading import Lock

import numpy as np

from nlpsf import defaults, roman
from nlpsf.checks import InputError

from .splines import evaluate_cubic, not_a_knot_spline

METRICS = defaults.METRICS
MODES = defaults.MODES
#: Table columns of the three measured metrics (the modulus "e" is derived from e1 and e2).
COLUMN_METRICS = {"size": "dR_over_R", "e1": "de1", "e2": "de2"}
#: The grid starts this far brighter than saturation (in beta0 x flux).
BRIGHT_MARGIN_MAG = 1.5
#: Columns holding slopes (each has ``_err`` and ``_interp`` companions).
SLOPE_COLUMNS: tuple[str, ...] = tuple(f"{mode}_{metric}" for metric in COLUMN_METRICS for mode in MODES)


def table_key(band: str, sca: int, point: int | None = None) -> str:
    """How one table is named in a file's metadata: "H158 18", or "H158 18 p2" at field point 2."""
    return f"{band} {int(sca)}" + (f" p{int(point)}" if point else "")


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
    #: Per slope column, its spline as scipy's public ``PPoly`` holds it, (breakpoints x: the flux
    #: ascending, coefficients c (4, rows - 1)), read from the runtime file and evaluated with numpy. A
    #: column without one (a table read from its ECSV) has it built with scipy when first read.
    splines: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
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
            stored = self.splines.get(name)
            breaks, coefficients = stored if stored is not None else not_a_knot_spline(flux, self.columns[name][order])

            def spline(x, breaks=breaks, coefficients=coefficients):
                return evaluate_cubic(breaks, coefficients, np.asarray(x, dtype=np.float64))

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
        value = spline(np.minimum(np.maximum(flux, fluxes[0]), fluxes[-1])) * flux
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
        clipped = np.minimum(np.maximum(flux, fluxes[0]), fluxes[-1])
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
        """Slope at other conditions, by the exact beta-flux scaling (see the ``nlpsf.slopes.tables`` docstring)."""
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
        table = self._tables.get((band, sca) + ((point,) if point else ()))  # a request's band and SCA, checked once
        if table is not None:
            return table
        # A band already in its checked form (a request's) is not checked again; another is (a caller's own).
        checked = band if band in defaults.BANDS else roman.check_band(band)
        key = (checked, roman.check_sca(sca)) + ((int(point),) if point else ())
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
    from nlpsf.roman import photometry  # astropy units: only a relabelled read needs them

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
