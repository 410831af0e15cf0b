"""``nlpsf sweep``: a grid of simulations (bands x SCAs x magnitudes x betas x sigma_betas), locally or on dask."""

from __future__ import annotations

import argparse
import sys
import time

from .. import defaults
from . import progress_printer
from .options import add_simulation_options, config_from, print_json


def configure(parser: argparse.ArgumentParser) -> None:
    add_simulation_options(parser, band_sca=False)
    parser.add_argument("--band", action="append", help=f"Roman band; repeat for several (default {defaults.BAND})")
    parser.add_argument("--sca", action="append", type=int, help=f"detector 1-{defaults.N_SCA}; repeat (default {defaults.SCA})")
    parser.add_argument("--magnitude", type=float, action="append", help="AB magnitude; repeat (default the paper's five)")
    parser.add_argument(
        "--beta",
        type=float,
        action="append",
        help=f"NL coefficient [1/e-] in --beta-convention; repeat (default {defaults.BETA0:g})",
    )
    parser.add_argument(
        "--sigma-beta", type=float, action="append", help="per-pixel beta scatter [1/e-]; repeat (default 0: no scatter)"
    )
    parser.add_argument(
        "--output",
        default="build/sweep",
        help="folder for the per-(band, SCA) results; a re-run skips the cells already there",
    )
    parser.add_argument("--to", default=None, metavar="FILE", help="also write the whole table (.ecsv, .csv, .fits, ...)")
    parser.add_argument(
        "--workers", type=int, default=1, help="local worker processes (or LocalCluster workers with --dask local)"
    )
    parser.add_argument(
        "--dask", default=None, metavar="ADDRESS", help="run on a dask.distributed scheduler ('local' starts one)"
    )
    parser.add_argument("--scheduler-file", default=None, help="connect to the dask scheduler described in this file")
    parser.add_argument(
        "--retries", type=int, default=2, help="re-runs of a cell that raised (a lost worker is dask's own retry)"
    )


def run(args: argparse.Namespace) -> int:
    from nlpsf.sim import detector, sweep

    bands = args.band or [defaults.BAND]
    scas = args.sca or [defaults.SCA]
    args.band, args.sca = bands[0], scas[0]  # the shared settings; each cell sets its own band and SCA
    grid = sweep.SweepGrid(
        bands=tuple(bands),
        scas=tuple(scas),
        magnitudes=tuple(args.magnitude or defaults.PAPER_MAGNITUDES),
        betas=tuple(args.beta or [detector.to_paper_beta(defaults.BETA0, args.beta_convention)]),
        sigma_betas=tuple(args.sigma_beta or [0.0]),
        beta_convention=args.beta_convention,
        settings=config_from(args),
    )
    start = time.perf_counter()
    table = sweep.sweep(
        grid,
        args.output,
        workers=args.workers,
        dask_address=args.dask,
        scheduler_file=args.scheduler_file,
        retries=args.retries,
        progress=progress_printer(not args.quiet),
    )
    print(
        f"{len(table)} rows from {len(grid.cells())} cells in {args.output} ({time.perf_counter() - start:.1f} s)",
        file=sys.stderr,
    )
    if args.to:
        table.write(args.to, overwrite=True)
        print(f"written to {args.to}", file=sys.stderr)
    if args.json:
        print_json([{k: _plain(row[k]) for k in table.colnames} for row in table])
    elif not args.to:
        shown = table[
            "band", "sca", "magnitude", "beta", "sigma_beta", "dR_over_R", "de1", "de2", "dR_over_R_std", "failed_realizations"
        ]
        shown.pprint_all()
    return 0


def _plain(value):
    item = value.item() if hasattr(value, "item") else value
    return None if isinstance(item, float) and item != item else item
