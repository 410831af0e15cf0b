"""What the page and the API draw and download: slope curves with their conditions, flat table rows."""

from __future__ import annotations

import math

import numpy as np

from nlpsf import defaults, roman
from nlpsf._version import __version__
from nlpsf.checks import InputError, check_beta0, check_choice, check_exptime, check_full_well

from .model import METRICS, MODES, SlopeTable, TableSet
from .storage import load_tables


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
        "conditions": conditions(table, exptime, beta0, full_well),
    }


def conditions(table: SlopeTable, exptime: float, beta0: float, full_well: float) -> dict:
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
