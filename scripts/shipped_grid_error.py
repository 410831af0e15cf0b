"""The shipped Roman field grid against fresh simulations at random positions (docs/field.md).

At ``--positions`` random (band, SCA, position) among those the grid covers (a position that is no
node), the Roman default's slopes are simulated afresh (``TableSettings.roman()``: the grid's own
settings, 100 centroids, the same seed, so the same centroid draws as every node) at magnitudes
where resultants saturate (the grid's saturation magnitude + 0.3, 1, 2 mag; between the ramp's limit
and the final frame's) and where none does (+4 mag, 20, 22), and compared with
``FieldGrid.slope`` there (float32, magnitude spline, biquadratic across the field). Each case is
classed by the fresh simulation's own ramp summary (any weighted pixel on fewer resultants).
"Near zero": |fresh| < 10 % of the median |slope| of that (band, SCA, metric, magnitude) over the
grid's nodes, excluded from the relative errors (counted).

``--band B`` draws the positions in that band only (other draws than the all-band set);
``--compare OTHER`` reads a second field-grid file at the same cases, against the same fresh
simulations (a 3 x 3 against a 5 x 5 grid, say), summarised beside the first.

    nice -n 10 python scripts/shipped_grid_error.py --positions 16 --output build/shipped_grid_error.json
    nice -n 10 python scripts/shipped_grid_error.py --band W146 --positions 12 --compare old_grid.npz
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from nlpsf.sim import experiment
from nlpsf.slopes import fieldgrid, tablebuild

METRICS = {"size": "dR_over_R", "e1": "de1", "e2": "de2"}
NEAR_ZERO_FRACTION = 0.1
TARGET = {"size": 0.01, "e1": 0.03, "e2": 0.03}


def fresh_slopes(band: str, sca: int, position, magnitudes, realizations: int = 100) -> list:
    settings = tablebuild.TableSettings.roman(realizations=realizations)
    config = settings.config(band, sca, position=position)
    return experiment.slopes(config, list(magnitudes), beta0=settings.beta0, linearise_at=settings.linearise_at)


def _read(grid: fieldgrid.FieldGrid, band: str, sca: int, position, metric: str, magnitude: float, fresh: float, stderr) -> dict:
    value, error = grid.slope(band, sca, position, metric, "bias", magnitude)
    nodes = grid.node_values(band, sca, f"bias_{metric}", magnitude)
    scale = float(np.median(np.abs(nodes)))
    return {
        "near_zero": bool(abs(fresh) < NEAR_ZERO_FRACTION * scale),
        "grid_size": int(grid.meta["tables"][grid.key(band, sca)]["grid"]),
        "grid": float(value),
        "grid_error": float(error),
        "relative_error": float(value / fresh - 1) if fresh else None,
        "in_fresh_stderr": float(abs(value - fresh) / stderr) if stderr else None,
    }


def cases(
    grid: fieldgrid.FieldGrid,
    positions: int,
    seed: int,
    realizations: int = 100,
    band: str | None = None,
    other: fieldgrid.FieldGrid | None = None,
) -> list[dict]:
    rng = np.random.default_rng(seed)
    covered = [pair for pair in grid.coverage() if band is None or pair[0] == band]
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
                row = {"band": band, "sca": sca, "position": position, "magnitude": magnitude, "metric": metric}
                row |= {"saturating": saturating, "fresh": fresh, "fresh_stderr": stderr}
                row |= _read(grid, band, sca, position, metric, magnitude, fresh, stderr)
                if other is not None:
                    row["other"] = _read(other, band, sca, position, metric, magnitude, fresh, stderr)
                out.append(row)
    return out


def summary(rows: list[dict]) -> dict:
    out = {}
    for saturating in (False, True):
        for metric in METRICS:
            picked = [r for r in rows if r["metric"] == metric and r["saturating"] == saturating]
            clear = [r for r in picked if not r["near_zero"] and r["relative_error"] is not None]
            rel = [abs(r["relative_error"]) for r in clear]
            key = f"{'saturating' if saturating else 'no saturation'} {metric}"
            worst = max(clear, key=lambda r: abs(r["relative_error"])) if clear else None
            out[key] = {
                "where": None if worst is None else f"{worst['band']} SCA {worst['sca']}, m = {worst['magnitude']}",
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
    parser.add_argument("--band", default=None, help="draw the positions in this band only")
    parser.add_argument("--compare", default=None, help="a second field-grid file read at the same cases")
    parser.add_argument("--output", default=None)
    args = parser.parse_args()
    grid = fieldgrid.FieldGrid.load(args.grid) if args.grid else fieldgrid.shipped_grid()
    other = fieldgrid.FieldGrid.load(args.compare) if args.compare else None
    cpu = time.process_time()
    rows = cases(grid, args.positions, args.seed, band=args.band, other=other)
    result = {"summary": summary(rows), "cases": rows, "cpu_s": time.process_time() - cpu, "grid": args.grid or "shipped"}
    if other is not None:
        result |= {"compare": args.compare, "summary_compare": summary([{**r, **r["other"]} for r in rows])}
    _print(result["summary"], args.grid or "shipped")
    if other is not None:
        _print(result["summary_compare"], args.compare)
    if args.output:
        with open(args.output, "w") as handle:
            json.dump(result, handle, indent=1)


def _print(table: dict, name: str) -> None:
    print(name)
    for key, value in table.items():
        worst = "-" if value["worst"] is None else f"{100 * value['worst']:.3f} %"
        median = "-" if value["median"] is None else f"{100 * value['median']:.3f} %"
        print(
            f"{key:>20}: {value['cases']} cases ({value['near_zero']} near zero), worst {worst}, median {median}, "
            f"worst/stderr {value['worst_in_fresh_stderr']:.2f}, target {100 * value['target']:g} % ({value['where']})"
        )


if __name__ == "__main__":
    main()
