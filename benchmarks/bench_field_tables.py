"""CPU cost of Roman-default field-grid tables as a build pays them, and the before/after ratio of a change.

Work: ``tablebuild.compute_table`` with ``TableSettings.roman()`` (100 centroids, the tables' magnitude
grid, linear response, the corrected state) for a sample of nodes: by default one SCA per band (a
different one each) and three of its 3 x 3 nodes, computed in that order in one fresh process, after
one small warm-up table of another band and SCA (imports and the background files are paid once per
worker; the optics of every node, and each SCA's pupil polynomials once, are paid as in a build,
where a worker takes about half the nodes of an SCA in a row). ``--before PATH``: the same sample,
in a fresh process of its own, with the nlpsf found at PATH (a checkout of an earlier commit, e.g.
``git archive 82794a9 | tar -x -C PATH``); ``--repeat`` alternates the two. CPU seconds
(``time.process_time``), BLAS on one thread. Usage:

    OMP_NUM_THREADS=1 python benchmarks/bench_field_tables.py [--before PATH] [--repeat 2] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

#: (band, SCA): every band once, on SCAs spread over the focal plane.
SAMPLE = (("R062", 3), ("Z087", 5), ("Y106", 7), ("J129", 9), ("H158", 11), ("F184", 13), ("K213", 15), ("W146", 17))
NODES = ((3, 0, 0), (3, 1, 1), (3, 2, 2))

CHILD = r"""
import json, sys, time
from nlpsf.slopes import tablebuild
sample, nodes = json.loads(sys.argv[1]), [tuple(n) for n in json.loads(sys.argv[2])]
roman = tablebuild.TableSettings.roman
tablebuild.compute_table("H158", 1, roman(realizations=2, faint_limit=15.0), node=(3, 1, 0))  # warm-up
out = []
for band, sca in sample:
    for node in nodes:
        start = time.process_time()
        table = tablebuild.compute_table(band, sca, roman(), node=node)
        out.append({"band": band, "sca": sca, "node": node, "cpu_s": time.process_time() - start, "rows": len(table)})
print(json.dumps(out))
"""


def sample_cost(sample, nodes, code: str | None = None) -> list[dict]:
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    if code:
        env["PYTHONPATH"] = code
    args = [sys.executable, "-c", CHILD, json.dumps(sample), json.dumps(nodes)]
    out = subprocess.run(args, env=env, capture_output=True, text=True, check=True, cwd=code)
    return json.loads(out.stdout.strip().splitlines()[-1])


def per_band(rows: list[dict]) -> dict[str, float]:
    out: dict[str, float] = {}
    for row in rows:
        out[row["band"]] = out.get(row["band"], 0.0) + row["cpu_s"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--band", action="append", default=None, help="only these bands of the sample")
    parser.add_argument("--before", default=None, help="path holding an earlier nlpsf/ to time the same sample with")
    parser.add_argument("--repeat", type=int, default=1, help="runs of each (alternating, before first)")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    sample = [s for s in SAMPLE if not args.band or s[0] in args.band]
    runs: dict[str, list] = {"after": [], "before": []}
    for _ in range(args.repeat):
        if args.before:
            runs["before"].append(sample_cost(sample, NODES, args.before))
        runs["after"].append(sample_cost(sample, NODES))
    for which in ("before", "after"):
        for k, rows in enumerate(runs[which]):
            bands = per_band(rows)
            total = sum(bands.values())
            print(
                f"{which} run {k + 1}: {total:.2f} CPU-s for {len(rows)} tables ({total / len(rows):.2f} per table); "
                + ", ".join(f"{b} {v / len(NODES):.2f}" for b, v in bands.items()),
                flush=True,
            )
    if args.before:
        for k, (before, after) in enumerate(zip(runs["before"], runs["after"], strict=True)):
            b, a = per_band(before), per_band(after)
            ratios = ", ".join(f"{band} x {b[band] / a[band]:.2f}" for band in a)
            print(f"pair {k + 1}: speed-up x {sum(b.values()) / sum(a.values()):.2f} (CPU-s ratio); {ratios}", flush=True)
    if args.json:
        with open(args.json, "w") as handle:
            json.dump({"sample": sample, "nodes": NODES, **runs}, handle, indent=1)


if __name__ == "__main__":
    main()
