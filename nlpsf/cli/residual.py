"""``nlpsf residual``: what a calibration residual does to a star's PSF, the scale a residual shape may have,
and the envelope eps(Q) (docs/calibration.md)."""

from __future__ import annotations

import argparse

from .. import defaults
from .options import print_json


def configure(parser: argparse.ArgumentParser) -> None:
    from .solve import add_star_options

    add_star_options(parser, over_field=False)  # the star, as kernel's; kernel's --output is not residual's
    given = parser.add_argument_group("the residual (one of)")
    given.add_argument("--residual", metavar="FILE.ecsv", help="a residual curve: columns charge_e, residual_e [e-]")
    given.add_argument("--polynomial", metavar="A0,A1,...", help="r(Q) = sum_k a_k Q^k [e-], Q in e-")
    given.add_argument("--linearity", metavar="FILE.asdf", help="a romancal linearity reference file (applied); with --reference")
    given.add_argument("--reference", metavar="FILE.asdf", help="the linearity reference file it is compared with (the truth)")
    given.add_argument("--shape", help="a residual up to its scale: constant_fraction, power_law:ALPHA, quadratic, polynomial:N")
    shaped = parser.add_argument_group("a residual shape's scale (with --shape)")
    shaped.add_argument("--scale", type=float, help="the shape's scale (two of --scale, --tolerance, --magnitude)")
    shaped.add_argument("--tolerance", type=float, help="the allowed PSF error: dR/R, |de1|, |de2| or |de|")
    shaped.add_argument("--metric", choices=defaults.METRICS, default="size", help="size (dR/R), e1, e2 or e (|de|)")
    shaped.add_argument("--envelope", metavar="BRIGHT,FAINT", help="with --tolerance: eps(Q) over these magnitudes")
    parser.add_argument("--gain", type=float, default=None, help="e-/DN of the linearity files (default romanisim's 2)")


def run(args: argparse.Namespace) -> int:
    from ..calibration import requirement, residuals, star_response
    from ..checks import InputError
    from .kernel import request_from

    metric = args.metric
    if args.shape:
        description, shape = residuals.family(args.shape)
        request = request_from(args, magnitude_needed=False)
        scene = requirement.scene_for(request)
        if args.envelope:
            bright, faint = (float(v) for v in args.envelope.split(","))
            if args.tolerance is None:
                raise InputError("tolerance", "an envelope needs the tolerance")
            out = requirement.envelope(scene, metric, shape, description, request.beta0, args.tolerance, (bright, faint))
            print_json(out) if args.json else _print_envelope(out)
            return 0
        answer = requirement.solve_scale(
            scene, metric, shape, description, request.beta0, args.scale, args.tolerance, args.magnitude
        )
        if args.json:
            print_json(answer.to_dict())
        else:
            print(f"{request.band} SCA {request.sca}, {metric}, residual {description}")
            for name in ("scale", "tolerance", "magnitude"):
                mark = "  <- solved" if name == answer.solved_for else ""
                print(f"  {name:10s} {getattr(answer, name):.6g}{mark}")
            print(f"  response per unit scale {answer.response:.6g} ± {answer.response_error:.2g}")
        return 0
    request = request_from(args)
    scene = requirement.scene_for(request)
    response = star_response(scene, request.magnitude, request.beta0)
    if args.linearity or args.reference:
        if not (args.linearity and args.reference):
            raise InputError("linearity", "give both --linearity FILE and --reference FILE")
        out = _files(args, response, residuals)
    else:
        if args.residual and args.polynomial:
            raise InputError("residual", "give one residual: --residual FILE or --polynomial")
        if args.residual:
            residual, description = residuals.read_curve(args.residual), f"curve {args.residual}"
        elif args.polynomial:
            coefficients = [float(v) for v in args.polynomial.split(",")]
            residual, description = residuals.from_polynomial(coefficients), f"polynomial {coefficients}"
        else:
            raise InputError("residual", "give a residual: --residual, --polynomial, --linearity with --reference, or --shape")
        out = requirement.effect(response, residual, description).to_dict()
    if args.json:
        print_json(out)
        return 0
    print(f"{request.band} SCA {request.sca}, m = {request.magnitude:g}: {out['conditions']['residual']}")
    for name, value in out["bias"].items():
        print(f"  bias  {name:4s} {value['value']:.6g} ± {value['uncertainty']:.2g}")
    for name, value in out.get("scatter", {}).items():
        print(f"  scatter {name:4s} {value['value']:.6g} (pixel-to-pixel part, rms over centroids)")
    return 0


def _files(args, response, residuals) -> dict:
    # Only the pixels around the star are read from disk (memory-mapped): those its measurement reads, and
    # the star-free pixels of its stamp, which the sky estimate reads.
    window = residuals.star_window(response.star_position, response.stamp, response.oversampling)
    applied = residuals.read_linearity(args.linearity, window)
    reference = residuals.read_linearity(args.reference, window)
    return residuals.pixel_effect(response, applied, reference, args.gain)


def _print_envelope(out: dict) -> None:
    print(f"envelope eps(Q) for {out['shape']}, {out['metric']} within {out['tolerance']:g} over m = {out['magnitudes']}")
    print(f"  scale {out['scale']:.6g} (set by m = {out['worst_magnitude']:.2f})")
    for q, e in list(zip(out["charge_e"], out["epsilon_e"], strict=True))[:: max(1, len(out["charge_e"]) // 20)]:
        print(f"  Q = {q:10.4g} e-   eps = {e:.4g} e-")
