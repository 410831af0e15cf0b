"""Precomputed slope tables: what the calculator reads instead of simulating.

For every SCA (1-18) and imaging band, on a magnitude grid from 1.5 mag brighter than saturation
to m = 28 in steps of 0.25 mag, the table holds at the paper's defaults (168.1 s, beta0 = 5e-7,
N = 3, 96 x 96, 100 centroid realizations, seed 1, weight cut rho^2 = 25):

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
the faint end); the interpolation error, measured by leaving every other grid point out, is stored
with the table and added to the stated uncertainty. Fainter than the grid the slopes follow the
linear regime exactly (slope proportional to flux); brighter than the grid there is no answer.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np
from astropy.table import Table, vstack
from scipy.interpolate import CubicSpline

from . import __version__, experiment, photometry, roman
from .checks import InputError, check_integer, check_number

METRICS = ("size", "e1", "e2", "e")
MODES = ("bias", "scatter")
#: Table columns of the three measured metrics (the modulus "e" is derived from e1 and e2).
_COLUMN_METRICS = {"size": "dR_over_R", "e1": "de1", "e2": "de2"}
FAINT_LIMIT = 28.0
BRIGHT_MARGIN_MAG = 1.5
MAGNITUDE_STEP = 0.25
#: Where the nonlinearity is strong (up to a magnitude fainter than saturation) the grid is twice
#: as fine, so that interpolation stays below the statistical error there too.
BRIGHT_STEP_FACTOR = 0.5


def shipped_table_path() -> Path:
    return Path(str(resources.files("nlpsf") / "data" / "tables" / "slopes.ecsv"))


@dataclass(frozen=True)
class TableSettings:
    """How a set of tables is computed. Defaults are the paper's."""

    exptime_s: float = roman.DEFAULT_EXPTIME_S
    beta0: float = 5e-7
    full_well_e: float = roman.DEFAULT_FULL_WELL_E
    oversampling: int = 3
    stamp: int = 96
    realizations: int = 100
    seed: int = 1
    weight_cut_rho2: float = 25.0
    pupil_scale: str = "galsim"
    magnitude_step: float = MAGNITUDE_STEP
    faint_limit: float = FAINT_LIMIT

    def config(self, band: str, sca: int) -> experiment.SimulationConfig:
        return experiment.SimulationConfig(
            band=band,
            sca=sca,
            realizations=self.realizations,
            seed=self.seed,
            oversampling=self.oversampling,
            stamp=self.stamp,
            exptime_s=self.exptime_s,
            full_well_e=self.full_well_e,
            weight_cut_rho2=self.weight_cut_rho2,
            pupil_scale=self.pupil_scale,
            method="linear",
        )

    def fingerprint(self) -> str:
        """Identifies the settings and code a table was made with (resuming skips matching ones)."""
        text = json.dumps({**asdict(self), "code": __version__, "data": roman.DATA_VERSION}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def saturation_magnitude(peak_fraction: float, band: str, exptime_s: float, full_well_e: float, oversampling: int) -> float:
    """Magnitude at which the brightest fine pixel (over centroids) reaches the full well."""
    electrons_at_full_well = full_well_e / (peak_fraction * oversampling**2)
    return float(photometry.electrons_to_magnitude(electrons_at_full_well, band, exptime_s))


def magnitude_grid(saturation: float, step: float = MAGNITUDE_STEP, faint_limit: float = FAINT_LIMIT) -> np.ndarray:
    """From BRIGHT_MARGIN_MAG brighter than saturation to ``faint_limit``, finer at the bright end."""
    fine = step * BRIGHT_STEP_FACTOR
    first = math.floor((saturation - BRIGHT_MARGIN_MAG) / step) * step
    switch = math.ceil((saturation + 1.0) / step) * step
    bright = np.arange(first, switch, fine)
    faint = np.arange(switch, faint_limit + step / 2, step)
    return np.round(np.concatenate([bright, faint]), 6)


def compute_table(band: str, sca: int, settings: TableSettings | None = None, progress=None) -> Table:
    """The slope table of one (band, SCA)."""
    settings = settings or TableSettings()
    start = time.perf_counter()
    config = settings.config(band, sca)
    scene = experiment.prepare(config)
    m_sat = saturation_magnitude(
        float(scene.peak_fraction.max()), config.band, settings.exptime_s, settings.full_well_e, settings.oversampling
    )
    magnitudes = magnitude_grid(m_sat, settings.magnitude_step, settings.faint_limit)
    results = experiment.slopes(config, list(magnitudes), beta0=settings.beta0, scene=scene, progress=progress)
    columns: dict[str, list] = {"magnitude": list(magnitudes), "flux_electrons": [], "peak_electrons": []}
    for metric in _COLUMN_METRICS:
        for mode in MODES:
            columns[f"{mode}_{metric}"] = []
            columns[f"{mode}_{metric}_err"] = []
    columns["failed_realizations"] = []
    for r in results:
        columns["flux_electrons"].append(r.flux_electrons)
        columns["peak_electrons"].append(r.peak_electrons)
        columns["failed_realizations"].append(r.failed_realizations)
        for metric, name in _COLUMN_METRICS.items():
            bias = r.bias[name]
            columns[f"bias_{metric}"].append(np.nan if bias.mean is None else bias.mean)
            columns[f"bias_{metric}_err"].append(np.nan if bias.stderr is None else bias.stderr)
            scatter = r.scatter[name]
            columns[f"scatter_{metric}"].append(np.nan if scatter["value"] is None else scatter["value"])
            columns[f"scatter_{metric}_err"].append(np.nan if scatter["uncertainty"] is None else scatter["uncertainty"])
    flux = np.asarray(columns["flux_electrons"])
    for metric in _COLUMN_METRICS:
        for mode in MODES:
            name = f"{mode}_{metric}"
            columns[f"{name}_interp"] = list(interpolation_error_estimate(flux, np.asarray(columns[name])))
    table = Table(columns)
    table.add_column(band, name="band", index=0)
    table.add_column(np.int16(sca), name="sca", index=1)
    table.meta.update(
        {
            "band": band,
            "sca": int(sca),
            "saturation_magnitude": m_sat,
            "peak_fraction": float(scene.peak_fraction.max()),
            "settings": asdict(settings),
            "fingerprint": settings.fingerprint(),
            "method": "linear response at beta0, mean over centroid realizations",
            "data_version": roman.DATA_VERSION,
            "code_version": __version__,
            "elapsed_s": time.perf_counter() - start,
        }
    )
    return table


def _partial_path(directory: Path, band: str, sca: int) -> Path:
    return directory / f"slopes_{band}_SCA{sca:02d}.ecsv"


def _compute_and_write(band: str, sca: int, settings: TableSettings, directory: str) -> tuple[str, int, float]:
    table = compute_table(band, sca, settings)
    path = _partial_path(Path(directory), band, sca)
    temporary = path.with_suffix(".tmp")
    table.write(temporary, format="ascii.ecsv", overwrite=True)
    temporary.replace(path)  # atomic: an interrupted build never leaves half a table behind
    return band, sca, float(table.meta["elapsed_s"])


def build_tables(
    directory: Path | str,
    bands: Iterable[str] = roman.BANDS,
    scas: Iterable[int] = range(1, roman.N_SCA + 1),
    settings: TableSettings | None = None,
    workers: int = 1,
    dask_address: str | None = None,
    progress: Callable[[int, int, str], None] | None = None,
) -> list[Path]:
    """Compute every (band, SCA) table into ``directory``, skipping those already done.

    Work is spread over ``workers`` local processes, or over a dask.distributed cluster when
    ``dask_address`` is given ("local" starts a LocalCluster with ``workers`` workers).
    Interrupting and re-running resumes where it stopped.
    """
    settings = settings or TableSettings()
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    todo, done = [], []
    pairs = [(roman.check_band(b), roman.check_sca(s)) for b in bands for s in scas]
    for band, sca in pairs:
        path = _partial_path(directory, band, sca)
        if path.exists() and Table.read(path, format="ascii.ecsv").meta.get("fingerprint") == settings.fingerprint():
            done.append(path)
        else:
            todo.append((band, sca))
    total = len(pairs)
    if progress:
        progress(len(done), total, "resumed" if done else "starting")
    if dask_address is not None:
        finished = _run_dask(todo, settings, str(directory), workers, dask_address)
    elif workers > 1 and len(todo) > 1:
        finished = _run_processes(todo, settings, str(directory), workers)
    else:
        finished = (_compute_and_write(band, sca, settings, str(directory)) for band, sca in todo)
    for count, (band, sca, elapsed) in enumerate(finished, start=len(done) + 1):
        done.append(_partial_path(directory, band, sca))
        if progress:
            progress(count, total, f"{band} SCA {sca} ({elapsed:.1f} s)")
    return done


def _run_processes(todo, settings, directory, workers):
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures = [pool.submit(_compute_and_write, band, sca, settings, directory) for band, sca in todo]
        for future in as_completed(futures):
            yield future.result()


def _run_dask(todo, settings, directory, workers, address):
    try:
        from dask.distributed import Client, LocalCluster
        from dask.distributed import as_completed as dask_completed
    except ImportError as error:  # pragma: no cover - depends on the optional extra
        raise InputError("dask", "dask.distributed is not installed: pip install 'nlpsf[dask]'") from error
    cluster = LocalCluster(n_workers=max(workers, 1), threads_per_worker=1, processes=True) if address == "local" else None
    client = Client(cluster if cluster is not None else address)
    try:
        futures = [client.submit(_compute_and_write, band, sca, settings, directory, pure=False) for band, sca in todo]
        for future in dask_completed(futures):
            yield future.result()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def merge_tables(paths: Iterable[Path], destination: Path | str) -> Table:
    """Stack per-(band, SCA) tables into one file with their metadata kept per table."""
    tables = [Table.read(p, format="ascii.ecsv") for p in sorted(paths)]
    if not tables:
        raise InputError("tables", "nothing to merge")
    fingerprints = {t.meta["fingerprint"] for t in tables}
    if len(fingerprints) != 1:
        raise InputError("tables", f"the partial tables were made with different settings: {sorted(fingerprints)}")
    per_table = {
        f"{t.meta['band']} {t.meta['sca']}": {k: t.meta[k] for k in ("saturation_magnitude", "peak_fraction", "elapsed_s")}
        for t in tables
    }
    merged = vstack([Table(t, meta={}) for t in tables], metadata_conflicts="silent")
    merged.meta.update(
        {
            "description": "nlpsf slope tables: bias slopes d(metric)/dbeta and scatter slopes sigma(metric)/sigma_beta",
            "settings": tables[0].meta["settings"],
            "fingerprint": tables[0].meta["fingerprint"],
            "method": tables[0].meta["method"],
            "data_version": tables[0].meta["data_version"],
            "code_version": tables[0].meta["code_version"],
            "per_table": per_table,
            "units": {
                "magnitude": "AB mag",
                "flux_electrons": "e-",
                "peak_electrons": "e- per fine pixel x N^2",
                "bias_*": "per (1/e-) of beta",
                "scatter_*": "per (1/e-) of sigma_beta",
            },
        }
    )
    Path(destination).parent.mkdir(parents=True, exist_ok=True)
    merged.write(destination, format="ascii.ecsv", overwrite=True)
    return merged


def interpolation_error_estimate(flux: np.ndarray, slope: np.ndarray) -> np.ndarray:
    """Estimated error of interpolating slope / flux with a cubic spline in flux, per grid point.

    Leave each interior point out, interpolate it back from the others (which doubles the local
    spacing) and divide by 2^4, the factor by which a cubic spline's error grows when the spacing
    doubles. End points take their neighbour's estimate. The tests check the estimate against
    fresh simulations between grid points.
    """
    order = np.argsort(flux)
    x, q = flux[order], slope[order] / flux[order]
    estimate = np.zeros_like(q)
    for k in range(1, q.size - 1):
        keep = np.ones(q.size, dtype=bool)
        keep[k] = False
        estimate[k] = abs(CubicSpline(x[keep], q[keep])(x[k]) - q[k]) / 16.0
    estimate[0], estimate[-1] = estimate[1], estimate[-2]
    out = np.empty_like(estimate)
    out[order] = estimate * x  # back to slope units
    return out


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
    _interpolants: dict = field(default_factory=dict, repr=False)

    @property
    def exptime_s(self) -> float:
        return float(self.settings["exptime_s"])

    @property
    def beta0(self) -> float:
        return float(self.settings["beta0"])

    def _interpolant(self, name: str):
        """(spline of slope/flux, relative statistical error, interpolation error/flux) vs flux."""
        if name not in self._interpolants:
            order = np.argsort(self.flux_electrons)
            flux = self.flux_electrons[order]
            value = self.columns[name][order]
            relative = np.abs(self.columns[f"{name}_err"][order] / np.where(value != 0, value, np.inf))
            interp = self.columns[f"{name}_interp"][order] / flux
            self._interpolants[name] = (flux, CubicSpline(flux, value / flux), relative, interp)
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


@dataclass(frozen=True, eq=False)
class TableSet:
    """All shipped tables, keyed by (band, SCA)."""

    tables: dict[tuple[str, int], SlopeTable]
    meta: dict

    def get(self, band: str, sca: int) -> SlopeTable:
        key = (roman.check_band(band), roman.check_sca(sca))
        if key not in self.tables:
            raise InputError("band", f"no table for {key[0]} SCA {key[1]} in this table set")
        return self.tables[key]

    @property
    def bands(self) -> list[str]:
        return sorted({b for b, _ in self.tables}, key=roman.BANDS.index)

    @property
    def scas(self) -> list[int]:
        return sorted({s for _, s in self.tables})


@lru_cache(maxsize=4)
def load_tables(path: str | None = None) -> TableSet:
    """Read a table file (the shipped one by default). Cached: the calculator never re-reads."""
    source = Path(path) if path is not None else shipped_table_path()
    if not source.exists():
        raise InputError("tables", f"no table file at {source}; build one with `nlpsf tables build`")
    table = Table.read(source, format="ascii.ecsv")
    settings = dict(table.meta["settings"])
    per_table = table.meta["per_table"]
    out: dict[tuple[str, int], SlopeTable] = {}
    bands = np.asarray(table["band"]).astype(str)
    scas = np.asarray(table["sca"], dtype=int)
    for key in sorted(set(zip(bands, scas, strict=True))):
        rows = table[(bands == key[0]) & (scas == key[1])]
        rows.sort("magnitude")
        columns = {name: np.asarray(rows[name], dtype=float) for name in rows.colnames if name.startswith(("bias_", "scatter_"))}
        info = per_table[f"{key[0]} {key[1]}"]
        out[(str(key[0]), int(key[1]))] = SlopeTable(
            band=str(key[0]),
            sca=int(key[1]),
            magnitudes=np.asarray(rows["magnitude"], dtype=float),
            flux_electrons=np.asarray(rows["flux_electrons"], dtype=float),
            peak_electrons=np.asarray(rows["peak_electrons"], dtype=float),
            columns=columns,
            settings=settings,
            saturation_magnitude=float(info["saturation_magnitude"]),
            peak_fraction=float(info["peak_fraction"]),
        )
    meta = {k: table.meta[k] for k in ("settings", "fingerprint", "method", "data_version", "code_version") if k in table.meta}
    meta["source"] = str(source)
    return TableSet(out, meta)


def check_metric_mode(metric: str, mode: str) -> tuple[str, str]:
    if metric not in METRICS:
        raise InputError("metric", f"must be one of {', '.join(METRICS)}, got {metric!r}")
    if mode not in MODES:
        raise InputError("mode", f"must be one of {', '.join(MODES)}, got {mode!r}")
    return metric, mode


def curve(
    band: str,
    sca: int = 18,
    metric: str = "size",
    mode: str = "bias",
    exptime: float = roman.DEFAULT_EXPTIME_S,
    beta0: float = 5e-7,
    full_well: float = roman.DEFAULT_FULL_WELL_E,
    step: float = 0.25,
    tables: TableSet | None = None,
) -> dict:
    """Slope vs magnitude for plotting (the paper's Figs. 3 and 5), at the given conditions."""
    check_metric_mode(metric, mode)
    exptime = check_number(exptime, "exptime", *roman.EXPTIME_RANGE_S)
    beta0 = check_number(beta0, "beta0", 1e-12, 1e-3)
    full_well = check_number(full_well, "full_well", *roman.FULL_WELL_RANGE_E)
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
        "fidelity": "table",
        "table_conditions": {"exptime_s": s["exptime_s"], "beta0": s["beta0"]},
        "data_version": roman.DATA_VERSION,
        "code_version": __version__,
    }


def table_rows(band: str | None = None, sca: int | None = None, tables: TableSet | None = None) -> list[dict]:
    """Flat rows of the shipped tables (for JSON or CSV download), optionally one band/SCA."""
    tables = tables or load_tables()
    rows = []
    for (b, s), table in tables.tables.items():
        if (band is not None and b != roman.check_band(band)) or (sca is not None and s != roman.check_sca(sca)):
            continue
        for k, m in enumerate(table.magnitudes):
            row = {
                "band": b,
                "sca": s,
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
    (effective areas of 2021 vs the paper's Cycle 5); what remains is the optics (Cycle-9 vs Cycle-5
    PSF shape), the same 5.7 % drop for every band only if the optics did not change.
    """
    tables = tables or load_tables()
    paper = paper_data()
    table2 = paper["table2_powerlaw"]
    # Paper Table 1: baseline electrons at m = 18.3 in 168.1 s (Cycle-5 throughput, GalSim 1.3).
    paper_flux_183 = {"Y106": 2.7621e5, "J129": 2.8267e5, "H158": 2.7922e5, "F184": 1.8346e5}
    rows = []
    for band in ("Y106", "J129", "H158", "F184"):
        table = tables.get(band, sca)
        ours = {mode: powerlaw_fit(table, mode) for mode in MODES}
        flux_ratio = float(photometry.magnitude_to_electrons(18.3, band, 168.1)) / paper_flux_183[band]
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


# --- command line -----------------------------------------------------------------------------


def _register_cli() -> None:
    from . import cli

    def configure(parser) -> None:
        sub = parser.add_subparsers(dest="tables_command", required=True)
        build = sub.add_parser("build", help="compute the slope tables (resumable)")
        build.add_argument(
            "--output", default="build/tables", help="folder for the per-(band, SCA) tables (default build/tables)"
        )
        build.add_argument("--merge-to", default=None, help="also merge them into this file (e.g. nlpsf/data/tables/slopes.ecsv)")
        build.add_argument("--band", action="append", help="only these bands (repeat); default all")
        build.add_argument("--sca", action="append", type=int, help="only these SCAs (repeat); default all")
        build.add_argument("--workers", type=int, default=1, help="local worker processes (default 1)")
        build.add_argument(
            "--dask", default=None, metavar="ADDRESS", help="run on a dask.distributed scheduler ('local' starts one)"
        )
        build.add_argument("--realizations", type=int, default=100)
        build.add_argument("--faint-limit", type=float, default=FAINT_LIMIT)
        build.add_argument("--step", type=float, default=MAGNITUDE_STEP)
        build.add_argument("--quiet", action="store_true")
        show = sub.add_parser("show", help="print one table")
        show.add_argument("--band", default="H158")
        show.add_argument("--sca", type=int, default=18)
        show.add_argument("--format", choices=("text", "json", "csv"), default="text")
        fits = sub.add_parser("fits", help="power-law fits, the paper's Table 2 form")
        fits.add_argument("--sca", type=int, default=18)
        fits.add_argument("--markdown", action="store_true", help="the side-by-side with the paper's Table 2")
        fits.add_argument("--json", action="store_true")

    @cli.register("tables", configure, "slope tables: build, show, power-law fits")
    def run(args) -> int:
        if args.tables_command == "build":
            return _build_command(args, cli)
        if args.tables_command == "show":
            return _show_command(args)
        return _fits_command(args)


def _build_command(args, cli) -> int:
    check_integer(args.workers, "workers", 1, 256)
    settings = TableSettings(realizations=args.realizations, faint_limit=args.faint_limit, magnitude_step=args.step)
    start = time.perf_counter()
    paths = build_tables(
        args.output,
        bands=args.band or roman.BANDS,
        scas=args.sca or range(1, roman.N_SCA + 1),
        settings=settings,
        workers=args.workers,
        dask_address=args.dask,
        progress=cli._progress_printer(not args.quiet),
    )
    print(f"{len(paths)} tables in {args.output} ({time.perf_counter() - start:.1f} s)", file=sys.stderr)
    if args.merge_to:
        merge_tables(paths, args.merge_to)
        print(f"merged into {args.merge_to}", file=sys.stderr)
    return 0


def _show_command(args) -> int:
    rows = table_rows(args.band, args.sca)
    if args.format == "json":
        print(json.dumps(rows, indent=1))
    elif args.format == "csv":
        Table(rows=[list(r.values()) for r in rows], names=list(rows[0])).write(sys.stdout, format="ascii.csv")
    else:
        print(
            f"{args.band} SCA {args.sca}: bias slopes d(metric)/dbeta and scatter slopes sigma(metric)/sigma_beta "
            "at beta0=5e-7, 168.1 s"
        )
        print(f"{'mag':>6} {'size':>11} {'e1':>10} {'e2':>10} {'size scat':>11} {'e1 scat':>10} {'e2 scat':>10}  saturated")
        for r in rows:
            print(
                f"{r['magnitude']:6.2f} {r['bias_size']:11.5g} {r['bias_e1']:10.4g} {r['bias_e2']:10.4g} "
                f"{r['scatter_size']:11.5g} {r['scatter_e1']:10.4g} {r['scatter_e2']:10.4g}  {'yes' if r['saturated'] else ''}"
            )
    return 0


def _fits_command(args) -> int:
    if args.markdown:
        print(table2_markdown(sca=args.sca))
        return 0
    fits = powerlaw_fits(scas=[args.sca])
    if args.json:
        print(json.dumps(fits, indent=1))
        return 0
    print(f"SCA {args.sca}: slope = A 10^(B (m - 20)) over m = {PAPER_FIT_RANGE[0]}-{PAPER_FIT_RANGE[1]}")
    for f in fits:
        print(
            f"{f['band']:>5} {f['mode']:>8}  A = {f['A']:9.1f} +- {f['A_err']:.1f}  B = {f['B']:.4f} +- {f['B_err']:.4f}  "
            f"max residual {100 * f['max_relative_residual']:.2f} %"
        )
    return 0


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


_register_cli()
