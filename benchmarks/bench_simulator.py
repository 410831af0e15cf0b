"""Speed of the simulator against the GalSim pipeline, on identical work, measured in one run.

Work: the paper's Fig. 3 grid on SCA 18 -- 4 bands (Y106 J129 H158 F184) x 7 magnitudes
(18.3 19 20 21 22 23 24) x 3 beta (beta0 x {0.99, 1, 1.01}, beta0 = 5e-7) x R centroid
realizations (default 100), N = 3, 96 x 96 stamps, 168.1 s. Both sides use the same centroid
offsets and compute, for every cell, the mean Delta R / R, Delta e1, Delta e2 over realizations.

Peers (GalSim 2.8, ``pip install nlpsf[reference]``):
- ``galsim-paper``: the paper's procedure -- for each (band, m, beta, realization) draw the
  reference image and the NL image, measure both with FindAdaptiveMom;
- ``galsim-reuse``: a careful GalSim user -- draw each centroid once per band, reuse it for
  every (m, beta) (same numbers, fewer draws).

Prints ratios (GalSim time / nlpsf time), per-realization costs, where the time goes, nlpsf's
peak memory (a fresh subprocess's max RSS), and how far the two pipelines' answers are apart. The
shell run (four ``nlpsf simulate`` processes) uses the caller's environment as it is: no thread
count is pinned. ``python benchmarks/run_all.py --only simulator`` writes the output into
docs/benchmarks.md.
Usage: python benchmarks/bench_simulator.py [--realizations 100] [--skip-paper-pipeline]
"""

from __future__ import annotations

import argparse
import compileall
import importlib.util
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

BANDS = ("Y106", "J129", "H158", "F184")
MAGNITUDES = (18.3, 19.0, 20.0, 21.0, 22.0, 23.0, 24.0)
BETA0 = 5e-7
BETAS = (0.99 * BETA0, BETA0, 1.01 * BETA0)
SCA = 18
#: GalSim's Roman module uses its 2021 effective areas: the cell means compare like with like.
THROUGHPUT = "galsim-2021"
#: The design goal: the grid from the shell, as a user runs it, at least this many times cheaper in
#: CPU than the paper's GalSim pipeline in the same run (issue 16).
SHELL_TARGET = 300


def run_nlpsf(realizations: int, method: str = "monte_carlo") -> dict:
    """The whole grid with nlpsf, cold (optics computed here), with a time breakdown."""
    from nlpsf import threads

    # The library's entry points run their kernels on NLPSF_BLAS_THREADS threads; this timing calls
    # the kernels one by one, so it applies the same limit around them.
    with threads.limited_blas():
        return _run_nlpsf(realizations, method)


def _run_nlpsf(realizations: int, method: str) -> dict:
    from nlpsf.sim import experiment, moments, optics, render

    optics.effective_psf.cache_clear()
    timings = {"optics": 0.0, "rendering": 0.0, "reference_moments": 0.0, "perturbed_moments": 0.0}
    cells = {}
    start = time.perf_counter()
    for band in BANDS:
        config = experiment.SimulationConfig(band=band, sca=SCA, realizations=realizations, method=method, throughput=THROUGHPUT)
        t = time.perf_counter()
        psf = optics.effective_psf(config.optics, round(config.grid.field_arcsec(), 9))
        timings["optics"] += time.perf_counter() - t
        t = time.perf_counter()
        offsets = render.draw_offsets(np.random.default_rng(config.seed), realizations, config.oversampling)
        stamps = render.draw(psf, config.grid, offsets)
        timings["rendering"] += time.perf_counter() - t
        t = time.perf_counter()
        reference = moments.fit(stamps, config.moment_settings)
        timings["reference_moments"] += time.perf_counter() - t
        scene = experiment.Scene(config, psf, offsets, stamps, reference, 0.0)
        t = time.perf_counter()
        results = experiment.simulate(config, MAGNITUDES, BETAS, scene=scene)
        timings["perturbed_moments"] += time.perf_counter() - t
        for r in results:
            cells[f"{band} {r.magnitude:g} {r.beta:.4g}"] = [r.dR_over_R.mean, r.de1.mean, r.de2.mean]
    total = time.perf_counter() - start
    return {"total_s": total, "timings": timings, "cells": cells, "offsets_seed": 1}


def run_galsim(realizations: int, redraw: bool) -> dict:
    from nlpsf.sim import experiment, reference, render

    timings = {"setup": 0.0, "draw": 0.0, "measure": 0.0}
    cells = {}
    start = time.perf_counter()
    cpu_start = time.process_time()
    for band in BANDS:
        config = experiment.SimulationConfig(band=band, sca=SCA, realizations=realizations, throughput=THROUGHPUT)
        offsets = render.draw_offsets(np.random.default_rng(config.seed), realizations, config.oversampling)
        t = time.perf_counter()
        pipeline = reference.GalSimPipeline(band, SCA, weight_cut_rho2=config.weight_cut_rho2)
        pipeline.draw(1.0, (0.0, 0.0))  # GalSim builds the PSF lazily on the first draw
        timings["setup"] += time.perf_counter() - t
        cached = {}
        for magnitude in MAGNITUDES:
            flux = pipeline.electrons(magnitude, 168.1)
            for beta in BETAS:
                rows = []
                for k, (dx, dy) in enumerate(offsets):
                    t = time.perf_counter()
                    if redraw or k not in cached:
                        unit = pipeline.draw(1.0, (dx, dy))
                        if not redraw:
                            cached[k] = unit
                    else:
                        unit = cached[k]
                    image = unit * flux
                    distorted = pipeline.draw(flux, (dx, dy)) if redraw else image.copy()
                    timings["draw"] += time.perf_counter() - t
                    t = time.perf_counter()
                    ref = pipeline.measure(image, precision=1e-6)
                    distorted.applyNonlinearity(lambda x, b: x - b * x * x, beta)
                    nl = pipeline.measure(distorted, precision=1e-6)
                    timings["measure"] += time.perf_counter() - t
                    rows.append(ref + nl)
                v = np.asarray(rows)
                cells[f"{band} {magnitude:g} {beta:.4g}"] = [
                    float(np.mean(v[:, 3] / v[:, 0] - 1)),
                    float(np.mean(v[:, 4] - v[:, 1])),
                    float(np.mean(v[:, 5] - v[:, 2])),
                ]
    return {"total_s": time.perf_counter() - start, "cpu_s": time.process_time() - cpu_start, "timings": timings, "cells": cells}


def _child(realizations: int, method: str) -> None:
    result = run_nlpsf(realizations, method)
    result["max_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps(result))


def measure_nlpsf(realizations: int, method: str = "monte_carlo") -> dict:
    """Run nlpsf in a fresh interpreter so its peak memory is its own."""
    out = subprocess.run(
        [sys.executable, __file__, "--child", str(realizations), method],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, "PYTHONHASHSEED": "0"},
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_cli_processes(realizations: int) -> dict:
    """The grid as a user runs it from the shell: one `nlpsf simulate` process per band.

    CPU time of the child processes (user + system), which a shared machine does not inflate the
    way it does wall time. Every process computes its own optics (nothing is cached between
    processes). The environment is the user's own: no thread count is pinned here (the library
    chooses its BLAS threads, ``nlpsf/threads.py``). The modules are byte-compiled first, as ``pip
    install`` does for a user: a ``PYTHONDONTWRITEBYTECODE`` environment would otherwise recompile
    them in every process.
    """
    command = [sys.executable, "-m", "nlpsf", "simulate", "--sca", str(SCA), "--realizations", str(realizations)]
    command += ["--throughput", THROUGHPUT]
    command += [a for m in MAGNITUDES for a in ("--magnitude", f"{m:g}")]
    command += [a for b in BETAS for a in ("--beta", repr(b))] + ["--json", "--quiet"]
    environment = dict(os.environ)
    environment.pop("PYTHONDONTWRITEBYTECODE", None)
    package = os.path.dirname(importlib.util.find_spec("nlpsf").origin)
    compileall.compile_dir(package, quiet=1)
    cpu0, wall0 = _children_cpu(), time.perf_counter()
    for band in BANDS:
        subprocess.run([*command, "--band", band], check=True, capture_output=True, env=environment)
    cpu, wall = _children_cpu() - cpu0, time.perf_counter() - wall0
    cpu1 = _children_cpu()
    subprocess.run([sys.executable, "-m", "nlpsf", "--help"], check=True, capture_output=True, env=environment)
    help_cpu = _children_cpu() - cpu1
    cpu2 = _children_cpu()
    solve = [sys.executable, "-m", "nlpsf", "solve", "--band", "H158", "--magnitude", "18.3", "--tolerance", "1e-4"]
    subprocess.run(solve, check=True, capture_output=True, env=environment)
    solve_cpu = _children_cpu() - cpu2
    return {"cpu_s": cpu, "wall_s": wall, "help_cpu_s": help_cpu, "solve_cpu_s": solve_cpu}


def blas_environment() -> str:
    """The BLAS library, its default threads, and what the environment says about threads."""
    from threadpoolctl import threadpool_info

    from nlpsf import threads

    found = [b for b in threadpool_info() if b["user_api"] == "blas"]
    blas = [f"{b['internal_api']} {b['version']}, {b['num_threads']} threads" for b in found]
    pinned = [f"{k}={v}" for k, v in sorted(os.environ.items()) if k.endswith("_NUM_THREADS")]
    kernels = threads.blas_threads()
    return (
        f"{'; '.join(blas) or 'none found'}; {' '.join(pinned) or 'no *_NUM_THREADS set'}; "
        f"the kernels use {kernels if kernels else 'the BLAS default of'} thread(s) ({threads.VARIABLE}="
        f"{os.environ.get(threads.VARIABLE, 'unset')})"
    )


def disagreement(a: dict, b: dict) -> dict:
    worst = {"dR_over_R": 0.0, "de1": 0.0, "de2": 0.0}
    for key, values in a["cells"].items():
        for k, name in enumerate(worst):
            x, y = values[k], b["cells"][key][k]
            worst[name] = max(worst[name], abs(x - y) / max(abs(y), 1e-7 if k else 1e-30))
    return worst


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--realizations", type=int, default=100)
    parser.add_argument("--skip-paper-pipeline", action="store_true", help="skip the slow redraw-everything GalSim peer")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        _child(int(args.child[0]), args.child[1])
        return
    r = args.realizations
    cells = len(BANDS) * len(MAGNITUDES) * len(BETAS)
    print(
        f"Fig. 3 grid: {len(BANDS)} bands x {len(MAGNITUDES)} magnitudes x {len(BETAS)} beta x {r} realizations = "
        f"{cells * r} NL measurements, SCA {SCA}, N=3, 96x96; machine: {os.cpu_count()} cores"
    )
    print(f"BLAS as this environment sets it: {blas_environment()}")
    ours = measure_nlpsf(r)
    linear = measure_nlpsf(r, "linear")
    print(f"\nnlpsf monte_carlo: {ours['total_s']:.2f} s total (cold: optics included), peak RSS {ours['max_rss_mb']:.0f} MB")
    for name, seconds in ours["timings"].items():
        print(f"  {name:<20} {seconds:7.3f} s  ({100 * seconds / ours['total_s']:4.1f} %)")
    print(f"  per NL measurement (perturbed fit): {1e6 * ours['timings']['perturbed_moments'] / (cells * r):.1f} us")
    print(f"nlpsf linear response: {linear['total_s']:.2f} s total, peak RSS {linear['max_rss_mb']:.0f} MB")
    shell = run_cli_processes(r)
    print(
        f"nlpsf from the shell, one `nlpsf simulate` per band: {shell['cpu_s']:.2f} CPU-s ({shell['wall_s']:.2f} s wall); "
        f"`nlpsf --help` {shell['help_cpu_s']:.3f} CPU-s, `nlpsf solve` {shell['solve_cpu_s']:.3f} CPU-s"
    )

    peers = {"galsim-reuse": run_galsim(r, redraw=False)}
    if not args.skip_paper_pipeline:
        peers["galsim-paper"] = run_galsim(r, redraw=True)
    for name, peer in peers.items():
        t = peer["timings"]
        draws = cells * r * 2 if name == "galsim-paper" else len(BANDS) * r
        print(
            f"\n{name}: {peer['total_s']:.1f} s total  "
            f"(setup {t['setup']:.1f} s, drawing {t['draw']:.1f} s, measuring {t['measure']:.1f} s)"
        )
        print(f"  per draw {1e3 * t['draw'] / draws:.1f} ms, per FindAdaptiveMom {1e3 * t['measure'] / (2 * cells * r):.2f} ms")
        print(
            f"  RATIO {name} / nlpsf monte_carlo = {peer['total_s'] / ours['total_s']:.0f}x ;"
            f" / nlpsf linear = {peer['total_s'] / linear['total_s']:.0f}x"
        )
        ratio = peer["cpu_s"] / shell["cpu_s"]
        target = "" if name != "galsim-paper" else f" (target >= {SHELL_TARGET}x: {'met' if ratio >= SHELL_TARGET else 'MISSED'})"
        print(
            f"  CPU RATIO {name} ({peer['cpu_s']:.1f} CPU-s) / nlpsf as four shell processes ({shell['cpu_s']:.2f} CPU-s) = "
            f"{ratio:.0f}x{target}"
        )
        worst = disagreement(ours, peer)
        print(
            "  largest difference of the cell means, nlpsf vs this peer: "
            + ", ".join(f"{k} {100 * v:.2f} %" for k, v in worst.items())
        )
    print(
        "\n(GalSim's default getPSF interpolates a Nyquist-sampled PSF; the differences above are that, see"
        " tests/library/test_reference.py, where GalSim with a finer pupil plane agrees with nlpsf to <1e-4.)"
    )


if __name__ == "__main__":
    main()
