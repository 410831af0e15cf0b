"""The Roman default's field grid between the saturation limits, against fresh simulations, and why
it misses there (issue 28, item 1; docs/field.md, "Between the saturation limits").

At ``--points`` random (band, SCA, position, magnitude) with the magnitude uniform between the
ramp's saturation limit and the final frame's at that position (where pixels lose resultants), the
default's bias slopes (size, e1, e2) are simulated afresh at the position with the grid's own
settings (``TableSettings.roman()``: 100 centroids, seed 1, the draws every node shares) and
compared with the shipped grid's answer there. The difference is split into:

- ``magnitude``: the nodes' magnitude interpolation, sum_k w_k (node spline_k(m) - node_k(m)), with
  node_k(m) each node simulated afresh at exactly m (the grid's splines against their own scene);
- ``field``: the field interpolation at exact magnitudes, sum_k w_k node_k(m) - fresh(x, m);
- ``draws``: how much the fresh value itself moves with other centroid draws (seed 2, 100
  centroids): the scale of the truth's own sampling error, which no interpolant can beat.

``total = magnitude + field`` exactly (same draws everywhere). With ``--dense STEP`` the magnitude
part is also measured for node tables sampled every STEP mag between the limits (the build recipe
``tablebuild.magnitude_grid(between=...)``): each node simulated on that grid around m and its spline
(the grid's own: not-a-knot cubic of slope/flux in flux) evaluated at m.

    nice -n 10 python scripts/between_limits_error.py --points 12 --output build/between_limits.json

``--answers``: also what a user gets there, the default answer (``nlpsf.answer``; simulated afresh
between the limits since issue 28, with the request's residual model), against a fresh
``--fidelity polychromatic`` answer of the same request. The grid comparisons use the grid's own
residual model (its nodes' setting), so that they differ by the interpolation alone.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np
from scipy.interpolate import CubicSpline

from nlpsf.sim import experiment
from nlpsf.slopes import fieldgrid, tablebuild

METRICS = {"size": "dR_over_R", "e1": "de1", "e2": "de2"}


#: The residual model the simulations use: the grid's own (``fieldgrid.grid_residual_model``), set by
#: :func:`main` from the grid read, so that grid and fresh values differ by the interpolation alone.
RESIDUAL_NL: str | None = None


def simulate(band, sca, position, magnitudes, seed=1, realizations=100):
    """{metric: [(value, stderr), ...]} and the ramp summary per magnitude, the grid's settings."""
    settings = tablebuild.TableSettings.roman(realizations=realizations, seed=seed, residual_nl=RESIDUAL_NL)
    config = settings.config(band, sca, position=position)
    results = experiment.slopes(
        config, list(magnitudes), beta0=settings.beta0, linearise_at=settings.linearise_at, residual_nl=settings.residual_nl
    )
    out = {metric: [(r.bias[name].mean, r.bias[name].stderr) for r in results] for metric, name in METRICS.items()}
    out["flux"] = [r.flux_electrons for r in results]
    out["ramp"] = [{k: r.extras.get("ramp", {}).get(k) for k in ("fitted_on_fewer", "unusable", "pixels")} for r in results]
    return out


def draw_point(grid, rng, band=None, only=None):
    covered = [pair for pair in grid.coverage() if (band is None or pair[0] == band) and (not only or pair in only)]
    band, sca = covered[int(rng.integers(len(covered)))]
    position = tuple(float(v) for v in rng.uniform(60.0, 4030.0, 2))
    ramp = grid.saturation_magnitude(band, sca, position)
    final = grid.final_frame_saturation_magnitude(band, sca, position)
    magnitude = round(float(rng.uniform(ramp + 0.05, final - 0.05)), 3)
    return band, sca, position, magnitude, ramp, final


def node_spline_at(band, sca, node, magnitude, step, seed=1):
    """A node's spline at ``magnitude`` from rows every ``step`` mag around it (7 rows each side):
    the grid's interpolant (cubic of slope/flux in flux) on a denser magnitude sampling."""
    rows = np.round(np.arange(-7, 8) * step + (math.floor(magnitude / step) + 0.5) * step, 6)
    sim = simulate(band, sca, node, rows, seed)
    flux = np.asarray(sim["flux"])
    order = np.argsort(flux)
    target = simulate(band, sca, node, [magnitude], seed)
    out = {}
    for metric in METRICS:
        values = np.asarray([v for v, _ in sim[metric]])
        spline = CubicSpline(flux[order], (values / flux)[order])
        f = target["flux"][0]
        out[metric] = (float(spline(f) * f), target[metric][0][0])
    return out


def measure(grid, band, sca, position, magnitude, dense=None) -> dict:
    n = int(grid.conditions(band, sca)["grid"])
    w = fieldgrid.weights(n, position)
    nodes = fieldgrid.grid_positions(n)
    fresh = simulate(band, sca, position, [magnitude])
    other = simulate(band, sca, position, [magnitude], seed=2)
    exact = {metric: np.zeros((n, n)) for metric in METRICS}
    for i, j, node in nodes:
        sim = simulate(band, sca, node, [magnitude])
        for metric in METRICS:
            exact[metric][j, i] = sim[metric][0][0]
    out = {"band": band, "sca": sca, "position": list(position), "magnitude": magnitude, "grid_size": n}
    out["ramp"] = fresh["ramp"][0]
    out["metrics"] = {}
    for metric in METRICS:
        value, error = grid.slope(band, sca, position, metric, "bias", magnitude)
        node_spline = grid.node_values(band, sca, f"bias_{metric}", magnitude)
        truth, stderr = fresh[metric][0]
        field = float(np.sum(w * exact[metric]))
        out["metrics"][metric] = {
            "fresh": truth,
            "fresh_stderr": stderr,
            "fresh_seed2": other[metric][0][0],
            "grid": float(value),
            "grid_stated_error": float(error),
            "field_only": field,
            "total": float(value) - truth,
            "field": field - truth,
            "magnitude": float(np.sum(w * (node_spline - exact[metric]))),
            "draws": other[metric][0][0] - truth,
            "node_magnitude_errors": (node_spline - exact[metric]).tolist(),
        }
    if dense:
        # The dense recipe's magnitude error at the node nearest the position (its largest weight).
        j, i = np.unravel_index(np.argmax(np.abs(w)), w.shape)
        node = nodes[j * n + i][2]
        spline = node_spline_at(band, sca, node, magnitude, dense)
        for metric in METRICS:
            interpolated, simulated = spline[metric]
            out["metrics"][metric]["dense_magnitude_at_node"] = {
                "node": list(node),
                "step": dense,
                "interpolated": interpolated,
                "simulated": simulated,
                "shipped_node_error": float(grid.node_values(band, sca, f"bias_{metric}", magnitude)[j, i] - simulated),
            }
    return out


def answers(band, sca, position, magnitude) -> dict:
    """The default answer at the point (``nlpsf.answer``, what a user gets) against a fresh
    ``--fidelity polychromatic`` answer of the same scene (Monte Carlo, 8 wavelengths, the same 100
    centroids), per metric: their slopes and the default's flag codes."""
    from dataclasses import replace

    from nlpsf import SolveRequest, answer
    from nlpsf.request import presets

    scene = replace(presets.base_scene(), position=tuple(position))
    out = {}
    for metric in METRICS:
        request = {"sca": sca, "metric": metric, "magnitude": magnitude, "precision": 0.01, "scene": scene}
        default = answer(SolveRequest(band, **request))
        poly = answer(SolveRequest(band, fidelity="polychromatic", **request))
        out[metric] = {
            "default": default.slope,
            "default_error": default.slope_uncertainty,
            "default_fidelity": default.fidelity,
            "default_flags": [getattr(f, "code", None) and f.code.value for f in default.flags],
            "polychromatic": poly.slope,
            "polychromatic_error": poly.slope_uncertainty,
            "relative": (default.slope - poly.slope) / abs(poly.slope) if poly.slope else None,
        }
    return out


def relative(row: dict, part: str, metric: str) -> float:
    m = row["metrics"][metric]
    return m[part] / abs(m["fresh"]) if m["fresh"] else math.nan


def summary(rows: list[dict]) -> dict:
    out = {}
    for metric in METRICS:
        parts = {}
        for part in ("total", "magnitude", "field", "draws"):
            values = [abs(relative(r, part, metric)) for r in rows]
            parts[part] = {"median": float(np.median(values)), "worst": float(np.max(values))}
        within = sum(abs(relative(r, "total", metric)) <= (0.05 if metric == "size" else 0.10) for r in rows)
        parts["within_target"] = f"{within} of {len(rows)}"
        out[metric] = parts
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=8)
    parser.add_argument("--seed", type=int, default=28)
    parser.add_argument("--first", type=int, default=0, help="skip the first N draws (resume)")
    parser.add_argument("--band", default=None)
    parser.add_argument("--grid", default=None, help="field-grid file (default: the shipped one)")
    parser.add_argument("--dense", type=float, default=None, help="also the node magnitude error at this row step")
    parser.add_argument("--only", default=None, help="draw in these (band, SCA)s only: B:S,B:S,...")
    parser.add_argument(
        "--answers", action="store_true", help="also the default answer against a fresh --fidelity polychromatic one"
    )
    parser.add_argument("--output", default=None)
    args = parser.parse_args()
    grid = fieldgrid.FieldGrid.load(args.grid) if args.grid else fieldgrid.shipped_grid()
    global RESIDUAL_NL
    band, sca = grid.coverage()[0]
    RESIDUAL_NL = fieldgrid.grid_residual_model(grid.conditions(band, sca)["settings"])
    print(f"the grid's residual model: {RESIDUAL_NL}", flush=True)
    rng = np.random.default_rng(args.seed)
    only = None if not args.only else [(b, int(s)) for b, s in (item.split(":") for item in args.only.split(","))]
    rows = []
    for index in range(args.points):
        band, sca, position, magnitude, ramp, final = draw_point(grid, rng, args.band, only)
        if index < args.first:
            continue
        cpu = time.process_time()
        row = measure(grid, band, sca, position, magnitude, args.dense)
        if args.answers:
            row["answers"] = answers(band, sca, position, magnitude)
            print(
                "   default vs polychromatic: "
                + ", ".join(f"{m} {100 * a['relative']:+.2f} %" for m, a in row["answers"].items() if a["relative"] is not None),
                flush=True,
            )
        row.update(index=index, limits=[ramp, final], cpu_s=time.process_time() - cpu)
        rows.append(row)
        text = ", ".join(
            f"{metric} {100 * relative(row, 'total', metric):+.2f} % (mag {100 * relative(row, 'magnitude', metric):+.2f},"
            f" field {100 * relative(row, 'field', metric):+.2f}, draws {100 * relative(row, 'draws', metric):+.2f})"
            for metric in METRICS
        )
        print(f"#{index} {band} SCA {sca} ({position[0]:.0f}, {position[1]:.0f}) m={magnitude}: {text}", flush=True)
        if args.output:
            with open(args.output, "w") as handle:
                json.dump({"rows": rows, "summary": summary(rows)}, handle, indent=1)
    print(json.dumps(summary(rows), indent=1))


if __name__ == "__main__":
    main()
