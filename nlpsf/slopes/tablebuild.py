"""Building the slope tables: what ``nlpsf tables build`` runs (see ``nlpsf.slopes.tables`` for what they hold).

For every SCA and band, on a magnitude grid from 1.5 mag brighter than saturation to m = 28 in
steps of 0.25 mag (twice as fine near saturation), the linear response at beta0 gives the bias and
scatter slopes with their standard errors, and a leave-one-out estimate of the interpolation error.
Per-(band, SCA) tables are written atomically into a folder, so an interrupted build resumes; the
workers (local processes or a dask cluster, ``nlpsf.sim.cluster``) return the tables and the client
writes them, so a worker on another machine or in another directory never needs the client's path;
``merge_tables`` stacks them into the shipped ECSV file and writes its binary companion (the
reading side's fast path, ``tables.write_companion``).
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from astropy.table import Table, vstack
from scipy.interpolate import CubicSpline

from nlpsf import defaults, roman
from nlpsf._version import __version__
from nlpsf.checks import InputError, SimulationError
from nlpsf.request import presets as roman_default
from nlpsf.roman import photometry
from nlpsf.sim import cluster, experiment

from . import fidelity, fieldgrid, gridfile
from .tables import BRIGHT_MARGIN_MAG, COLUMN_METRICS, MODES, ecsv_fingerprint, table_key, write_companion, write_ecsv

FAINT_LIMIT = defaults.TABLE_FAINT_LIMIT
MAGNITUDE_STEP = defaults.TABLE_MAGNITUDE_STEP
#: Where the nonlinearity is strong (up to a magnitude fainter than saturation) the grid is twice
#: as fine, so that interpolation stays below the statistical error there too.
BRIGHT_STEP_FACTOR = 0.5
#: Rows every this many magnitudes between a ramp's saturation limit and the final frame's (the
#: Roman default's recipe, ``TableSettings.roman``): there pixels lose resultants one by one and the
#: slope has a kink at each. The grid shipped until issue 28 had 0.125 mag rows to 1 mag past the
#: ramp's limit and 0.25 after, which missed a node's own fresh value by up to 27 % in size (median
#: 2.5 %, 16 random nodes); 0.125 mag all the way: 2.7 % (median 0.7 %), 0.0625: 7.4 % (0.3 %).
#: The e slopes there move by their centroid noise, which no row step removes (docs/field.md,
#: "Between the saturation limits").
BETWEEN_LIMITS_STEP = 0.125
#: The dense rows reach this far past both limits [mag] (a pixel near a limit still changes there).
BETWEEN_LIMITS_MARGIN_MAG = 0.25


@dataclass(frozen=True)
class TableSettings:
    """How a set of tables is computed. Defaults are the paper's."""

    exptime_s: float = defaults.EXPTIME_S
    beta0: float = defaults.BETA0
    full_well_e: float = defaults.FULL_WELL_E
    oversampling: int = defaults.OVERSAMPLING
    stamp: int = defaults.STAMP
    realizations: int = defaults.REALIZATIONS
    seed: int = defaults.SEED
    weight_cut_rho2: float = defaults.PAPER_WEIGHT_CUT_RHO2
    pupil_scale: str = defaults.PUPIL_SCALE
    magnitude_step: float = MAGNITUDE_STEP
    faint_limit: float = FAINT_LIMIT
    #: Throughput data (``defaults.THROUGHPUTS``): the per-SCA official curves by default.
    throughput: str = defaults.THROUGHPUT
    #: ``fieldgrid.TABLE_SCENES``: "paper" (the shipped tables) or "roman", the candidate Roman default
    #: (``nlpsf.request.presets``; ``TableSettings.roman`` sets its exposure, pupil scale and state).
    scene: str = "paper"
    #: The fidelity level the slopes are computed at: "linear" (the tables') or "polychromatic"
    #: (Monte Carlo on the PSF integrated over 8 wavelengths, ``fidelity.simulation_settings``).
    fidelity: str = "linear"
    #: Where the slopes are taken (``experiment.LINEARISE_STATES``): "beta0" (the paper's) or
    #: "corrected" (the Roman default's).
    linearise_at: str = "beta0"
    #: How a calibration error acts in the corrected state (``experiment.correction.RESIDUAL_MODELS``);
    #: None: the default's there ("per_resultant_correction"), nothing at beta0.
    residual_nl: str | None = None
    #: Rows every this many magnitudes between a ramp's saturation limit and the final frame's
    #: (:data:`BETWEEN_LIMITS_STEP` for the Roman default; None: the plain grid, as the paper tables).
    between_step: float | None = None

    def __post_init__(self) -> None:
        roman.check_throughput(self.throughput)
        if self.scene not in fieldgrid.TABLE_SCENES:
            raise InputError("scene", f"tables are built for the scenes {', '.join(fieldgrid.TABLE_SCENES)}, got {self.scene!r}")
        if self.fidelity not in ("linear", "polychromatic"):
            raise InputError("fidelity", f"tables are built at fidelity linear or polychromatic, got {self.fidelity!r}")
        if self.linearise_at not in experiment.LINEARISE_STATES:
            raise InputError(
                "linearise_at", f"must be one of {', '.join(experiment.LINEARISE_STATES)}, got {self.linearise_at!r}"
            )
        object.__setattr__(self, "residual_nl", experiment.correction.check_model(self.residual_nl, self.linearise_at))
        if self.between_step is not None and not 0.01 <= float(self.between_step) <= self.magnitude_step:
            raise InputError("between_step", f"must lie in [0.01, {self.magnitude_step:g}] mag, got {self.between_step!r}")

    @classmethod
    def of_scene(cls, scene: str, **changes) -> TableSettings:
        """The settings of the tables of ``scene`` ("paper" or "roman", ``nlpsf tables --scene``): the
        field grid's recipe (:meth:`roman`) for the preset answered from a field grid
        (``presets.Policy.field_grid``), the paper tables' otherwise."""
        return cls.roman(**changes) if roman_default.policy(scene).field_grid else cls(**changes)

    @classmethod
    def roman(cls, **changes) -> TableSettings:
        """Settings for the candidate Roman default scene (official pupil scale and the HLWAS
        exposure unless given)."""
        base = {
            "scene": "roman",
            "pupil_scale": roman_default.PUPIL_SCALE,
            "exptime_s": roman_default.exptime_s(),
            "linearise_at": roman_default.LINEARISE_AT,
            "residual_nl": roman_default.RESIDUAL_NL,
            "between_step": BETWEEN_LIMITS_STEP,
        }
        return cls(**(base | changes))

    def config(
        self, band: str, sca: int, point: int | None = None, position: tuple[float, float] | None = None
    ) -> experiment.SimulationConfig:
        """The simulation of one table; ``point`` (1-4) puts the star at that corner field point of
        the SCA (``roman.field_points``), ``position`` at any pixel position, neither at the centre."""
        if point:
            position = field_position(sca, point)
        # The scene preset's readout, exposure and sky (``presets.fill``) and its scene at the position.
        filled = roman_default.fill(self.scene, band, sca, self.exptime_s, None, None, None)
        exptime, ramp = filled.exptime, filled.ramp
        scene = roman_default.preset_scene(self.scene, position, filled.background_e or 0.0) or experiment.PAPER_SCENE
        level = fidelity.simulation_settings(self.fidelity)
        return experiment.SimulationConfig(
            band=band,
            sca=sca,
            realizations=self.realizations,
            seed=self.seed,
            oversampling=self.oversampling,
            stamp=self.stamp,
            exptime_s=exptime,
            full_well_e=self.full_well_e,
            weight_cut_rho2=self.weight_cut_rho2,
            pupil_scale=self.pupil_scale,
            method=level.method,
            n_wavelengths=level.n_wavelengths,
            throughput=self.throughput,
            ramp=ramp,
            scene=scene,
        )

    def fingerprint(self) -> str:
        """Identifies the settings and code a table was made with (resuming skips matching ones).

        Fields added after the shipped tables were built enter only when they differ from their
        default, so the paper tables keep their fingerprints."""
        settings = asdict(self)
        added = (
            ("scene", "paper"),
            ("fidelity", "linear"),
            ("linearise_at", "beta0"),
            ("residual_nl", None),
            ("between_step", None),
        )
        for name, default in added:
            if settings[name] == default:
                settings.pop(name)
        text = json.dumps({**settings, "code": __version__, "data": roman.DATA_VERSION}, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]


def _residual_method(model: str | None) -> str:
    if model == "per_read_beta":
        return f"a residual {experiment.CORRECTED_RESIDUAL:g} beta0 on every read before IPC"
    return "the correction on every resultant as romancal applies it, d metric / d Delta_beta of r(Q) = -Delta_beta Q^2"


#: The corner field points of every SCA (``roman.field_points`` 1-4): with the SCA centre, the
#: points ``nlpsf solve --over-field`` answers for. Their tables ship in ``field_slopes.ecsv.gz``.
FIELD_POINTS = (1, 2, 3, 4)


def field_position(sca: int, point: int | None) -> tuple[float, float] | None:
    """Pixel position of a corner field point (1-4), None for the SCA centre (point None or 0)."""
    if not point:
        return None
    if point not in FIELD_POINTS:
        raise InputError("point", f"field points are {', '.join(map(str, FIELD_POINTS))} (the corners), got {point!r}")
    return roman.field_points(sca)[point]


def saturation_magnitude(peak_fraction: float, config: experiment.SimulationConfig) -> float:
    """Magnitude at which the brightest fine pixel (over centroids) reaches the full well, on top of
    the scene's background (none in the paper's scene)."""
    electrons_at_full_well = (config.full_well_e - config.scene.background_e) / (peak_fraction * config.oversampling**2)
    return float(
        photometry.electrons_to_magnitude(
            electrons_at_full_well, config.band, config.exptime_s, sca=config.sca, throughput=config.throughput
        )
    )


def magnitude_grid(
    saturation: float,
    step: float = MAGNITUDE_STEP,
    faint_limit: float = FAINT_LIMIT,
    between: tuple[float, float] | None = None,
    between_step: float | None = None,
) -> np.ndarray:
    """From BRIGHT_MARGIN_MAG brighter than saturation to ``faint_limit``, finer at the bright end.

    ``between`` (a ramp's saturation limit, the final frame's) with ``between_step``: rows every
    ``between_step`` mag (multiples of it) from :data:`BETWEEN_LIMITS_MARGIN_MAG` brighter than the
    first to as much fainter than the second, in place of the plain rows there."""
    fine = step * BRIGHT_STEP_FACTOR
    first = math.floor((saturation - BRIGHT_MARGIN_MAG) / step) * step
    switch = math.ceil((saturation + 1.0) / step) * step
    bright = np.arange(first, switch, fine)
    faint = np.arange(switch, faint_limit + step / 2, step)
    rows = np.round(np.concatenate([bright, faint]), 6)
    if between is None or not between_step:
        return rows
    lo = max(first, math.floor((between[0] - BETWEEN_LIMITS_MARGIN_MAG) / between_step) * between_step)
    hi = math.ceil((between[1] + BETWEEN_LIMITS_MARGIN_MAG) / between_step) * between_step
    dense = np.round(np.arange(lo, hi + between_step / 2, between_step), 6)
    keep = rows[(rows < lo - 1e-9) | (rows > hi + 1e-9)]
    return np.unique(np.concatenate([keep, dense]))


def table_magnitudes(scene: experiment.Scene, settings: TableSettings) -> tuple[float, np.ndarray]:
    """The saturation magnitude a table's grid is anchored at, and the grid (``magnitude_grid``).

    Final frame: the brightest fine pixel reaches the full well. Up the ramp a star stays measurable
    until its brightest pixel saturates within the resultants a slope needs, so the anchor moves
    brighter by ``ramps.Ramp.saturation_shift_mag`` (3.4 mag for H158 with C2A_IMG_HLWAS); with
    ``settings.between_step`` the rows between the two limits are that dense."""
    config = scene.config
    m_sat = final = saturation_magnitude(float(scene.star_peak_fraction), config)
    if config.ramp is not None:
        m_sat -= config.ramp.saturation_shift_mag(config.exptime_s, config.full_well_e, settings.beta0, config.scene.background_e)
    between = (m_sat, final) if config.ramp is not None and settings.between_step else None
    return m_sat, magnitude_grid(m_sat, settings.magnitude_step, settings.faint_limit, between, settings.between_step)


def compute_table(
    band: str,
    sca: int,
    settings: TableSettings | None = None,
    progress=None,
    point: int | None = None,
    node: tuple[int, int, int] | None = None,
) -> Table:
    """The slope table of one (band, SCA), at the SCA centre, a corner field point (1-4) or the
    node ``(n, i, j)`` of the n x n field grid (``fieldgrid.grid_positions``)."""
    settings = settings or TableSettings()
    start, cpu_start = time.perf_counter(), time.process_time()
    position = None
    if node is not None:
        n, i, j = (int(v) for v in node)
        position = (float(fieldgrid.grid_axis(n)[i]), float(fieldgrid.grid_axis(n)[j]))
    config = settings.config(band, sca, point, position)
    scene = experiment.prepare(config)
    m_sat, magnitudes = table_magnitudes(scene, settings)
    results = experiment.slopes(
        config,
        list(magnitudes),
        beta0=settings.beta0,
        scene=scene,
        progress=progress,
        linearise_at=settings.linearise_at,
        residual_nl=settings.residual_nl,
    )
    table = Table(_table_columns(magnitudes, results))
    table.add_column(band, name="band", index=0)
    table.add_column(np.int16(sca), name="sca", index=1)
    if point:
        table.add_column(np.int16(point), name="field_point", index=2)
        table.meta["field_point"] = int(point)
        table.meta["position"] = list(field_position(sca, point))
    if node is not None:
        table.meta["grid_node"] = [int(v) for v in node]
        table.meta["position"] = list(position)
    table.meta.update(
        {
            "band": band,
            "sca": int(sca),
            "saturation_magnitude": m_sat,
            "peak_fraction": float(scene.star_peak_fraction),
            "settings": asdict(settings),
            "fingerprint": settings.fingerprint(),
            "method": (
                "linear response at beta0, mean over centroid realizations"
                if settings.linearise_at == "beta0"
                else f"linear response at the {settings.linearise_at} state ({_residual_method(settings.residual_nl)}; "
                "a ramp's saturation flags at the raw beta0), mean over centroid realizations"
            ),
            "data_version": roman.DATA_VERSION,
            "code_version": __version__,
            "elapsed_s": time.perf_counter() - start,
            "cpu_s": time.process_time() - cpu_start,
            "exptime_s": config.exptime_s,
            "scene": config.scene.describe(),
        }
    )
    return table


def _table_columns(magnitudes, results: list[experiment.SlopeResult]) -> dict[str, list]:
    """A table's columns: per magnitude its flux, peak, failed realizations, and each metric's bias
    and scatter slopes with their standard errors and interpolation error estimates."""
    columns: dict[str, list] = {"magnitude": list(magnitudes), "flux_electrons": [], "peak_electrons": []}
    for metric in COLUMN_METRICS:
        for mode in MODES:
            columns[f"{mode}_{metric}"] = []
            columns[f"{mode}_{metric}_err"] = []
    columns["failed_realizations"] = []
    for r in results:
        columns["flux_electrons"].append(r.flux_electrons)
        columns["peak_electrons"].append(r.peak_electrons)
        columns["failed_realizations"].append(r.failed_realizations)
        for metric, name in COLUMN_METRICS.items():
            bias = r.bias[name]
            columns[f"bias_{metric}"].append(np.nan if bias.mean is None else bias.mean)
            columns[f"bias_{metric}_err"].append(np.nan if bias.stderr is None else bias.stderr)
            scatter = r.scatter[name]
            columns[f"scatter_{metric}"].append(np.nan if scatter["value"] is None else scatter["value"])
            columns[f"scatter_{metric}_err"].append(np.nan if scatter["uncertainty"] is None else scatter["uncertainty"])
    flux = np.asarray(columns["flux_electrons"])
    names = [f"{mode}_{metric}" for metric in COLUMN_METRICS for mode in MODES]
    estimates = interpolation_error_estimate(flux, np.stack([np.asarray(columns[name]) for name in names], axis=-1))
    for k, name in enumerate(names):
        columns[f"{name}_interp"] = list(estimates[:, k])
    return columns


def _partial_path(directory: Path, band: str, sca: int, point: int | None = None, node=None) -> Path:
    suffix = (f"_P{point}" if point else "") + (f"_G{node[0]}_{node[1]}{node[2]}" if node is not None else "")
    return directory / f"slopes_{band}_SCA{sca:02d}{suffix}.ecsv"


def build_tables(
    directory: Path | str,
    bands: Iterable[str] = defaults.BANDS,
    scas: Iterable[int] = range(1, defaults.N_SCA + 1),
    settings: TableSettings | None = None,
    workers: int = 1,
    dask_address: str | None = None,
    progress: Callable[[int, int, str], None] | None = None,
    scheduler_file: str | None = None,
    retries: int = 1,
    field: bool = False,
    grid: int | None = None,
) -> list[Path]:
    """Compute every (band, SCA) table into ``directory``, skipping those already done; with
    ``field``, the tables at each SCA's four corner field points instead (``FIELD_POINTS``); with
    ``grid`` n, at the n x n nodes of the field grid (``fieldgrid.grid_positions``).

    Work is spread over ``workers`` local processes, or over a dask.distributed cluster when
    ``dask_address`` ("local" starts a LocalCluster with ``workers`` workers) or ``scheduler_file``
    is given. Workers return the tables; this process writes them, each as soon as it arrives, so
    interrupting and re-running resumes where it stopped. A table that fails (after ``retries``)
    is reported once the others are written.
    """
    settings = settings or TableSettings()
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    todo, done = [], []
    if field and grid:
        raise InputError("grid", "give either the corner field points or a field grid, not both")
    points = FIELD_POINTS if field else (None,)
    nodes = [(grid, i, j) for i, j, _ in fieldgrid.grid_positions(grid)] if grid else [None]
    pairs = [(roman.check_band(b), roman.check_sca(s), p, q) for b in bands for s in scas for p in points for q in nodes]
    for band, sca, point, node in pairs:
        path = _partial_path(directory, band, sca, point, node)
        if path.exists() and ecsv_fingerprint(path) == settings.fingerprint():
            done.append(path)
        else:
            todo.append((band, sca, settings, None, point, node))
    total = len(pairs)
    if progress:
        progress(len(done), total, "resumed" if done else "starting")
    failures = []
    finished = cluster.run_tasks(
        compute_table, todo, workers=workers, dask_address=dask_address, scheduler_file=scheduler_file, retries=retries
    )
    for index, table, error in finished:
        band, sca, _, _, point, node = todo[index]
        where = f"{band} SCA {sca}" + (f" point {point}" if point else "") + (f" node {node[1]},{node[2]}" if node else "")
        if error is not None:
            failures.append(f"{where}: {type(error).__name__}: {error}")
            continue
        path = _partial_path(directory, band, sca, point, node)
        cluster.write_atomic(table, path)
        done.append(path)
        if progress:
            progress(len(done), total, f"{where} ({float(table.meta['elapsed_s']):.1f} s)")
    if failures:
        raise SimulationError(f"{len(failures)} of {total} tables failed (re-run to retry them): " + "; ".join(failures))
    return done


def merge_tables(paths: Iterable[Path], destination: Path | str) -> Table:
    """Stack per-(band, SCA) tables into one file with their metadata kept per table."""
    tables = [Table.read(p, format="ascii.ecsv") for p in sorted(paths)]
    if not tables:
        raise InputError("tables", "nothing to merge")
    fingerprints = {t.meta["fingerprint"] for t in tables}
    if len(fingerprints) != 1:
        raise InputError("tables", f"the partial tables were made with different settings: {sorted(fingerprints)}")
    points = {t.meta.get("field_point") is not None for t in tables}
    if len(points) != 1:
        raise InputError("tables", "centre tables and field-point tables go into separate files")
    per_table = {
        table_key(t.meta["band"], t.meta["sca"], t.meta.get("field_point")): {
            k: t.meta[k] for k in ("saturation_magnitude", "peak_fraction", "elapsed_s", "position") if k in t.meta
        }
        for t in tables
    }
    merged = vstack([Table(t, meta={}) for t in tables], metadata_conflicts="silent")
    merged.meta.update(
        {
            "description": "nlpsf slope tables: bias slopes d(metric)/dbeta and scatter slopes sigma(metric)/sigma_beta"
            + (", at each SCA's corner field points (field_point 1-4, positions in per_table)" if points == {True} else ""),
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
    destination = write_ecsv(merged, destination)
    write_companion(merged, destination)
    return merged


def interpolation_error_estimate(flux: np.ndarray, slope: np.ndarray) -> np.ndarray:
    """Estimated error of interpolating slope / flux with a cubic spline in flux, per grid point.

    Leave each interior point out, interpolate it back from the others (which doubles the local
    spacing) and divide by 2^4, the factor by which a cubic spline's error grows when the spacing
    doubles. End points take their neighbour's estimate. The tests check the estimate against
    fresh simulations between grid points. ``slope`` may hold several columns (points, columns):
    one spline per left-out point fits them all.
    """
    order = np.argsort(flux)
    x = flux[order]
    q = slope[order] / (x if slope.ndim == 1 else x[:, None])
    estimate = np.zeros_like(q)
    for k in range(1, len(q) - 1):
        keep = np.ones(len(q), dtype=bool)
        keep[k] = False
        estimate[k] = abs(CubicSpline(x[keep], q[keep])(x[k]) - q[k]) / 16.0
    estimate[0], estimate[-1] = estimate[1], estimate[-2]
    out = np.empty_like(estimate)
    out[order] = estimate * (x if slope.ndim == 1 else x[:, None])  # back to slope units
    return out


def merge_field_grid(
    paths: Iterable[Path], destination: Path | str, provenance: dict | None = None, complete_only: bool = False
) -> Path:
    """Pack the node tables of a ``build_tables(grid=n)`` run into one field-grid file
    (``gridfile.write_grid``: float32 slopes, the runtime format ``fieldgrid.FieldGrid`` reads).

    ``complete_only``: leave out every (band, SCA) whose n x n nodes are not all there (a build still
    running or stopped), instead of refusing; ``provenance`` goes into the file's metadata."""
    tables = [Table.read(p, format="ascii.ecsv") for p in sorted(paths)]
    if not tables:
        raise InputError("tables", "nothing to merge")
    if any("grid_node" not in t.meta for t in tables):
        raise InputError("tables", "only field-grid node tables (built with grid=n) go into a field-grid file")
    if complete_only:
        groups: dict[tuple[str, int], list] = {}
        for t in tables:
            groups.setdefault((t.meta["band"], int(t.meta["sca"])), []).append(t)
        tables = [t for group in groups.values() if len(group) == int(group[0].meta["grid_node"][0]) ** 2 for t in group]
        if not tables:
            raise InputError("tables", "no (band, SCA) has all its grid nodes yet")
    return gridfile.write_grid(tables, destination, provenance=provenance, per_table=_ramp_shifts(tables))


def _ramp_shifts(tables: list) -> dict[str, dict]:
    """Per (band, SCA) of a ramp scene: how much brighter the ramp's saturation limit is than the
    final frame's (``Ramp.saturation_shift_mag``, exact for its rules, at the tables' beta0 and background)."""
    out: dict[str, dict] = {}
    for t in tables:
        key = f"{t.meta['band']}_{int(t.meta['sca']):02d}"
        if key in out:
            continue
        settings = TableSettings(**t.meta["settings"])
        config = settings.config(t.meta["band"], int(t.meta["sca"]))
        if config.ramp is None:
            continue
        shift = config.ramp.saturation_shift_mag(config.exptime_s, config.full_well_e, settings.beta0, config.scene.background_e)
        out[key] = {"ramp_shift_mag": float(shift)}
    return out
