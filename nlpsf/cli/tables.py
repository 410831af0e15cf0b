"""``nlpsf tables``: build the slope tables, show one, export them as ECSV, fit the paper's power laws."""

from __future__ import annotations

import argparse
import json
import sys
import time

from .. import defaults
from . import progress_printer


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="tables_command", required=True, metavar="ACTION", parser_class=type(parser))
    build = sub.add_parser("build", help="compute the slope tables (resumable)", formatter_class=parser.formatter_class)
    build.add_argument("--output", default="build/tables", help="folder for the per-(band, SCA) tables")
    build.add_argument(
        "--merge-to",
        default=None,
        help="also merge into this file (and its .npz companion)",
    )
    build.add_argument(
        "--field",
        action="store_true",
        help="the tables at each SCA's four corner field points (what --over-field reads) instead of the centres",
    )
    build.add_argument(
        "--scene",
        choices=("paper", "roman"),
        default="paper",
        help="paper: the shipped tables' idealised scene; roman: the candidate Roman default (nlpsf.slopes.fieldgrid: "
        "preset roman at the position, roman-typical background, HLWAS ramp with the likelihood fit, official pupil scale)",
    )
    build.add_argument(
        "--grid",
        type=int,
        default=None,
        metavar="N",
        help="tables at the N x N field-grid nodes of each SCA (N = 3, 5, 7, 9; nlpsf.slopes.fieldgrid); "
        "--merge-to then writes one float32 .npz field-grid file",
    )
    build.add_argument("--band", action="append", help="only these bands (repeat); default all")
    build.add_argument("--sca", action="append", type=int, help="only these SCAs (repeat); default all")
    build.add_argument("--workers", type=int, default=1, help="local worker processes")
    build.add_argument("--dask", default=None, metavar="ADDRESS", help="run on a dask.distributed scheduler ('local' starts one)")
    build.add_argument("--scheduler-file", default=None, help="connect to the dask scheduler described in this file")
    build.add_argument("--retries", type=int, default=1, help="re-runs of a table whose computation raised")
    build.add_argument("--realizations", type=int, default=defaults.REALIZATIONS, help="centroid realizations per table")
    build.add_argument(
        "--faint-limit", type=float, default=defaults.TABLE_FAINT_LIMIT, help="faintest magnitude of the grid [AB]"
    )
    build.add_argument("--step", type=float, default=defaults.TABLE_MAGNITUDE_STEP, help="magnitude step of the grid [mag]")
    build.add_argument(
        "--throughput", choices=defaults.THROUGHPUTS, default=defaults.THROUGHPUT, help="effective-area data the tables use"
    )
    build.add_argument(
        "--pupil-scale",
        choices=defaults.PUPIL_SCALE_RULES,
        default=None,
        help=f"pupil mask scale rule the tables use (see nlpsf/data/SOURCES.md); default {defaults.PUPIL_SCALE} "
        "for --scene paper, official for --scene roman",
    )
    build.add_argument("--quiet", action="store_true", help="no progress bar")
    show = sub.add_parser("show", help="print one table", formatter_class=parser.formatter_class)
    show.add_argument("--band", default=defaults.BAND, help=f"Roman band: {', '.join(defaults.BANDS)}")
    show.add_argument("--sca", type=int, default=defaults.SCA, help=f"detector 1-{defaults.N_SCA}")
    show.add_argument("--format", choices=("text", "json", "csv"), default="text", help="output format")
    export = sub.add_parser(
        "export", help="write the shipped tables as ECSV (units and metadata)", formatter_class=parser.formatter_class
    )
    export.add_argument("--output", required=True, metavar="FILE.ecsv", help="the ECSV to write (gzipped if it ends in .gz)")
    export.add_argument("--field", action="store_true", help="the tables at each SCA's four corner field points")
    fits = sub.add_parser("fits", help="power-law fits, the paper's Table 2 form", formatter_class=parser.formatter_class)
    fits.add_argument("--sca", type=int, default=defaults.SCA, help=f"detector 1-{defaults.N_SCA}")
    fits.add_argument("--markdown", action="store_true", help="the side-by-side with the paper's Table 2")
    fits.add_argument("--json", action="store_true", help="print JSON")


def run(args: argparse.Namespace) -> int:
    if args.tables_command == "build":
        return _build(args)
    if args.tables_command == "show":
        return _show(args)
    if args.tables_command == "export":
        return _export(args)
    return _fits(args)


def _export(args) -> int:
    from nlpsf.slopes import tables

    path = tables.export_ecsv(args.output, tables.field_table_path() if args.field else tables.shipped_table_path())
    print(f"written to {path}", file=sys.stderr)
    return 0


def _build(args) -> int:
    from nlpsf.slopes import tablebuild

    from ..checks import check_integer

    check_integer(args.workers, "workers", 1, 256)
    if args.grid is not None:
        from nlpsf.slopes import fieldgrid

        fieldgrid.check_grid(args.grid)
    chosen = {"pupil_scale": args.pupil_scale} if args.pupil_scale else {}
    settings = tablebuild.TableSettings.of_scene(
        args.scene,
        realizations=args.realizations,
        faint_limit=args.faint_limit,
        magnitude_step=args.step,
        throughput=args.throughput,
        **chosen,
    )
    start = time.perf_counter()
    paths = tablebuild.build_tables(
        args.output,
        bands=args.band or defaults.BANDS,
        scas=args.sca or range(1, defaults.N_SCA + 1),
        settings=settings,
        workers=args.workers,
        dask_address=args.dask,
        scheduler_file=args.scheduler_file,
        retries=args.retries,
        progress=progress_printer(not args.quiet),
        field=args.field,
        grid=args.grid,
    )
    print(f"{len(paths)} tables in {args.output} ({time.perf_counter() - start:.1f} s)", file=sys.stderr)
    if args.merge_to and args.grid:
        tablebuild.merge_field_grid(paths, args.merge_to)
        print(f"field grid packed into {args.merge_to}", file=sys.stderr)
    elif args.merge_to:
        tablebuild.merge_tables(paths, args.merge_to)
        print(f"merged into {args.merge_to} (and its .npz companion)", file=sys.stderr)
    return 0


def _show(args) -> int:
    from nlpsf.slopes import tables

    rows = tables.table_rows(args.band, args.sca)
    if args.format == "json":
        print(json.dumps(rows, indent=1))
    elif args.format == "csv":
        import csv

        writer = csv.DictWriter(sys.stdout, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    else:
        settings = tables.load_tables().get(args.band, args.sca).settings
        print(
            f"{rows[0]['band']} SCA {rows[0]['sca']}: bias slopes d(metric)/dbeta and scatter slopes sigma(metric)/sigma_beta "
            f"per (1/e-), at beta0={settings['beta0']:g} /e-, {settings['exptime_s']:g} s"
        )
        print(f"{'mag AB':>6} {'size':>11} {'e1':>10} {'e2':>10} {'size scat':>11} {'e1 scat':>10} {'e2 scat':>10}  saturated")
        for r in rows:
            print(
                f"{r['magnitude']:6.2f} {r['bias_size']:11.5g} {r['bias_e1']:10.4g} {r['bias_e2']:10.4g} "
                f"{r['scatter_size']:11.5g} {r['scatter_e1']:10.4g} {r['scatter_e2']:10.4g}  {'yes' if r['saturated'] else ''}"
            )
    return 0


def _fits(args) -> int:
    from nlpsf.slopes import tables

    if args.markdown:
        print(tables.table2_markdown(sca=args.sca))
        return 0
    fits = tables.powerlaw_fits(scas=[args.sca])
    if args.json:
        print(json.dumps(fits, indent=1))
        return 0
    low, high = tables.PAPER_FIT_RANGE
    print(f"SCA {args.sca}: slope = A 10^(B (m - 20)) over m = {low}-{high} AB")
    for f in fits:
        print(
            f"{f['band']:>5} {f['mode']:>8}  A = {f['A']:9.1f} ± {f['A_err']:.1f}  B = {f['B']:.4f} ± {f['B_err']:.4f}  "
            f"max residual {100 * f['max_relative_residual']:.2f} %"
        )
    return 0
