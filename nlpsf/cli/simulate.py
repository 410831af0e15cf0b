"""``nlpsf simulate``: NL-induced change of PSF size and ellipticity for magnitudes x betas."""

from __future__ import annotations

import argparse
import sys

from .. import defaults
from . import progress_printer
from .options import (
    add_simulation_options,
    beta_from_coefficients,
    config_from,
    number,
    print_json,
    scene_from,
    with_default_conditions,
    with_error,
)


def configure(parser: argparse.ArgumentParser) -> None:
    add_simulation_options(parser, scene_base="roman")
    parser.add_argument(
        "--magnitude", type=float, action="append", help=f"AB magnitude; repeat for several (default {defaults.MAGNITUDE})"
    )
    parser.add_argument(
        "--beta",
        type=float,
        action="append",
        help=f"NL coefficient [1/e-] in --beta-convention; repeat for several (default {defaults.BETA0:g})",
    )
    parser.add_argument(
        "--sigma-beta",
        type=float,
        default=0.0,
        help="per-pixel beta scatter [1/e-]; > 0 draws --realizations beta maps at a fixed centroid",
    )


def run(args: argparse.Namespace) -> int:
    from nlpsf.sim import detector, experiment

    config = config_from(args, roman_default_applies=True)
    magnitudes = args.magnitude or [defaults.MAGNITUDE]
    betas = args.beta or [detector.to_paper_beta(defaults.BETA0, args.beta_convention)]
    b2 = scene_from(args)[1]
    if b2 is not None:
        betas = [beta_from_coefficients(b, b2, b2) for b in args.beta] if args.beta else [b2]
    results = experiment.simulate(
        config,
        magnitudes,
        betas,
        sigma_beta=args.sigma_beta,
        beta_convention=args.beta_convention,
        progress=progress_printer(not args.quiet and not args.json and len(magnitudes) * len(betas) > 1),
    )
    all_failed = all(r.dR_over_R.count == 0 for r in results)
    if args.json:
        payload = with_default_conditions([r.to_dict() for r in results], args)
        print_json(payload[0] if len(payload) == 1 else payload)
    else:
        _print_table(config, results, args.sigma_beta)
    if all_failed:
        print("nlpsf simulate: failed: the adaptive moments failed in every realization (see the flags)", file=sys.stderr)
        return 1
    return 0


def _print_table(config, results, sigma_beta: float) -> None:
    first = results[0]
    print(
        f"{config.band} SCA {config.sca}, {config.exptime_s:g} s, N={config.oversampling}, {config.stamp}x{config.stamp} "
        f"fine pixels, {config.realizations} {'beta maps' if sigma_beta > 0 else 'centroids'}, seed {config.seed}, "
        f"fidelity {config.fidelity}; {first.to_dict()['nl_model']}"
    )
    if not config.scene.no_effects:
        print(f"scene: {config.scene.describe()}")
    if config.ramp is not None:
        print(f"up the ramp: {config.ramp.describe()}")
    scatter = sigma_beta > 0
    head = f"{'mag AB':>6} {'beta 1/e-':>10} {'flux e-':>9} {'peak e-':>9} {'dR/R':>22} {'de1':>22} {'de2':>22}"
    if scatter:
        head += f" {'sd dR/R':>9} {'sd de1':>9} {'sd de2':>9}"
    print(head)
    for r in results:
        line = (
            f"{r.magnitude:6.2f} {r.beta:10.3g} {r.flux_electrons:9.4g} {r.peak_electrons:9.4g} "
            f"{with_error(r.dR_over_R.mean, r.dR_over_R.stderr):>22} {with_error(r.de1.mean, r.de1.stderr):>22} "
            f"{with_error(r.de2.mean, r.de2.stderr):>22}"
        )
        if scatter:
            line += f" {number(r.dR_over_R.std, 3):>9} {number(r.de1.std, 3):>9} {number(r.de2.std, 3):>9}"
        print(line)
        for flag in r.flags:
            print(f"       ! {flag}")
    print(
        "dR/R, de1, de2: mean over realizations ± its standard error"
        + ("; sd: their spread (standard deviation) over the beta maps" if scatter else "")
    )
