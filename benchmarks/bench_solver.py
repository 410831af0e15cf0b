"""Speed of the calculator: a solve from the shipped tables, against getting the same slope with the
GalSim pipeline (the paper's way: 100 centroids x beta0 * {0.99, 1.01}, reference and NL images
drawn and measured), measured in one run; and the cost of a fresh solve at each fidelity level.

Usage: python benchmarks/bench_solver.py [--galsim-realizations 100]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np


def time_solves(count: int = 5000) -> dict:
    from nlpsf.slopes import tables
    from nlpsf.solve import solver

    tables.load_tables()
    rng = np.random.default_rng(0)
    cases = []
    for _ in range(count):
        band = str(rng.choice(["Y106", "J129", "H158", "F184"]))
        kind = int(rng.integers(3))
        kwargs = {"band": band, "sca": int(rng.integers(1, 19)), "metric": str(rng.choice(["size", "e"]))}
        if kind == 0:
            kwargs.update(precision=0.01, magnitude=float(rng.uniform(19, 25)))
        elif kind == 1:
            kwargs.update(tolerance=1e-4, magnitude=float(rng.uniform(19, 25)))
        else:
            kwargs.update(precision=0.01, tolerance=float(10 ** rng.uniform(-6, -3)))
        cases.append((kind, kwargs))
    for _, kwargs in cases[:50]:  # build the interpolants once, as a running service has
        solver.solve(**kwargs)
    per_kind: dict[int, list[float]] = {0: [], 1: [], 2: []}
    for kind, kwargs in cases:
        start = time.perf_counter()
        solver.solve(**kwargs)
        per_kind[kind].append(time.perf_counter() - start)
    names = {
        0: "tolerance from (precision, magnitude)",
        1: "precision from (tolerance, magnitude)",
        2: "magnitude from (precision, tolerance)",
    }
    return {names[k]: v for k, v in per_kind.items()}


def galsim_slope_seconds(realizations: int) -> float:
    """The same H158 SCA 18 m=19 size slope from the GalSim pipeline, as the paper computed it."""
    from nlpsf.sim import experiment, reference, render

    config = experiment.SimulationConfig(realizations=realizations)
    offsets = render.draw_offsets(np.random.default_rng(1), realizations, 3)
    start = time.perf_counter()
    pipeline = reference.GalSimPipeline("H158", 18, weight_cut_rho2=config.weight_cut_rho2)
    for beta in (0.99 * 5e-7, 1.01 * 5e-7):
        pipeline.run(19.0, beta, offsets, 168.1, redraw=True, precision=1e-6)
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--galsim-realizations", type=int, default=100)
    args = parser.parse_args()
    from nlpsf.solve import solver

    start = time.perf_counter()
    from nlpsf.slopes import tables

    tables.load_tables.cache_clear()
    tables.load_tables()
    load = time.perf_counter() - start
    print(f"machine: {os.cpu_count()} cores; loading the shipped tables once: {load:.2f} s")
    results = time_solves()
    everything = [t for v in results.values() for t in v]
    for name, values in results.items():
        print(
            f"  solve {name:<40} median {1e6 * statistics.median(values):6.1f} us, p99 {1e6 * np.percentile(values, 99):6.1f} us"
        )
    median = statistics.median(everything)
    print(f"  all solves: median {1e6 * median:.1f} us, p99 {1e6 * np.percentile(everything, 99):.1f} us")

    for level in ("linear", "monte_carlo", "polychromatic"):
        from nlpsf.sim import optics

        optics.effective_psf.cache_clear()
        start = time.perf_counter()
        solver.solve("H158", precision=0.01, magnitude=19.0, fidelity=level)
        print(f"  fresh solve at fidelity {level:<14} {time.perf_counter() - start:6.2f} s (optics included)")

    seconds = galsim_slope_seconds(args.galsim_realizations)
    print(f"\nGalSim pipeline, the same slope ({args.galsim_realizations} centroids, 2 beta): {seconds:.1f} s")
    print(f"RATIO GalSim slope / table solve (median) = {seconds / median:.3g}x")


if __name__ == "__main__":
    main()
