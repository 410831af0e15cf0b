"""Merge the Roman-default field-grid node tables into the one shipped runtime file.

    nice -n 10 nlpsf tables build --scene roman --grid 3 --output build/roman_grid [--band B ...]
    python scripts/ship_field_grid.py build/roman_grid [--to nlpsf/data/tables/roman_field_grid.npz]

Every (band, SCA) whose nine nodes are all built goes in (a build still running ships what has
finished); the file's metadata records the code commit the nodes were built with (``CODE_COMMIT``
in the build folder, else the current one), the date, the CPU time of every node and which
(band, SCA) are covered. docs/field.md says what the shipped file holds.
"""

from __future__ import annotations

import argparse
import datetime
import statistics
import subprocess
from pathlib import Path

from nlpsf import __version__, defaults, fieldgrid, tablebuild


def _commit(build: Path) -> str:
    recorded = build / "CODE_COMMIT"
    if recorded.is_file():
        return recorded.read_text().strip()
    return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=False).stdout.strip()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("build", type=Path, help="folder of node tables (nlpsf tables build --grid 3 --output ...)")
    parser.add_argument("--to", type=Path, default=fieldgrid.shipped_grid_path())
    args = parser.parse_args()
    paths = sorted(args.build.glob("slopes_*_G3_*.ecsv"))
    started = (args.build / "STARTED").read_text().strip() if (args.build / "STARTED").is_file() else None
    provenance = {
        "built_with": "nlpsf tables build --scene roman --grid 3 (TableSettings.roman())",
        "code_commit": _commit(args.build),
        "code_version": __version__,
        "build_started": started,
        "merged": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "node_tables_found": len(paths),
        "method": "linear response at the corrected state (1e-2 beta0; a ramp's saturation flags at the raw beta0), "
        "mean over 100 centroid draws shared by every node",
        "scene": "the Roman default (nlpsf.roman_default) at each node's position",
    }
    out = tablebuild.merge_field_grid(paths, args.to, provenance=provenance, complete_only=True)
    grid = fieldgrid.FieldGrid.load(out)
    covered = grid.coverage()
    cpu = [c for entry in grid.meta["tables"].values() for row in entry["cpu_s"] for c in row]
    full = len(defaults.BANDS) * defaults.N_SCA
    print(f"{out}: {out.stat().st_size / 1e6:.2f} MB, {len(covered)} of {full} (band, SCA), {len(cpu)} node tables")
    print(f"node CPU s: total {sum(cpu):.0f}, median {statistics.median(cpu):.2f}, max {max(cpu):.2f}")
    for band in defaults.BANDS:
        scas = [s for b, s in covered if b == band]
        print(f"  {band}: {len(scas)} SCAs" + (f" ({', '.join(map(str, scas))})" if 0 < len(scas) < defaults.N_SCA else ""))


if __name__ == "__main__":
    main()
