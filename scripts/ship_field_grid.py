"""Merge the Roman-default field-grid node tables into the one shipped runtime file.

    nice -n 10 nlpsf tables build --scene roman --grid 3 --output build/roman_grid [--band B ...]
    python scripts/ship_field_grid.py build/roman_grid [--to nlpsf/data/tables/roman_field_grid.npz]

    # a denser grid for some (band, SCA)s, put into the shipped file in place of their 3 x 3 entries:
    nice -n 10 nlpsf tables build --scene roman --grid 5 --band W146 --output build/roman_grid5
    python scripts/ship_field_grid.py build/roman_grid5 --grid 5 --into nlpsf/data/tables/roman_field_grid.npz

Every (band, SCA) whose n x n nodes are all built goes in (a build still running ships what has
finished); the file's metadata records the code commit the nodes were built with (``CODE_COMMIT``
in the build folder, else the current one), the date, the CPU time of every node and which
(band, SCA) are covered. With ``--into`` the entries replace those of an existing file
(``fieldgrid.merge_grids``: each keeps its own build's provenance, the others stay bit for bit).

    # a file of an earlier format rewritten in today's (gridfile.FORMAT), nothing rebuilt:
    python scripts/ship_field_grid.py --resave nlpsf/data/tables/roman_field_grid.npz

``--resave`` keeps every slope bit for bit and rounds the errors up to the format's precision; the
file's provenance records the file it was made from (format, size and git blob id, so
``git cat-file blob ID`` gives it back where it was committed: tests/library/test_shipped_field_grid.py
compares against it).
docs/field.md says what the shipped file holds.
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import statistics
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from nlpsf import __version__, defaults
from nlpsf.slopes import fieldgrid, gridfile, tablebuild


def _commit(build: Path) -> str:
    recorded = build / "CODE_COMMIT"
    if recorded.is_file():
        return recorded.read_text().strip()
    return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=False).stdout.strip()


def git_blob_id(path: Path) -> str:
    """The id git gives ``path``'s content (``git hash-object``), computed without git."""
    content = path.read_bytes()
    return hashlib.sha1(b"blob %d\0" % len(content) + content).hexdigest()


def resave(path: Path) -> Path:
    """Rewrite a field-grid file in today's format, recording what it was made from."""
    grid = fieldgrid.FieldGrid.load(path)
    with open(path, "rb") as handle:
        old_format = json.loads(np.load(handle)["meta"].tobytes().decode())["format"]
    provenance = grid.meta.setdefault("provenance", {})
    provenance["converted_from"] = {
        "format": old_format,
        "bytes": path.stat().st_size,
        "git_blob": git_blob_id(path),
        "converted": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }
    return grid.save(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("build", type=Path, nargs="?", help="folder of node tables (nlpsf tables build --grid N --output ...)")
    parser.add_argument("--grid", type=int, default=3, help="the build's grid size N")
    parser.add_argument("--to", type=Path, default=fieldgrid.shipped_grid_path())
    parser.add_argument("--into", type=Path, default=None, help="put the entries into this existing field-grid file instead")
    parser.add_argument("--resave", type=Path, default=None, help="rewrite this field-grid file in today's format instead")
    args = parser.parse_args()
    if args.resave is not None:
        before = args.resave.stat().st_size
        out = resave(args.resave)
        print(f"{out}: {before / 1e6:.2f} MB -> {out.stat().st_size / 1e6:.2f} MB ({gridfile.FORMAT})")
        return
    if args.build is None:
        parser.error("give a build folder or --resave FILE")
    n = fieldgrid.check_grid(args.grid)
    paths = sorted(args.build.glob(f"slopes_*_G{n}_*.ecsv"))
    started = (args.build / "STARTED").read_text().strip() if (args.build / "STARTED").is_file() else None
    provenance = {
        "built_with": f"nlpsf tables build --scene roman --grid {n} (TableSettings.roman())",
        "code_commit": _commit(args.build),
        "code_version": __version__,
        "build_started": started,
        "merged": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "node_tables_found": len(paths),
        "method": "linear response at the corrected state (1e-2 beta0; a ramp's saturation flags at the raw beta0), "
        "mean over 100 centroid draws shared by every node",
        "scene": "the Roman default (nlpsf.request.presets) at each node's position",
    }
    if args.into is None:
        out = tablebuild.merge_field_grid(paths, args.to, provenance=provenance, complete_only=True)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            update = tablebuild.merge_field_grid(paths, Path(tmp) / "update.npz", provenance=provenance, complete_only=True)
            merged = fieldgrid.merge_grids(fieldgrid.FieldGrid.load(args.into), fieldgrid.FieldGrid.load(update))
        out = merged.save(args.into)
    grid = fieldgrid.FieldGrid.load(out)
    covered = grid.coverage()
    cpu = [c for entry in grid.meta["tables"].values() for row in entry["cpu_s"] for c in row]
    full = len(defaults.BANDS) * defaults.N_SCA
    print(f"{out}: {out.stat().st_size / 1e6:.2f} MB, {len(covered)} of {full} (band, SCA), {len(cpu)} node tables")
    print(f"node CPU s: total {sum(cpu):.0f}, median {statistics.median(cpu):.2f}, max {max(cpu):.2f}")
    for band in defaults.BANDS:
        scas = [s for b, s in covered if b == band]
        sizes = sorted({grid.meta["tables"][grid.key(band, s)]["grid"] for s in scas})
        listed = f" ({', '.join(map(str, scas))})" if 0 < len(scas) < defaults.N_SCA else ""
        print(f"  {band}: {len(scas)} SCAs{listed}, grid {' and '.join(f'{g} x {g}' for g in sizes)}")


if __name__ == "__main__":
    main()
