"""``nlpsf slopes``: bias and scatter slopes against magnitude (the paper's Figs. 3 and 5)."""

from __future__ import annotations

import argparse

from .. import defaults
from . import progress_printer
from .options import (
    add_simulation_options,
    beta_from_coefficients,
    config_from,
    print_json,
    scene_from,
    with_default_conditions,
    with_error,
)


def configure(parser: argparse.ArgumentParser) -> None:
    add_simulation_options(parser, scene_base="roman")
    parser.add_argument(
        "--magnitude",
        type=float,
        action="append",
        help=f"AB magnitude; repeat (default {' '.join(f'{m:g}' for m in defaults.PAPER_MAGNITUDES)}, the paper's)",
    )
    parser.add_argument(
        "--beta0",
        type=float,
        default=None,
        help=f"beta at which slopes are taken [1/e-], in --beta-convention (default {defaults.BETA0:g})",
    )
    parser.add_argument(
        "--sigma-beta",
        type=float,
        default=None,
        help=f"per-pixel beta scatter of the Monte Carlo scatter slope [1/e-] (default {defaults.SIGMA_BETA_FRACTION:g} |beta0|)",
    )
    from nlpsf.sim.experiment.config import LINEARISE_STATES

    parser.add_argument(
        "--linearise-at",
        choices=LINEARISE_STATES,
        default=None,
        help="where the slope is taken (default corrected for the Roman default, beta0 for --scene paper): "
        "beta0 (the uncorrected detector, the paper's) or corrected (after the pipeline's "
        "linearity correction, saturation flagged at the raw beta0; --residual-nl says how the error acts there)",
    )
    from nlpsf.sim.experiment.correction import RESIDUAL_MODELS

    parser.add_argument(
        "--residual-nl",
        choices=RESIDUAL_MODELS,
        default=None,
        help="how a calibration error acts in the corrected state: per_resultant_correction (the default: the "
        "linearity correction evaluated on every resultant of the measured, IPC-coupled signal, as romancal's linearity "
        "step applies it) or per_read_beta (the earlier model: a residual beta on every read before IPC)",
    )


def _state(args: argparse.Namespace) -> str:
    from nlpsf.request import presets as roman_default

    from .options import simulation_preset

    return roman_default.policy(simulation_preset(args)).linearise_at


def run(args: argparse.Namespace) -> int:
    from nlpsf.sim import experiment

    config = config_from(args, roman_default_applies=True)
    args.beta0 = beta_from_coefficients(args.beta0, scene_from(args)[1], defaults.BETA0)
    magnitudes = args.magnitude or list(defaults.PAPER_MAGNITUDES)
    results = experiment.slopes(
        config,
        magnitudes,
        beta0=args.beta0,
        sigma_beta=args.sigma_beta,
        beta_convention=args.beta_convention,
        linearise_at=args.linearise_at or _state(args),
        residual_nl=args.residual_nl,
        progress=progress_printer(not args.quiet and not args.json),
    )
    if args.json:
        print_json(with_default_conditions([r.to_dict() for r in results], args))
        return 0
    print(
        f"{config.band} SCA {config.sca}, beta0={args.beta0:g} /e- ({args.beta_convention} convention), {config.exptime_s:g} s, "
        f"fidelity {config.fidelity}"
    )
    if not config.scene.no_effects:
        print(f"scene: {config.scene.describe()}")
    if config.ramp is not None:
        print(f"up the ramp: {config.ramp.describe()}")
    print("bias slope d(metric)/dbeta and scatter slope sigma(metric)/sigma_beta, both per (1/e-), ± standard error")
    print(
        f"{'mag AB':>6} {'size bias':>18} {'e1 bias':>18} {'e2 bias':>18} {'size scatter':>18} {'e1 scatter':>18} "
        f"{'e2 scatter':>18}"
    )
    for r in results:
        b, s = r.bias, r.scatter
        cells = [with_error(b[n].mean, b[n].stderr) for n in ("dR_over_R", "de1", "de2")]
        cells += [with_error(s[n]["value"], s[n]["uncertainty"]) for n in ("dR_over_R", "de1", "de2")]
        print(f"{r.magnitude:6.2f} " + " ".join(f"{c:>18}" for c in cells))
        for flag in r.flags:
            print(f"       ! {flag}")
    return 0
