"""``nlpsf tradeoff``: measure each fidelity level's error and time against the most exact one.

On a set of test points spread over bands, SCAs and magnitudes, each level's relative error is
measured against a reference more exact than any of them -- polychromatic with 16 wavelengths,
400 centroid realizations and exact derivatives at beta0 -- with its time per answer, all in one
run on this machine. ``fidelity.write_measured`` stores the result in ``nlpsf/data/fidelity.json``,
which the solver's ``accuracy`` option reads (``nlpsf.slopes.fidelity``) to pick the cheapest level.

``default="roman"`` measures the levels inside the Roman default's scene (``nlpsf.request.presets``
through ``tablebuild.TableSettings.roman``: its SED, jitter, diffusion, IPC, background, HLWAS
optimal ramp, official pupil scale, slopes at the corrected state) against that scene's most exact
level: 16 wavelengths, :data:`ROMAN_REFERENCE_REALIZATIONS` centroids, exact derivatives. Its table
level is the linear level (the Roman tables are built at it, ``TableSettings.roman``; their grid
interpolation error is measured with the field grid, docs/field.md), so it is stated equal to the
linear level's, and said so. ``fidelity.write_measured(result, default="roman")`` stores it under
the file's ``"roman"`` key, leaving the paper scene's entries as they are.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from nlpsf import roman
from nlpsf.sim import experiment, optics
from nlpsf.sim.levels import LEVELS, simulation_settings
from nlpsf.slopes import tables

from . import solver

#: (band, SCA, magnitude) where the levels are compared: bright to faint, short to long bands.
TEST_POINTS = (
    ("H158", 18, 18.5),
    ("H158", 18, 21.0),
    ("J129", 9, 19.5),
    ("Y106", 3, 22.0),
    ("F184", 14, 19.0),
    ("W146", 6, 20.5),
    ("R062", 1, 20.0),
    ("Z087", 12, 19.0),
    ("K213", 17, 18.5),
)
REFERENCE_WAVELENGTHS = 16
REFERENCE_REALIZATIONS = 400
#: Centroids of the Roman default's reference (its ramp's likelihood fit makes 400 too dear here).
ROMAN_REFERENCE_REALIZATIONS = 200
DEFAULTS = ("paper", "roman")
METRIC_NAMES = {"size": ("dR_over_R",), "e1": ("de1",), "e2": ("de2",), "e": ("de1", "de2")}


def _combine(values: list[float], errors: list[float]) -> float:
    return float(values[0]) if len(values) == 1 else float(math.hypot(*values))


def reference_slopes(band: str, sca: int, magnitude: float, default: str = "paper") -> dict:
    """Most exact slopes: polychromatic (16 wavelengths), 400 centroids (the Roman default's: its
    full scene, :data:`ROMAN_REFERENCE_REALIZATIONS`), exact derivatives."""
    if default == "roman":
        config = replace(
            _roman_config(band, sca, ROMAN_REFERENCE_REALIZATIONS), method="linear", n_wavelengths=REFERENCE_WAVELENGTHS
        )
        return _slope_values(experiment.slopes(config, [magnitude], linearise_at=_roman_state())[0])
    reference = {"method": "linear", "n_wavelengths": REFERENCE_WAVELENGTHS, "realizations": REFERENCE_REALIZATIONS}
    config = experiment.SimulationConfig.from_settings(reference, band=band, sca=sca)
    return _slope_values(experiment.slopes(config, [magnitude])[0])


def _roman_config(band: str, sca: int, realizations: int | None = None, level: str = "linear"):
    """The Roman default's simulation at the SCA centre (``TableSettings.roman``) at a level."""
    from . import tablebuild

    changes = {} if realizations is None else {"realizations": realizations}
    fidelity = "polychromatic" if level == "polychromatic" else "linear"
    config = tablebuild.TableSettings.roman(fidelity=fidelity, **changes).config(band, sca)
    return replace(config, method=simulation_settings(level).method)


def _roman_state() -> str:
    from nlpsf.request import presets as roman_default

    return roman_default.LINEARISE_AT


def _slope_values(result: experiment.SlopeResult) -> dict:
    out = {"bias": {}, "scatter": {}}
    for metric, names in METRIC_NAMES.items():
        out["bias"][metric] = _combine([result.bias[n].mean for n in names], [])
        out["scatter"][metric] = _combine([result.scatter[n]["value"] for n in names], [])
    return out


def level_slopes(level: str, band: str, sca: int, magnitude: float, default: str = "paper") -> tuple[dict, float]:
    """Slopes from one fidelity level and the seconds it took."""
    start = time.perf_counter()
    out = {"bias": {}, "scatter": {}}
    if default == "roman":
        # The table level is the linear level on a grid (see the module docstring).
        config = _roman_config(band, sca, level="linear" if level == "table" else level)
        optics.clear_caches()
        result = experiment.slopes(config, [magnitude], linearise_at=_roman_state())[0]
        return _slope_values(result), time.perf_counter() - start
    if level == "table":
        table = tables.load_tables().get(band, sca)
        for mode in out:
            for metric in METRIC_NAMES:
                out[mode][metric] = float(table.slope(metric, mode, magnitude)[0][0])
        # A table answer's cost is one solve; time that rather than this loop.
        elapsed = _time_table_solve(band, sca, magnitude)
        return out, elapsed
    settings = simulation_settings(level)
    config = experiment.SimulationConfig.from_settings(settings, band=band, sca=sca)  # its method and wavelengths
    optics.clear_caches()  # a fresh request pays for its optics
    result = experiment.slopes(config, [magnitude])[0]
    return _slope_values(result), time.perf_counter() - start


def _time_table_solve(band: str, sca: int, magnitude: float) -> float:
    solver.solve(band, sca, precision=0.01, magnitude=magnitude, scene="paper")  # warm the interpolants
    count = 200
    start = time.perf_counter()
    for _ in range(count):
        solver.solve(band, sca, precision=0.01, magnitude=magnitude, scene="paper")
    return (time.perf_counter() - start) / count


def tradeoff(points=TEST_POINTS, progress=None, default: str = "paper") -> dict:
    """Measure every level's error and time against the reference, in one run. ``default``:
    "paper" (the paper's scene, what the shipped file's top level holds) or "roman" (the Roman
    default's scene against its own most exact level; see the module docstring)."""
    if default not in DEFAULTS:
        raise ValueError(f"default must be one of {', '.join(DEFAULTS)}, got {default!r}")
    rows = []
    for index, (band, sca, magnitude) in enumerate(points):
        if progress:
            progress(index, len(points), f"{band} SCA {sca} m={magnitude}")
        reference = reference_slopes(band, sca, magnitude, default)
        for level in LEVELS:
            if default == "roman" and level == "table":
                continue  # stated from the linear level below
            values, seconds = level_slopes(level, band, sca, magnitude, default)
            for mode in ("bias", "scatter"):
                for metric in METRIC_NAMES:
                    ref = reference[mode][metric]
                    rows.append(
                        {
                            "band": band,
                            "sca": sca,
                            "magnitude": magnitude,
                            "level": level,
                            "mode": mode,
                            "metric": metric,
                            "value": values[mode][metric],
                            "reference": ref,
                            "relative_error": abs(values[mode][metric] - ref) / abs(ref),
                            "seconds": seconds,
                        }
                    )
    if default == "roman":
        # The Roman tables are the linear level on a grid: the same error, a table look-up's time.
        rows += [{**r, "level": "table", "seconds": None, "stated_from": "linear"} for r in rows if r["level"] == "linear"]
    if progress:
        progress(len(points), len(points), "done")
    errors = _worst_errors(rows)
    seconds = {}
    for level in LEVELS:
        times = [r["seconds"] for r in rows if r["level"] == level and r["seconds"] is not None]
        seconds[level] = float(np.median(times)) if times else None
    extra = {}
    if default == "roman":
        extra = {
            "scene": "the Roman default (nlpsf.request.presets via tablebuild.TableSettings.roman), SCA centre",
            "table_level": "stated equal to the linear level (the Roman tables are built at it); add their interpolation error",
            "linearise_at": _roman_state(),
        }
    return {
        "date": time.strftime("%Y-%m-%d"),
        "machine": f"{__import__('os').cpu_count()} cores",
        "reference": (
            f"polychromatic, {REFERENCE_WAVELENGTHS} wavelengths, {REFERENCE_REALIZATIONS} centroids, exact derivatives at beta0"
            if default == "paper"
            else f"the Roman default's full scene, {REFERENCE_WAVELENGTHS} wavelengths, {ROMAN_REFERENCE_REALIZATIONS} "
            f"centroids, exact derivatives at the {_roman_state()} state"
        ),
        **extra,
        "test_points": [list(p) for p in points],
        "errors": errors,
        "seconds_per_answer": seconds,
        "rows": rows,
        "data_version": roman.DATA_VERSION,
        "throughput": roman.DEFAULT_THROUGHPUT,
        "throughput_version": roman.THROUGHPUT_VERSIONS[roman.DEFAULT_THROUGHPUT],
    }


def _worst_errors(rows: list[dict]) -> dict:
    """{band: {mode: {metric: {level: the largest relative error over the test points}}}}."""
    bands = sorted({r["band"] for r in rows}, key=roman.BANDS.index)
    return {
        band: {
            mode: {
                metric: {
                    level: max(
                        r["relative_error"]
                        for r in rows
                        if (r["band"], r["mode"], r["metric"], r["level"]) == (band, mode, metric, level)
                    )
                    for level in LEVELS
                }
                for metric in METRIC_NAMES
            }
            for mode in ("bias", "scatter")
        }
        for band in bands
    }


def markdown(result: dict) -> str:
    lines = [
        f"Relative error against the reference ({result['reference']}), worst of {len(result['test_points'])} test points "
        "over all bands, "
        f"and median time per answer on this machine ({result['machine']}, {result['date']}):",
        "",
        "| level | time per answer | "
        + " | ".join(f"{m} bias" for m in METRIC_NAMES)
        + " | "
        + " | ".join(f"{m} scatter" for m in METRIC_NAMES)
        + " |",
        "|---|---|" + "---|" * (2 * len(METRIC_NAMES)),
    ]
    for level in LEVELS:
        t = result["seconds_per_answer"][level]
        time_text = "as linear" if t is None else f"{1e6 * t:.0f} µs" if t < 1e-3 else f"{t:.2f} s"
        worst = {
            (mode, m): max(result["errors"][band][mode][m][level] for band in result["errors"])
            for mode in ("bias", "scatter")
            for m in METRIC_NAMES
        }
        cells = [f"{100 * worst[(mode, m)]:.2g} %" for mode in ("bias", "scatter") for m in METRIC_NAMES]
        lines.append(f"| {level} | {time_text} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Per band, size bias: "
        + ", ".join(
            f"{band} " + "/".join(f"{100 * result['errors'][band]['bias']['size'][level]:.2g}" for level in LEVELS) + " %"
            for band in result["errors"]
        )
        + " (table/linear/monte_carlo/polychromatic).",
    ]
    return "\n".join(lines)
