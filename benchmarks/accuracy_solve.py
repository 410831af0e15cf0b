"""Speed of an ``--accuracy 0.01`` solve of the Roman default scene (``nlpsf.solve.accuracy``).

Varied requests -- random band, SCA, field position (neither centre nor corner), metric and
magnitude, half of them solving for the tolerance at a given magnitude, half for the magnitude --
each solved in a fresh state of the PSF cache's neighbours (a different band, SCA and position
every time), with the Roman default's readout (HLWAS ramp, optimal fit) and background. Quoted per
request: wall and CPU seconds of the accuracy solve, and its CPU ratio to two solves of the same
request measured in the same run: ``plain`` (no accuracy, no scene, the same ramp: the Roman
default without a position, read from its field grid's nodes over the SCA) and ``table`` (no ramp
either: the default's HLWAS readout, the grid's nodes again); then the median and the distribution.
Wall exceeds CPU where the machine is shared.

Usage: python benchmarks/accuracy_solve.py [--requests 10] [--seed 17] [--search auto|always]
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np


def requests(count: int, seed: int) -> list[dict]:
    from nlpsf import roman

    rng = np.random.default_rng(seed)
    bands = list(roman.BANDS)
    out = []
    for index in range(count):
        band = bands[index % len(bands)]
        sca = int(rng.integers(1, 19))
        position = (float(rng.uniform(300, 3800)), float(rng.uniform(300, 3800)))
        metric = str(rng.choice(["size", "e1", "e2", "e"]))
        case = {"band": band, "sca": sca, "position": position, "metric": metric}
        if index % 2 == 0:
            case.update(magnitude=float(rng.uniform(19.0, 21.5)), precision=0.01)
        else:
            case.update(precision=0.01, tolerance=float(10 ** rng.uniform(-4.5, -3.5)))
        out.append(case)
    return out


def build(case: dict, accuracy: float | None):
    from nlpsf.request import presets as roman_default
    from nlpsf.request.resolve import SolveRequest

    readout = roman_default.readout(case["band"], case["sca"])
    scene = roman_default.scene(case["position"], readout.background_e)
    triple = {k: case[k] for k in ("precision", "tolerance", "magnitude") if k in case}
    kwargs = dict(metric=case["metric"], ramp=readout.ramp, exptime=readout.exptime_s, **triple)
    full = SolveRequest(case["band"], case["sca"], accuracy=accuracy, scene=scene, **kwargs)
    plain = SolveRequest(case["band"], case["sca"], **kwargs)  # no accuracy, no scene
    table = SolveRequest(case["band"], case["sca"], metric=case["metric"], **triple)  # tables only
    return full, plain, table


def timed(function):
    wall, cpu = time.perf_counter(), time.process_time()
    value = function()
    return value, time.perf_counter() - wall, time.process_time() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--requests", type=int, default=10)
    parser.add_argument("--seed", type=int, default=17)
    parser.add_argument("--accuracy", type=float, default=0.01)
    parser.add_argument("--search", default="auto", choices=("auto", "always", "never"))
    args = parser.parse_args()

    from nlpsf.slopes import tables
    from nlpsf.solve import accuracy, solver

    tables.load_tables()
    solver.answer(build(requests(1, 999)[0], None)[2])  # interpolants built once, as a service has them
    if args.search != "auto":
        original = accuracy.select
        accuracy.select = lambda request, magnitude, tables_set=None: original(request, magnitude, tables_set, args.search)
    rows = []
    for case in requests(args.requests, args.seed):
        full, plain, table = build(case, args.accuracy)
        _, _, plain_cpu = timed(lambda plain=plain: solver.answer(plain))
        _, _, table_cpu = timed(lambda table=table: solver.answer(table))
        answer, wall, cpu = timed(lambda full=full: solver.answer(full))
        rows.append(
            {
                **{k: case[k] for k in ("band", "sca", "metric")},
                "solved_for": answer.solved_for,
                "fidelity": answer.fidelity,
                "left_out": [p.get("members") for p in (answer.model or {}).get("left_out", []) if "members" in p],
                "wall_s": round(wall, 3),
                "cpu_s": round(cpu, 3),
                "plain_solve_cpu_s": round(plain_cpu, 4),
                "table_solve_cpu_s": round(table_cpu, 5),
                "cpu_ratio_to_plain_solve": round(cpu / max(plain_cpu, 1e-6), 2),
                "cpu_ratio_to_table_solve": round(cpu / max(table_cpu, 1e-6)),
            }
        )
        print(json.dumps(rows[-1]), flush=True)
    walls = sorted(r["wall_s"] for r in rows)
    cpus = sorted(r["cpu_s"] for r in rows)
    summary = {
        "requests": len(rows),
        "accuracy": args.accuracy,
        "search": args.search,
        "wall_s": {"median": statistics.median(walls), "min": walls[0], "max": walls[-1], "all": walls},
        "cpu_s": {"median": statistics.median(cpus), "min": cpus[0], "max": cpus[-1]},
        "median_cpu_ratio_to_plain_solve": statistics.median(r["cpu_ratio_to_plain_solve"] for r in rows),
        "median_cpu_ratio_to_table_solve": statistics.median(r["cpu_ratio_to_table_solve"] for r in rows),
    }
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
