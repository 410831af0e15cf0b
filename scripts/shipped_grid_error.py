"""The shipped Roman field grid against fresh simulations at random positions (docs/field.md).

At ``--positions`` random (band, SCA, position) among those the grid covers (a position that is no
node), the Roman default's slopes are simulated afresh (``TableSettings.roman()``: the grid's own
settings, 100 centroids, the same seed, so the same centroid draws as every node) at magnitudes
where resultants saturate (the grid's saturation magnitude + 0.3, 1, 2 mag; between the ramp's limit
and the final frame's) and where none does (+4 mag, 20, 22), and compared with
``FieldGrid.slope`` there (float32, magnitude spline, biquadratic across the field). Each case is
classed by the fresh simulation's own ramp summary (any weighted pixel on fewer resultants).
"Near zero": |fresh| < 10 % of the median |slope| of that (band, SCA, metric, magnitude) over the
grid's nine nodes, excluded from the relative errors (counted).

    nice -n 10 python scripts/shipped_grid_error.py --positions 16 --output build/shipped_grid_error.json
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from nlpsf import experiment, fieldgrid, tablebuild

METRICS = {"size": "dR_over_R", "e1": "de1", "e2": "de2"}
NEAR_ZERO_FRACTION = 0.1
TARGET = {"size": 0.01, "e1": 0.03, "e2": 0.03}


def fresh_slopes(band: str, sca: int, position, magnitudes, realizations: int = 100) -> list:
    settings = tablebuild.TableSettings.roman(realizations=realizations)
    config = settings.config(band, sca, position=position)
    return experiment.slopes(config, list(magnitudes), beta0=settings.beta0, linearise_at=settings.linearise_at)


def cases(grid: fieldgrid.FieldGrid, positions: int, seed: int, realizations: int = 100) -> list[dict]:
    rng = np.random.default_rng(seed)
    covered = grid.coverage()
    out = []
    for _ in range(positions):
        band, sca = covered[int(rng.integers(len(covered)))]
        position = tuple(float(v) for v in rng.uniform(60.0, 4030.0, 2))
        m_sat = grid.saturation_magnitude(band, sca, position)
        magnitudes = [round(m_sat + d, 3) for d in (0.3, 1.0, 2.0, 4.0)] + [20.0, 22.0]
        results = fresh_slopes(band, sca, position, magnitudes, realizations)
        for magnitude, result in zip(magnitudes, results, strict=True):
            ramp = result.extras["ramp"]
            saturating = bool(ramp["fitted_on_fewer"] or ramp["unusable"])
            for metric, name in METRICS.items():
                fresh, stderr = result.bias[name].mean, result.bias[name].stderr
                value, error = grid.slope(band, sca, position, metric, "bias", magnitude)
                nodes = grid.node_values(band, sca, f"bias_{metric}", magnitude)
                scale = float(np.median(np.abs(nodes)))
                near_zero = abs(fresh) < NEAR_ZERO_FRACTION * scale
                out.append(
                    {
                        "band": band,
                        "sca": sca,
                        "position": position,
                        "magnitude": magnitude,
                        "metric": metric,
                        "saturating": saturating,
                        "near_zero": bool(near_zero),
                        "fresh": fresh,
                        "fresh_stderr": stderr,
                        "grid": float(value),
                        "grid_error": float(error),
                        "relative_error": float(value / fresh - 1) if fresh else None,
                        "in_fresh_stderr": float(abs(value - fresh) / stderr) if stderr else None,
                    }
                )
    return out


def summary(rows: list[dict]) -> dict:
    out = {}
    for saturating in (False, True):
        for metric in METRICS:
            picked = [r for r in rows if r["metric"] == metric and r["saturating"] == saturating]
            rel = [abs(r["relative_error"]) for r in picked if not r["near_zero"] and r["relative_error"] is not None]
            key = f"{'saturating' if saturating else 'no saturation'} {metric}"
            out[key] = {
                "cases": len(picked),
                "near_zero": sum(r["near_zero"] for r in picked),
                "worst": max(rel) if rel else None,
                "median": float(np.median(rel)) if rel else None,
                "worst_in_fresh_stderr": max((r["in_fresh_stderr"] or 0) for r in picked) if picked else None,
                "target": TARGET[metric],
            }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--grid", default=None, help="field-grid file (default: the shipped one)")
    parser.add_argument("--positions", type=int, default=16)
    parser.add_argument("--seed", type=int, default=2026)
    parser.add_argument("--output", default=None)
    args = parser.parse_args()
    grid = fieldgrid.FieldGrid.load(args.grid) if args.grid else fieldgrid.shipped_grid()
    cpu = time.process_time()
    rows = cases(grid, args.positions, args.seed)
    result = {"summary": summary(rows), "cases": rows, "cpu_s": time.process_time() - cpu, "grid": args.grid or "shipped"}
    for key, value in result["summary"].items():
        worst = "-" if value["worst"] is None else f"{100 * value['worst']:.3f} %"
        median = "-" if value["median"] is None else f"{100 * value['median']:.3f} %"
        print(
            f"{key:>20}: {value['cases']} cases ({value['near_zero']} near zero), worst {worst}, median {median}, "
            f"worst/stderr {value['worst_in_fresh_stderr']:.2f}, target {100 * value['target']:g} %"
        )
    if args.output:
        with open(args.output, "w") as handle:
            json.dump(result, handle, indent=1)


if __name__ == "__main__":
    main()
