"""Peak memory of one simulation job per stamp pixel (realizations x stamp^2), to set the service's
``max_stamp_pixels`` and ``job_memory_mb`` from a measurement rather than from 8 bytes a pixel.

Each case runs in a fresh process (as a job does) and reports its peak RSS (``ru_maxrss``). The
marginal cost per stamp pixel is the slope between the smallest and the largest run of a fidelity,
so the interpreter and library baseline (the intercept) is reported separately.

Usage: python benchmarks/bench_job_memory.py [--largest 1200]
"""

from __future__ import annotations

import argparse
import multiprocessing
import resource
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def _child(request: dict, queue) -> None:
    from nlpsf.web import job_kinds

    job_kinds.run(request)
    queue.put(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024)


def peak_bytes(request: dict) -> int:
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()
    process = context.Process(target=_child, args=(request, queue))
    process.start()
    value = queue.get(timeout=1800)
    process.join()
    return value


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--largest", type=int, default=1200, help="realizations of the largest run (default 1200)")
    args = parser.parse_args()
    from nlpsf.web import models

    base = models.SimulationRequest(magnitudes=[18.3, 20.0], betas=[5e-7]).model_dump()
    print(f"{'fidelity':<14} {'realizations':>12} {'stamp px':>12} {'peak MB':>9}")
    slopes = {}
    for fidelity, extra in (("linear", {}), ("monte_carlo", {}), ("polychromatic", {"n_wavelengths": 8})):
        points = []
        for realizations in (args.largest // 6, args.largest):
            request = {**base, **extra, "fidelity": fidelity, "realizations": realizations, "band": "H158"}
            from nlpsf.web import job_kinds
            from nlpsf.web.settings import Limits

            normalised = job_kinds.validate(request, Limits(max_realizations=100_000, max_stamp_pixels=10**11, max_work=10**15))
            pixels = realizations * normalised["stamp"] ** 2
            peak = peak_bytes(normalised)
            points.append((pixels, peak))
            print(f"{fidelity:<14} {realizations:>12} {pixels:>12,} {peak / 1e6:>9.0f}")
        (p0, b0), (p1, b1) = points
        slopes[fidelity] = ((b1 - b0) / (p1 - p0), b0 - (b1 - b0) / (p1 - p0) * p0)
    print()
    for fidelity, (slope, intercept) in slopes.items():
        print(f"{fidelity:<14} {slope:6.1f} bytes per stamp pixel, baseline {intercept / 1e6:.0f} MB")
    worst = max(s for s, _ in slopes.values())
    print(f"\nworst case: {worst:.1f} bytes per stamp pixel")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
