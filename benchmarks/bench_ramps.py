"""Cost of an up-the-ramp simulation relative to the paper's final frame, measured in one run.

Work: H158, SCA 18, the paper's grid settings (N = 3, 96 x 96, R centroid realizations, default
100), one scene prepared once (optics, stamps, reference moments: the same for every exposure
model), then for each exposure model the paper's 5 magnitudes x 1 beta (beta0 = 5e-7), with both
methods (``monte_carlo``: every realization fitted; ``linear``: first-order response). Exposure
models: the final frame; ``--ramp 55`` (uniform, OLS); the shipped MA table romanisim-110 with the
OLS (romancal's saturation rules, the default, and nlpsf's older charge rule) and with the optimal
fit. The magnitudes include two brighter than the final frame's
saturation, where pixels drop resultants.

Also timed: the ramp's pixel step alone for the whole scene (per-pixel ramp factors, the vectorised
path the simulator uses) against evaluating every read explicitly (``ramps.simulate_pixels``), and
one calculator answer (``nlpsf solve``) without a ramp, with a ramp read from the tables at beta_eff,
and with a ramp that needs fresh linear-response simulations.

Each timing is the median of ``--repeat`` runs. Usage:
python benchmarks/bench_ramps.py [--realizations 100] [--repeat 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

MAGNITUDES = (16.0, 17.0, 18.3, 20.0, 22.0)
BETA0 = 5e-7


def median_time(function, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--realizations", type=int, default=100)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--json", default=None, help="also write the numbers to this file")
    args = parser.parse_args()

    from nlpsf import defaults
    from nlpsf.sim import experiment, ramps
    from nlpsf.solve import solver

    exptime = defaults.EXPTIME_S
    table = ramps.load_ma_table("romanisim-110")
    models = {
        "final frame": (None, exptime),
        "uniform-55 OLS": (ramps.Ramp.uniform(55, exptime), exptime),
        "romanisim-110 OLS": (ramps.Ramp(table), table.duration_s),
        # nlpsf's rules before romancal's (charge saturation, one-resultant fit through zero): the
        # cost of judging saturation on the resultants' signal.
        "romanisim-110 OLS, charge rule": (
            ramps.Ramp(table, saturation="charge", single_resultant="through_zero"),
            table.duration_s,
        ),
        "romanisim-110 optimal": (ramps.Ramp(table, fit="optimal"), table.duration_s),
    }
    base = experiment.SimulationConfig(realizations=args.realizations)
    t0 = time.perf_counter()
    scene = experiment.prepare(base)
    prepare_s = time.perf_counter() - t0

    out: dict = {"realizations": args.realizations, "magnitudes": MAGNITUDES, "prepare_s": prepare_s, "simulate_s": {}}
    for method in ("monte_carlo", "linear"):
        for name, (ramp, exp_s) in models.items():
            config = experiment.SimulationConfig(realizations=args.realizations, method=method, exptime_s=exp_s, ramp=ramp)
            # Same stamps and reference fits: the exposure model changes only the detector step.
            same = experiment.Scene(config, scene.psf, scene.offsets, scene.stamps, scene.reference, 0.0)
            out["simulate_s"][f"{method} | {name}"] = median_time(
                lambda config=config, same=same: experiment.simulate(config, MAGNITUDES, [BETA0], scene=same), args.repeat
            )

    ramp = models["romanisim-110 optimal"][0]
    charge = scene.stamps * 1e5 / scene.stamps.max()  # peak at ~the full well
    out["pixel_step_s"] = {
        "ramp factors (vectorised)": median_time(lambda: ramps.order_factors(charge, ramp, table.duration_s, 1.1e5), args.repeat),
        "explicit reads": median_time(lambda: ramps.simulate_pixels(charge, ramp, table.duration_s, 1.1e5), args.repeat),
    }

    question = {"precision": 0.01, "magnitude": 19.0}
    out["solve_s"] = {
        "final frame (table)": median_time(lambda: solver.solve("H158", **question), args.repeat),
        "uniform-8 OLS (table at beta_eff)": median_time(
            lambda: solver.solve("H158", **question, ramp=ramps.Ramp.uniform(8, exptime)), args.repeat
        ),
        "uniform-8 optimal (fresh linear response)": median_time(
            lambda: solver.solve("H158", **question, ramp=ramps.Ramp.uniform(8, exptime, fit="optimal")), args.repeat
        ),
    }

    print(f"H158 SCA 18, {args.realizations} realizations, {len(MAGNITUDES)} magnitudes x 1 beta; median of {args.repeat}")
    print(f"scene (optics, stamps, reference moments, shared by all): {prepare_s:.2f} s")
    for method in ("monte_carlo", "linear"):
        reference = out["simulate_s"][f"{method} | final frame"]
        for name in models:
            seconds = out["simulate_s"][f"{method} | {name}"]
            print(f"  {method:<11} {name:<30} {seconds:8.3f} s   x{seconds / reference:5.2f} of the final frame")
    fast, slow = out["pixel_step_s"].values()
    print(f"ramp pixel step, whole scene, romanisim-110 optimal: factors {fast:.3f} s, explicit reads {slow:.3f} s", end="")
    print(f" (x{slow / fast:.1f})")
    reference = out["solve_s"]["final frame (table)"]
    for name, seconds in out["solve_s"].items():
        print(f"  solve {name:<42} {seconds * 1e3:9.2f} ms   x{seconds / reference:8.1f}")
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(out, handle, indent=2)


if __name__ == "__main__":
    main()
