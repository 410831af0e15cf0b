"""``nlpsf solve``: given two of precision, tolerance and magnitude, the third (paper Eq. calib)."""

from __future__ import annotations

import argparse

from .. import defaults
from ..fidelity import LEVELS
from . import progress_printer
from .options import add_exposure, add_scene_options, print_json, ramp_from, scene_from, with_error


def _sca(text: str):
    if text.strip().lower() == "all":
        return "all"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 1-{defaults.N_SCA} or all, got {text!r}") from None


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--band", default=defaults.BAND, help=f"Roman band: {', '.join(defaults.BANDS)}")
    parser.add_argument(
        "--sca", type=_sca, default=defaults.SCA, help=f"detector 1-{defaults.N_SCA} (the paper's is 18); all with --over-field"
    )
    parser.add_argument(
        "--over-field",
        action="store_true",
        help="answer for the worst position over the SCA's field points (all 18 SCAs with --sca all); simulates",
    )
    parser.add_argument("--metric", choices=defaults.METRICS, default="size", help="size (dR/R), e1, e2, or e (|de|)")
    parser.add_argument(
        "--mode", choices=defaults.MODES, default="bias", help="bias: error in the mean beta; scatter: per-pixel spread"
    )
    parser.add_argument("--beta0", type=float, default=defaults.BETA0, help="nominal NL coefficient [1/e-], paper convention")
    add_exposure(parser)
    parser.add_argument("--precision", type=float, help="delta_beta / beta0 (bias) or sigma_beta / beta0 (scatter)")
    parser.add_argument("--tolerance", type=float, help="allowed PSF error: dR/R, |de1|, |de2| or |de|")
    parser.add_argument("--magnitude", type=float, help="AB magnitude of the brightest PSF star")
    parser.add_argument(
        "--shear-m",
        type=float,
        help="multiplicative shear-bias budget |m| (size metric); with --size-ratio, takes the place of --tolerance",
    )
    parser.add_argument(
        "--shear-c",
        type=float,
        help="additive shear-bias budget |c| (e1, e2, e metrics); with --size-ratio, takes the place of --tolerance",
    )
    parser.add_argument(
        "--size-ratio",
        help="R_gal/R_psf, intrinsic galaxy over PSF, R = det(M)^(1/4): a number, 'ratio:weight,...' or @FILE "
        "(lines 'ratio [weight]'); alone it reports the shear bias the tolerance implies",
    )
    parser.add_argument(
        "--stars",
        type=int,
        default=1,
        help="scatter mode: the PSF model averages this many stars/dithers on independent pixels (sigma / sqrt(n))",
    )
    parser.add_argument("--fidelity", choices=LEVELS, default=None, help="how the slope is obtained (default table)")
    parser.add_argument(
        "--accuracy",
        type=float,
        default=None,
        help="relative accuracy wanted: picks the cheapest fidelity whose measured error is below it (instead of --fidelity)",
    )
    parser.add_argument(
        "--throughput",
        choices=defaults.THROUGHPUTS,
        default=None,
        help=f"photometry of the magnitude: default the tables' own ({defaults.THROUGHPUT}); another relabels them",
    )
    add_scene_options(parser)
    parser.add_argument("--json", action="store_true", help="print the JSON object other tools read")


def run(args: argparse.Namespace) -> int:
    from ..solver import solve, solve_over_field

    ramp, exptime = ramp_from(args)
    if args.over_field:
        if ramp is not None:
            from ..checks import InputError

            raise InputError("ramp", "--over-field works on the final frame; give no ramp")
        solution = solve_over_field(
            args.band,
            "all" if args.sca == "all" else [args.sca],
            scene=_scene(args),
            progress=progress_printer(not args.json),
            metric=args.metric,
            mode=args.mode,
            beta0=args.beta0,
            exptime=exptime,
            precision=args.precision,
            tolerance=args.tolerance,
            magnitude=args.magnitude,
            full_well=args.full_well,
            fidelity=args.fidelity,
            accuracy=args.accuracy,
        )
        return _report(solution, args)
    if args.sca == "all":
        from ..checks import InputError

        raise InputError("sca", "--sca all needs --over-field")
    solution = solve(
        args.band,
        args.sca,
        args.metric,
        args.mode,
        args.beta0,
        exptime,
        args.precision,
        args.tolerance,
        args.magnitude,
        args.full_well,
        args.fidelity,
        args.accuracy,
        scene=_scene(args),
        throughput=args.throughput,
        shear_m=args.shear_m,
        shear_c=args.shear_c,
        size_ratio=args.size_ratio,
        stars=args.stars,
        ramp=ramp,
    )
    return _report(solution, args, ramp)


def _report(solution, args: argparse.Namespace, ramp=None) -> int:
    payload = solution.to_dict()
    if args.json:
        print_json(payload)
        return 0
    print(
        f"{solution.band} SCA {solution.sca}, {solution.metric} {solution.mode}, beta0={solution.beta0:g} /e-, "
        f"{solution.exptime:g} s, full well {solution.full_well:.4g} e-, fidelity {solution.fidelity}"
    )
    units = {"precision": "(fraction of beta0)", "tolerance": _tolerance_unit(solution.metric), "magnitude": "AB"}
    for name in ("precision", "tolerance", "magnitude"):
        value = payload[name]
        solved = name == solution.solved_for
        text = with_error(value, payload["uncertainty"]) if solved else ("n/a" if value is None else f"{value:.6g}")
        print(f"  {name:<10} {text} {units[name]}{'  <- solved' if solved else ''}")
    if payload["uncertainty"] is not None:
        parts = ", ".join(
            f"{k} {payload[f'uncertainty_{k}']:.2g}"
            for k in ("statistical", "fidelity", "optical_model", "model")
            if payload[f"uncertainty_{k}"] is not None
        )
        print(f"  uncertainty ({parts})")
    slope_unit = "per (1/e-) of " + ("beta" if solution.mode == "bias" else "sigma_beta")
    print(f"  slope c(m) {with_error(payload['slope'], payload['slope_uncertainty'])} {slope_unit}")
    if ramp is None:
        print(f"  saturation at m={solution.saturation_magnitude:.2f} AB")
    else:
        print(f"  ramp: {ramp.describe()}; slopes from {solution.conditions['ramp_slopes_from']}")
        print(
            f"  saturation at m={solution.saturation_magnitude:.2f} AB (ramp rule: first resultant), "
            f"final frame m={solution.final_frame_saturation_magnitude:.2f} AB"
        )
    print(f"  applies to {solution.applies_to}")
    if solution.shear:
        _print_shear(solution.shear)
    if solution.binding_limit:
        print(f"  brightest usable star m={solution.brightest_usable_magnitude:.2f} AB ({solution.binding_limit} binds)")
    if solution.model:
        included = ", ".join(f"{e['name']} {_percent(e['impact'])}" for e in solution.model["included"]) or "none"
        if "accuracy" in solution.model:
            print(f"  effects modelled (impact above {solution.model['accuracy']:g}): {included}")
        elif solution.model["included"]:
            print(f"  effects simulated by the scene: {', '.join(e['name'] for e in solution.model['included'])}")
        # Measured at the point (accuracy): signed; from the shipped worst cases: a magnitude only.
        signed = "accuracy" in solution.model
        left = ", ".join(f"{e['name']} {_percent(e['impact'], signed)}" for e in solution.model["left_out"])
        print(f"  left out (in the model uncertainty): {left}")
    for flag in solution.flags:
        print(f"  ! {flag}")
    return 0


def _percent(value: float | None, signed: bool = True) -> str:
    if value is None:
        return "n/a"
    return f"{100 * value:+.2g} %" if signed else f"±{100 * value:.2g} %"


def _scene(args: argparse.Namespace):
    """The scene options, or None when none was given (the paper's scene, the tables' answer)."""
    given = any(
        getattr(args, name, None) is not None
        for name in (
            "scene",
            "position",
            "sed",
            "jitter",
            "charge_diffusion",
            "ipc",
            "ipc_order",
            "nl_coefficients",
            "bfe",
            "background",
        )
    )
    if not given:
        return None
    model, b2 = scene_from(args)
    if b2 is not None and b2 != args.beta0:
        from ..checks import InputError

        raise InputError("nl_coefficients", f"b2={b2:g} must equal --beta0 ({args.beta0:g}) in solve")
    return model


def _tolerance_unit(metric: str) -> str:
    return "(fractional size error dR/R)" if metric == "size" else f"(ellipticity error |d{metric}|)"


def _print_shear(budget: dict) -> None:
    kind = "m" if "m" in budget else "c"
    ratio = budget["size_ratio"]
    ratio_text = (
        f"{ratio:g}" if isinstance(ratio, float) else f"{len(ratio['ratios'])} ratios, effective {ratio['effective']:.4g}"
    )
    if budget["given"] == "tolerance":
        value = with_error(budget[kind], budget.get("uncertainty"))
        print(f"  implied shear bias |{kind}| {value} for R_gal/R_psf {ratio_text} ({budget['relation']})")
    else:
        print(f"  shear budget |{kind}| {budget[kind]:.4g}, R_gal/R_psf {ratio_text} -> tolerance {budget['tolerance']:.4g}")
