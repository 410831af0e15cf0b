"""CPU cost of one Roman-default field-grid table against the paper's table, measured in one run.

Work: ``tablebuild.compute_table`` for the SCA's centre node of the 3 x 3 grid (``TableSettings.roman()``:
100 centroids, the tables' magnitude grid, linear response, the corrected state) and the paper's
centre table (``TableSettings()``), for each band given, each in a fresh process, after one warm-up
table in that process (so imports, the optics' caches and the background files are not counted: a
build pays them once per worker). ``--before PATH``: also the same Roman table computed by the nlpsf
found at PATH (a checkout of an earlier commit, e.g. ``git archive 75fd217 nlpsf | tar -x -C PATH``),
in a fresh process of its own: the before/after ratio of a change, in the same run. CPU seconds
(``time.process_time``), BLAS on one thread. Usage:

    OMP_NUM_THREADS=1 python benchmarks/bench_field_tables.py [--band H158 --band W146] [--before PATH] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

CHILD = r"""
import json, sys, time
from nlpsf import tablebuild
scene, band, sca = sys.argv[1], sys.argv[2], int(sys.argv[3])
make = tablebuild.TableSettings.roman if scene == "roman" else tablebuild.TableSettings
node = (3, 1, 1) if scene == "roman" else None
tablebuild.compute_table(band, sca, make(realizations=2, faint_limit=15.0), node=node)  # warm-up
start = time.process_time()
table = tablebuild.compute_table(band, sca, make(), node=node)
print(json.dumps({"cpu_s": time.process_time() - start, "rows": len(table)}))
"""


def table_cost(scene: str, band: str, sca: int, code: str | None = None) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1")
    if code:
        env["PYTHONPATH"] = code
    out = subprocess.run(
        [sys.executable, "-c", CHILD, scene, band, str(sca)], env=env, capture_output=True, text=True, check=True, cwd=code
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--band", action="append", default=None)
    parser.add_argument("--sca", type=int, default=18)
    parser.add_argument("--before", default=None, help="path holding an earlier nlpsf/ to time the same Roman table with")
    parser.add_argument("--json", default=None)
    args = parser.parse_args()
    results = {}
    for band in args.band or ["H158", "W146"]:
        paper = table_cost("paper", band, args.sca)
        roman = table_cost("roman", band, args.sca)
        row = {"paper": paper, "roman": roman, "roman_over_paper": roman["cpu_s"] / paper["cpu_s"]}
        line = (
            f"{band} SCA {args.sca}: paper {paper['cpu_s']:.2f} CPU-s ({paper['rows']} rows), Roman {roman['cpu_s']:.2f} "
            f"CPU-s ({roman['rows']} rows): x {row['roman_over_paper']:.1f} the paper's"
        )
        if args.before:
            before = table_cost("roman", band, args.sca, args.before)
            row["roman_before"] = before
            row["speed_up"] = before["cpu_s"] / roman["cpu_s"]
            line += f"; before {before['cpu_s']:.2f} CPU-s: speed-up x {row['speed_up']:.1f}"
        print(line, flush=True)
        results[band] = row
    if args.json:
        with open(args.json, "w") as handle:
            json.dump(results, handle, indent=1)


if __name__ == "__main__":
    main()
