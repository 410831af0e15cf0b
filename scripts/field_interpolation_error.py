"""Slope tables over the field for the candidate Roman default scene: cost and interpolation error.

``--cost``: the CPU cost of one slope table (one band, SCA, position; the tables' magnitude grid,
linear response at beta0 x {0.99, 1, 1.01}... as ``tablebuild.compute_table``) for the paper's scene
and for the candidate Roman scene (``roman_default.scene``), each in a fresh process, in one run;
the Roman scene at the polychromatic level (Monte Carlo, 8 wavelengths) is projected from a few of
the grid's magnitudes (prepare + per-magnitude cost x the grid's count, said so in the output). Also
the float32 storage loss on the Roman table.

``--interpolation`` (default): for each band and SCA, slopes at the nodes of a 5 x 5 grid (its 3 x 3
subgrid too) and at random positions that are not nodes, all with the same centroid draws (so the
comparison measures interpolation, not realization noise); the node values are interpolated to the
random positions by each scheme of ``fieldgrid.SCHEMES`` and compared with the fresh slopes.
"Near zero" (excluded from the relative errors, reported in units of the median instead):
|slope| < 10 % of the median |slope| of that band, metric and magnitude over every position simulated.

    python scripts/field_interpolation_error.py --output build/field_error.json
    python scripts/field_interpolation_error.py --cost --output build/field_cost.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context

import numpy as np

from nlpsf.sim import experiment
from nlpsf.slopes import fieldgrid, tablebuild
from nlpsf.slopes.tables import COLUMN_METRICS

NEAR_ZERO_FRACTION = 0.1
METRIC_NAMES = {"size": "dR_over_R", "e1": "de1", "e2": "de2"}


# --- cost -------------------------------------------------------------------------------------


def _table_cost(scene: str, fidelity: str, band: str, sca: int, position, realizations: int, sample: int | None) -> dict:
    """Runs in a fresh process (no warm caches): the CPU seconds of one table, or its projection."""
    cpu0, wall0 = time.process_time(), time.perf_counter()
    make = tablebuild.TableSettings.roman if scene == "roman" else tablebuild.TableSettings
    settings = make(realizations=realizations, fidelity=fidelity)
    config = settings.config(band, sca, position=position)
    if sample is None:
        table = tablebuild.compute_table(band, sca, settings, node=None) if position is None else None
        if table is None:
            prepared = experiment.prepare(config)
            _, mags = tablebuild.table_magnitudes(prepared, settings)
            results = experiment.slopes(config, list(mags), beta0=settings.beta0, scene=prepared)
            values = np.array([[r.bias[m].mean for m in METRIC_NAMES.values()] for r in results], dtype=float)
            errors = np.array([[r.bias[m].stderr for m in METRIC_NAMES.values()] for r in results], dtype=float)
            n_mag = len(mags)
        else:
            n_mag = len(table)
            values = np.stack([np.asarray(table[f"bias_{k}"], float) for k in COLUMN_METRICS], axis=1)
            errors = np.stack([np.asarray(table[f"bias_{k}_err"], float) for k in COLUMN_METRICS], axis=1)
        cpu = time.process_time() - cpu0
        f32 = values.astype(np.float32).astype(np.float64)
        ok = np.isfinite(values) & (values != 0)
        return {
            "scene": scene,
            "fidelity": fidelity,
            "cpu_s": cpu,
            "wall_s": time.perf_counter() - wall0,
            "magnitudes": n_mag,
            "projected": False,
            "scene_description": config.scene.describe(),
            "wavelengths": config.optics.n_wavelengths,
            "float32_max_relative_loss": float(np.max(np.abs(f32 - values)[ok] / np.abs(values[ok]))),
            "float32_max_loss_over_stderr": float(np.nanmax(np.abs(f32 - values)[ok] / errors[ok])),
        }
    prepared = experiment.prepare(config)
    cpu_prepare = time.process_time() - cpu0
    _, mags = tablebuild.table_magnitudes(prepared, settings)
    picked = list(mags[np.linspace(0, len(mags) - 1, sample).round().astype(int)])
    cpu1 = time.process_time()
    experiment.slopes(config, picked, beta0=settings.beta0, scene=prepared)
    per_magnitude = (time.process_time() - cpu1) / len(picked)
    return {
        "scene": scene,
        "fidelity": fidelity,
        "cpu_s": cpu_prepare + per_magnitude * len(mags),
        "projected": True,
        "projection": f"prepare {cpu_prepare:.2f} s + {per_magnitude:.2f} s per magnitude (mean of {len(picked)} "
        f"spread over the grid) x {len(mags)} magnitudes",
        "magnitudes": len(mags),
        "scene_description": config.scene.describe(),
        "wavelengths": config.optics.n_wavelengths,
        "wall_s": time.perf_counter() - wall0,
    }


def measure_cost(args) -> dict:
    runs = [
        ("paper", "linear", None),
        ("roman", "linear", None),
        ("roman", "linear", args.sample),  # validates the projection against the full table above
        ("roman", "polychromatic", args.sample),
    ]
    out = []
    position = None if args.position is None else tuple(args.position)
    for scene, fid, sample in runs:
        with ProcessPoolExecutor(1, mp_context=get_context("spawn")) as pool:
            result = pool.submit(_table_cost, scene, fid, args.band[0], args.sca[0], position, args.realizations, sample).result()
        print(json.dumps(result), file=sys.stderr)
        out.append(result)
    paper = out[0]["cpu_s"]
    for r in out:
        r["ratio_to_paper"] = r["cpu_s"] / paper
    return {
        "what": "CPU seconds of one slope table (one band, SCA, position), each in a fresh process, one run",
        "band": args.band[0],
        "sca": args.sca[0],
        "position": position,
        "realizations": args.realizations,
        "runs": out,
    }


# --- interpolation error ------------------------------------------------------------------------


def _slopes_at(band: str, sca: int, position, realizations: int, magnitudes) -> dict:
    settings = tablebuild.TableSettings.roman(realizations=realizations)
    config = settings.config(band, sca, position=position)
    results = experiment.slopes(config, list(magnitudes), beta0=settings.beta0)
    values = np.array([[r.bias[m].mean for m in METRIC_NAMES.values()] for r in results], dtype=float)
    errors = np.array([[r.bias[m].stderr for m in METRIC_NAMES.values()] for r in results], dtype=float)
    saturated = [
        bool(r.extras.get("ramp", {}).get("fitted_on_fewer") or r.extras.get("ramp", {}).get("unusable")) for r in results
    ]
    return {"values": values, "errors": errors, "saturated": saturated}


def measure_interpolation(args) -> dict:
    rng = np.random.default_rng(args.seed)
    mags = np.asarray(args.magnitudes, dtype=float)
    report: dict = {
        "what": "the candidate Roman scene's bias slopes interpolated across the SCA, against fresh simulations",
        "scene": "roman_default.scene: preset roman + position + roman-typical background, HLWAS ramp "
        "(optimal fit), official pupil scale",
        "fidelity": "linear",
        "realizations": args.realizations,
        "common_centroids": "every position uses the same centroid draws (seed): the errors are the interpolation's",
        "near_zero": f"|slope| < {NEAR_ZERO_FRACTION:g} x median |slope| (band, metric, magnitude; all positions)",
        "magnitudes": list(mags),
        "simulations": [],
    }
    start = time.process_time()
    for band in args.band:
        for sca in args.sca:
            nodes5 = fieldgrid.grid_positions(5)
            values = np.zeros((5, 5, len(mags), 3))
            for i, j, pos in nodes5:
                values[j, i] = _slopes_at(band, sca, pos, args.realizations, mags)["values"]
            randoms = [tuple(float(v) for v in rng.uniform(1.0, 4088.0, 2)) for _ in range(args.random)]
            fresh = [_slopes_at(band, sca, pos, args.realizations, mags) for pos in randoms]
            report["simulations"].append(
                {
                    "band": band,
                    "sca": sca,
                    "nodes_5x5": values.tolist(),
                    "random_positions": randoms,
                    "fresh": [f["values"].tolist() for f in fresh],
                    "fresh_stderr": [f["errors"].tolist() for f in fresh],
                    "saturated_resultants": [f["saturated"] for f in fresh],
                }
            )
            print(f"{band} SCA {sca}: done ({time.process_time() - start:.0f} s CPU)", file=sys.stderr)
    report["cpu_s"] = time.process_time() - start
    report["cases"] = cases(report)
    report["summary"] = summarise(report["cases"])
    return report


#: Sub-grids of the simulated 5 x 5 nodes: 3 x 3 (every other node) and 2 x 2 (the corners).
SUBGRIDS = {5: slice(None), 3: slice(None, None, 2), 2: slice(None, None, 4)}


def cases(report: dict) -> list[dict]:
    """Every (random position, grid, scheme, magnitude, metric) comparison of a report's simulations."""
    out = []
    mags = report["magnitudes"]
    for sim in report["simulations"]:
        nodes = np.asarray(sim["nodes_5x5"])
        fresh = np.asarray(sim["fresh"])
        stderr = np.asarray(sim["fresh_stderr"])
        median = np.median(np.abs(np.concatenate([nodes.reshape(-1, len(mags), 3), fresh])), axis=0)
        for r, pos in enumerate(sim["random_positions"]):
            for n, cut in SUBGRIDS.items():
                grid = nodes[cut, cut]
                for scheme in fieldgrid.SCHEMES if n > 2 else ("bilinear",):
                    interp = fieldgrid.interpolate(grid, pos, scheme)
                    for k, mag in enumerate(mags):
                        for q, metric in enumerate(METRIC_NAMES):
                            truth = fresh[r, k, q]
                            error = interp[k, q] - truth
                            out.append(
                                {
                                    "band": sim["band"],
                                    "sca": sim["sca"],
                                    "position": pos,
                                    "grid": n,
                                    "scheme": scheme,
                                    "magnitude": float(mag),
                                    "metric": metric,
                                    "fresh": float(truth),
                                    "interpolated": float(interp[k, q]),
                                    "relative_error": float(error / truth),
                                    "error_over_median": float(error / median[k, q]),
                                    "error_over_stderr": float(error / stderr[r, k, q]),
                                    "near_zero": bool(abs(truth) < NEAR_ZERO_FRACTION * median[k, q]),
                                    "saturated_resultants": bool(sim["saturated_resultants"][r][k]),
                                }
                            )
    return out


def summarise(cases: list[dict]) -> list[dict]:
    """Worst and median |relative error| per band, metric, grid and scheme (near-zero excluded),
    separately for stars with saturated resultants."""
    rows = []
    keys = sorted({(c["band"], c["metric"], c["grid"], c["scheme"], c["saturated_resultants"]) for c in cases})
    for band, metric, grid, scheme, saturated in keys:
        chosen = [
            c
            for c in cases
            if (c["band"], c["metric"], c["grid"], c["scheme"], c["saturated_resultants"])
            == (band, metric, grid, scheme, saturated)
        ]
        usable = [abs(c["relative_error"]) for c in chosen if not c["near_zero"]]
        near = [abs(c["error_over_median"]) for c in chosen if c["near_zero"]]
        rows.append(
            {
                "band": band,
                "metric": metric,
                "grid": grid,
                "scheme": scheme,
                "saturated_resultants": saturated,
                "count": len(usable),
                "max_relative_error": max(usable) if usable else None,
                "median_relative_error": float(np.median(usable)) if usable else None,
                "max_error_over_fresh_stderr": max(abs(c["error_over_stderr"]) for c in chosen),
                "near_zero_count": len(near),
                "near_zero_max_error_over_median": max(near) if near else None,
            }
        )
    return rows


def measure_variation(args) -> dict:
    """The cheaper build: the centre at ``--realizations`` centroids plus the 3 x 3 nodes' difference
    from the centre at ``--field-realizations`` (the same first draws), interpolated; against fresh
    simulations at ``--realizations`` at random positions."""
    rng = np.random.default_rng(args.seed)
    mags = np.asarray(args.magnitudes, dtype=float)
    rows = []
    for band in args.band:
        for sca in args.sca:
            few = np.zeros((3, 3, len(mags), 3))
            for i, j, pos in fieldgrid.grid_positions(3):
                few[j, i] = _slopes_at(band, sca, pos, args.field_realizations, mags)["values"]
            centre = _slopes_at(band, sca, fieldgrid.grid_positions(3)[4][2], args.realizations, mags)["values"]
            for _ in range(args.random):
                pos = tuple(float(v) for v in rng.uniform(1.0, 4088.0, 2))
                fresh = _slopes_at(band, sca, pos, args.realizations, mags)
                answer = centre + fieldgrid.interpolate(few - few[1, 1], pos, "lagrange")
                for k, mag in enumerate(mags):
                    for q, metric in enumerate(METRIC_NAMES):
                        truth = fresh["values"][k, q]
                        rows.append(
                            {
                                "band": band,
                                "sca": sca,
                                "position": pos,
                                "magnitude": float(mag),
                                "metric": metric,
                                "relative_error": float((answer[k, q] - truth) / truth),
                                "error_over_stderr": float((answer[k, q] - truth) / fresh["errors"][k, q]),
                                "saturated_resultants": fresh["saturated"][k],
                            }
                        )
            print(f"{band} SCA {sca}: done", file=sys.stderr)
    summary = {}
    for row in rows:
        key = f"{row['band']} {row['metric']} {'saturated' if row['saturated_resultants'] else 'unsaturated'}"
        entry = summary.setdefault(key, {"max_relative_error": 0.0, "max_error_over_stderr": 0.0})
        entry["max_relative_error"] = max(entry["max_relative_error"], abs(row["relative_error"]))
        entry["max_error_over_stderr"] = max(entry["max_error_over_stderr"], abs(row["error_over_stderr"]))
    return {
        "what": "centre table + interpolated node-minus-centre differences at fewer centroids, against fresh simulations",
        "realizations": args.realizations,
        "field_realizations": args.field_realizations,
        "magnitudes": list(mags),
        "cases": rows,
        "summary": summary,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cost", action="store_true", help="measure the cost of one table instead")
    parser.add_argument("--variation", action="store_true", help="measure the centre + field-variation scheme instead")
    parser.add_argument("--field-realizations", type=int, default=32, help="centroids of the variation nodes")
    parser.add_argument("--band", action="append", help="bands (repeat); default H158 W146 F184")
    parser.add_argument("--sca", action="append", type=int, help="SCAs (repeat); default 1 9 18")
    parser.add_argument("--realizations", type=int, default=None, help="centroids (default 32; 100 with --cost)")
    parser.add_argument("--magnitudes", type=float, nargs="+", default=[17.0, 18.3, 20.0, 22.0])
    parser.add_argument("--random", type=int, default=4, help="random positions per (band, SCA)")
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--sample", type=int, default=4, help="magnitudes the polychromatic cost is projected from")
    parser.add_argument("--position", type=float, nargs=2, default=None, help="--cost at this position (default centre)")
    parser.add_argument("--resummarise", default=None, metavar="JSON", help="recompute cases and summary of a report")
    parser.add_argument("--output", default=None, help="write the JSON here (default: stdout)")
    args = parser.parse_args(argv)
    args.band = args.band or (["H158"] if args.cost else ["H158", "W146", "F184"])
    args.sca = args.sca or ([18] if args.cost else [1, 9, 18])
    args.realizations = args.realizations or (100 if args.cost or args.variation else 32)
    if args.resummarise:
        with open(args.resummarise) as handle:
            result = json.load(handle)
        result["cases"] = cases(result)
        result["summary"] = summarise(result["cases"])
    else:
        result = measure_cost(args) if args.cost else measure_variation(args) if args.variation else measure_interpolation(args)
    text = json.dumps(result, indent=1, default=float)
    if args.output:
        with open(args.output, "w") as handle:
            handle.write(text + "\n")
        print(f"wrote {args.output}", file=sys.stderr)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
