"""``nlpsf impact``: what each scene effect changes in the slopes at one point (linear response)."""

from __future__ import annotations

import argparse

from .. import defaults
from . import progress_printer
from .options import add_band_sca, add_scene_options, beta_from_coefficients, print_json, scene_from


def configure(parser: argparse.ArgumentParser) -> None:
    add_band_sca(parser)
    parser.add_argument("--magnitude", type=float, default=defaults.MAGNITUDE, help="AB magnitude of the star")
    parser.add_argument("--metric", choices=defaults.METRICS, default="size", help="the request's metric (size, e1, e2, e)")
    parser.add_argument("--mode", choices=defaults.MODES, default="bias", help="bias or scatter slopes")
    parser.add_argument("--beta0", type=float, default=None, help=f"beta0 [1/e-], paper convention (default {defaults.BETA0:g})")
    parser.add_argument("--exptime", type=float, default=defaults.EXPTIME_S, help="exposure time [s]")
    parser.add_argument("--realizations", type=int, default=defaults.REALIZATIONS, help="centroid realizations per run")
    parser.add_argument("--seed", type=int, default=defaults.SEED, help="random seed (both runs of an effect share it)")
    add_scene_options(parser)
    parser.add_argument(
        "--pupil-scale",
        choices=defaults.PUPIL_SCALE_RULES,
        default=None,
        help=f"pupil mask scale rule of every run (see nlpsf/data/SOURCES.md; default {defaults.PUPIL_SCALE})",
    )
    parser.add_argument("--json", action="store_true", help="print the JSON object other tools read")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from nlpsf.solve.impact import impact, markdown

    model, b2 = scene_from(args)
    report = impact(
        args.band,
        args.sca,
        args.magnitude,
        scene=model,
        metric=args.metric,
        mode=args.mode,
        beta0=beta_from_coefficients(args.beta0, b2, defaults.BETA0),
        exptime=args.exptime,
        realizations=args.realizations,
        seed=args.seed,
        pupil_scale=args.pupil_scale,
        progress=progress_printer(not args.quiet and not args.json),
    )
    if args.json:
        print_json(report)
    else:
        print(markdown(report))
    return 0
