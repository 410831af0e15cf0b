"""Sweeps: a grid of fresh simulations (bands x SCAs x magnitudes x betas x sigma_betas) as one table.

The unit of work, a *cell*, is one (band, SCA): it prepares the scene once (optics, stamps,
reference moments) and runs ``experiment.simulate`` over every sigma_beta, magnitude and beta,
so each row is exactly what ``nlpsf simulate`` prints for the same options, however the sweep is
spread. Cells run serially, on local processes, or on a dask.distributed cluster
(``nlpsf.sim.cluster``); a cell returns its rows and the client writes them, atomically, one ECSV file
per cell in ``directory``. Re-running the same sweep skips the cells already written (their
fingerprint, a hash of the settings, the cell and the code/data versions, must match), so an
interrupted sweep resumes, and a cell that failed is retried then and only then.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from astropy.table import Table, vstack

from nlpsf import defaults, roman
from nlpsf._version import __version__
from nlpsf.checks import InputError, SimulationError, check_numbers

from . import cluster, detector, experiment

#: Cells in one sweep at most (every band x every SCA is 144).
MAX_CELLS = 10_000
#: Rows in one cell at most (magnitudes x betas x sigma_betas).
MAX_ROWS_PER_CELL = 100_000
METRIC_COLUMNS = ("dR_over_R", "de1", "de2")
#: Column descriptions (units in brackets), written into every cell file.
DESCRIPTIONS = {
    "band": "Roman band",
    "sca": "detector (SCA) number",
    "magnitude": "AB magnitude of the star in the band [mag]",
    "beta": "NL coefficient as given, in beta_convention [1/e-]",
    "beta_paper": "NL coefficient in the paper's convention S = Q - beta Q^2 [1/e-]",
    "sigma_beta": "per-pixel scatter of beta [1/e-]; > 0: rows are statistics over beta maps at a fixed centroid",
    "flux_electrons": "star flux over the exposure [e-]",
    "peak_electrons": "the star's brightest fine pixel over every sub-pixel centroid, as native-pixel charge [e-]",
    "dR_over_R": "mean fractional size change over realizations",
    "de1": "mean change of e1 = (Mxx - Myy)/(Mxx + Myy)",
    "de2": "mean change of e2 = 2 Mxy/(Mxx + Myy)",
    "failed_realizations": "realizations whose moment fit failed",
    "flags": "warnings for this row, separated by ' | '",
    "elapsed_s": "compute time of the row [s]",
}


@dataclass(frozen=True)
class SweepGrid:
    """The axes of a sweep and the simulation settings they share (defaults are the paper's)."""

    bands: tuple[str, ...] = (defaults.BAND,)
    scas: tuple[int, ...] = (defaults.SCA,)
    magnitudes: tuple[float, ...] = defaults.PAPER_MAGNITUDES
    betas: tuple[float, ...] = (defaults.BETA0,)
    sigma_betas: tuple[float, ...] = (0.0,)
    beta_convention: str = "paper"
    settings: experiment.SimulationConfig = field(default_factory=experiment.SimulationConfig)

    def __post_init__(self) -> None:
        bands = tuple(roman.check_band(b) for b in _sequence(self.bands, "band"))
        scas = tuple(roman.check_sca(s) for s in _sequence(self.scas, "sca"))
        object.__setattr__(self, "bands", tuple(dict.fromkeys(bands)))
        object.__setattr__(self, "scas", tuple(dict.fromkeys(scas)))
        object.__setattr__(self, "magnitudes", tuple(experiment.check_magnitudes(self.magnitudes)))
        object.__setattr__(self, "betas", tuple(check_numbers(self.betas, "beta")))
        object.__setattr__(
            self, "sigma_betas", tuple(experiment.check_sigma_beta(s) for s in _sequence(self.sigma_betas, "sigma_beta"))
        )
        for beta in self.betas:
            detector.to_paper_beta(beta, self.beta_convention)  # validates the convention and the sign
        if not isinstance(self.settings, experiment.SimulationConfig):
            raise InputError("settings", "must be an experiment.SimulationConfig")
        cells = len(self.bands) * len(self.scas)
        if cells > MAX_CELLS:
            raise InputError("band", f"{cells} (band, SCA) cells; at most {MAX_CELLS}")
        rows = len(self.magnitudes) * len(self.betas) * len(self.sigma_betas)
        if rows > MAX_ROWS_PER_CELL:
            raise InputError("magnitudes", f"{rows} rows per (band, SCA); at most {MAX_ROWS_PER_CELL}")

    def cells(self) -> list[tuple[str, int]]:
        return [(band, sca) for band in self.bands for sca in self.scas]

    def config(self, band: str, sca: int) -> experiment.SimulationConfig:
        return replace(self.settings, band=band, sca=sca)

    def fingerprint(self, band: str, sca: int) -> str:
        """Identifies what one cell's rows were computed from (resuming skips a matching cell)."""
        conditions = self.config(band, sca).conditions()
        text = json.dumps(
            {
                "conditions": conditions,
                "magnitudes": self.magnitudes,
                "betas": self.betas,
                "sigma_betas": self.sigma_betas,
                "beta_convention": self.beta_convention,
            },
            sort_keys=True,
        )
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def to_dict(self) -> dict:
        out = asdict(self)
        out["settings"] = self.settings.conditions()
        return out


def _sequence(values, name: str) -> tuple:
    if isinstance(values, (str, int, float)):
        values = (values,)
    values = tuple(values)
    if not values:
        raise InputError(name, "give at least one value")
    return values


def run_cell(grid: SweepGrid, band: str, sca: int) -> Table:
    """The rows of one (band, SCA): every sigma_beta x magnitude x beta. Runs on a worker; writes nothing."""
    start = time.perf_counter()
    config = grid.config(band, sca)
    scene = experiment.prepare(config)
    results = []
    for sigma_beta in grid.sigma_betas:
        results += experiment.simulate(
            config, list(grid.magnitudes), list(grid.betas), sigma_beta, grid.beta_convention, scene=scene
        )
    columns: dict[str, list] = {name: [] for name in DESCRIPTIONS}
    for metric in METRIC_COLUMNS:
        columns[f"{metric}_std"] = []
        columns[f"{metric}_err"] = []
    for r in results:
        columns["band"].append(band)
        columns["sca"].append(sca)
        for name in ("magnitude", "beta", "beta_paper", "sigma_beta", "flux_electrons", "peak_electrons"):
            columns[name].append(getattr(r, name))
        for metric in METRIC_COLUMNS:
            stat = getattr(r, metric)
            columns[metric].append(_number(stat.mean))
            columns[f"{metric}_std"].append(_number(stat.std))
            columns[f"{metric}_err"].append(_number(stat.stderr))
        columns["failed_realizations"].append(r.failed_realizations)
        columns["flags"].append(" | ".join(r.flags))
        columns["elapsed_s"].append(r.elapsed_s)
    order = ["band", "sca", "magnitude", "beta", "beta_paper", "sigma_beta", "flux_electrons", "peak_electrons"]
    for metric in METRIC_COLUMNS:
        order += [metric, f"{metric}_std", f"{metric}_err"]
    order += ["failed_realizations", "flags", "elapsed_s"]
    table = Table({name: columns[name] for name in order})
    table["sca"] = table["sca"].astype(np.int16)
    for name in order:
        metric = name.removesuffix("_std").removesuffix("_err")
        text = DESCRIPTIONS.get(name) or DESCRIPTIONS[metric] + (
            ": standard deviation over realizations" if name.endswith("_std") else ": standard error of the mean"
        )
        table[name].description = text
    table.meta.update(
        {
            "band": band,
            "sca": int(sca),
            "fingerprint": grid.fingerprint(band, sca),
            "conditions": _json_safe(config.conditions()),
            "nl_model": detector.describe(grid.beta_convention),
            "elapsed_s": time.perf_counter() - start,
        }
    )
    return table


def _number(value: float | None) -> float:
    return math.nan if value is None else float(value)


def _json_safe(value):
    return json.loads(json.dumps(value, default=str))


def read_cell(path: Path) -> Table:
    """A cell file as ``run_cell`` returned it (ECSV reads an empty string back as masked)."""
    table = Table.read(path, format="ascii.ecsv")
    if hasattr(table["flags"], "filled"):
        table["flags"] = table["flags"].filled("").astype(str)
    return Table(table, masked=False)


def cell_path(directory: Path, band: str, sca: int) -> Path:
    return directory / f"sweep_{band}_SCA{sca:02d}.ecsv"


def sweep(
    grid: SweepGrid,
    directory: Path | str | None = None,
    workers: int = 1,
    dask_address: str | None = None,
    scheduler_file: str | None = None,
    retries: int = 2,
    progress: Callable[[int, int, str], None] | None = None,
    client=None,
) -> Table:
    """Run every cell of ``grid`` and return all rows as one table (ordered band, SCA, sigma_beta,
    magnitude, beta as in the grid).

    With ``directory``, each cell is written there as it finishes and a re-run skips the cells
    already written with the same fingerprint. Cells that fail after ``retries`` are reported in a
    ``SimulationError`` once the others are written (re-running retries just those).
    """
    if not isinstance(grid, SweepGrid):
        raise InputError("grid", "must be a SweepGrid")
    cluster.check_backend(workers, dask_address, scheduler_file, retries)
    folder = None if directory is None else Path(directory)
    if folder is not None:
        folder.mkdir(parents=True, exist_ok=True)
    cells = grid.cells()
    finished: dict[tuple[str, int], Table] = {}
    todo = []
    for band, sca in cells:
        path = None if folder is None else cell_path(folder, band, sca)
        if path is not None and path.exists():
            table = read_cell(path)
            if table.meta.get("fingerprint") == grid.fingerprint(band, sca):
                finished[band, sca] = table
                continue
        todo.append((grid, band, sca))
    total = len(cells)
    if progress:
        progress(len(finished), total, "resumed" if finished else "starting")
    failures = []
    outcomes = cluster.run_tasks(
        run_cell, todo, workers=workers, dask_address=dask_address, scheduler_file=scheduler_file, retries=retries, client=client
    )
    for index, table, error in outcomes:
        _, band, sca = todo[index]
        if error is not None:
            failures.append(f"{band} SCA {sca}: {type(error).__name__}: {error}")
            continue
        if folder is not None:
            cluster.write_atomic(table, cell_path(folder, band, sca))
        finished[band, sca] = table
        if progress:
            progress(len(finished), total, f"{band} SCA {sca} ({float(table.meta['elapsed_s']):.1f} s)")
    if failures:
        raise SimulationError(
            f"{len(failures)} of {total} cells failed after {retries} retries"
            + (" (re-run to retry them; the others are kept)" if folder is not None else "")
            + ": "
            + "; ".join(failures)
        )
    return combine([finished[cell] for cell in cells], grid)


def combine(tables: Sequence[Table], grid: SweepGrid) -> Table:
    """Stack cell tables into the sweep's table, with the grid and the per-cell conditions in meta."""
    merged = vstack([Table(t, meta={}) for t in tables], metadata_conflicts="silent")
    merged.meta.update(
        {
            "description": "nlpsf sweep: NL-induced PSF size and ellipticity changes over a grid of simulations",
            "grid": _json_safe(grid.to_dict()),
            "cells": {f"{t.meta['band']} {t.meta['sca']}": {"fingerprint": t.meta["fingerprint"]} for t in tables},
            "code_version": __version__,
            "data_version": roman.DATA_VERSION,
        }
    )
    return merged
