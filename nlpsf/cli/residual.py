"""``nlpsf residual``: what a calibration residual does to a star's PSF, the scale a residual shape may have,
and the envelope eps(Q) (docs/calibration.md)."""

from __future__ import annotations

import argparse

from .options import print_json


def configure(parser: argparse.ArgumentParser) -> None:
    from .kernel import configure as kernel_options

    kernel_options(parser)
    given = parser.add_argument_group("the residual (one of)")
    given.add_argument("--residual", metavar="FILE.ecsv", help="a residual curve: columns charge_e, residual_e [e-]")
    given.add_argument("--polynomial", metavar="A0,A1,...", help="r(Q) = sum_k a_k Q^k [e-], Q in e-")
    given.add_argument("--linearity", metavar="FILE.asdf", help="a romancal linearity reference file (applied); with --reference")
    given.add_argument("--reference", metavar="FILE.asdf", help="the linearity reference file it is compared with (the truth)")
    given.add_argument("--shape", help="a residual up to its scale: constant_fraction, power_law:ALPHA, quadratic, polynomial:N")
    parser.add_argument("--gain", type=float, default=None, help="e-/DN of the linearity files (default romanisim's 2)")
    parser.add_argument("--scale", type=float, help="the shape's scale (two of --scale, --tolerance, --magnitude)")
    parser.add_argument("--envelope", metavar="BRIGHT,FAINT", help="with --shape and --tolerance: eps(Q) over these magnitudes")


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
        out = _files(args, request, scene, response, residuals)
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


def _files(args, request, scene, response, residuals) -> dict:
    import numpy as np

    from ..calibration.kernel import summarise

    position = request.scene.position if request.scene is not None and request.scene.position else (2044.5, 2044.5)
    window = residuals.star_window(position, scene.stamps.shape[-1], scene.config.oversampling)
    applied = residuals.read_linearity(args.linearity, window)
    reference = residuals.read_linearity(args.reference, window)
    if applied.coeffs.shape[0] != reference.coeffs.shape[0]:
        n = max(applied.coeffs.shape[0], reference.coeffs.shape[0])
        applied = residuals.PixelPolynomials(_pad(applied.coeffs, n), applied.row0, applied.col0, applied.source)
        reference = residuals.PixelPolynomials(_pad(reference.coeffs, n), reference.row0, reference.col0, reference.source)
    gain = residuals.DEFAULT_GAIN if args.gain is None else args.gain
    per_pixel, common = residuals.file_residual(response, position, applied, reference, gain)
    total = _per_realization(response, per_pixel)
    bias = _per_realization(response, common)
    out = {
        "magnitude": response.magnitude,
        "bias": {k: {"value": v, "uncertainty": e} for k, (v, e) in summarise(bias).items()},
        "total": {k: {"value": v, "uncertainty": e} for k, (v, e) in summarise(total).items()},
        "scatter": {
            name: {"value": float(np.std(total[:, k] - bias[:, k], ddof=1))} for k, name in enumerate(("size", "e1", "e2"))
        },
        "conditions": {
            **response.conditions,
            "residual": f"linearity {applied.source} less reference {reference.source}, gain {gain:g} e-/DN",
            "gain_e_per_dn": gain,
            "gain_source": "given" if args.gain is not None else "romanisim 0.15.0 reference gain (no per-SCA gain is published)",
            "window_science_pixels": {"rows": [window[0], window[1]], "columns": [window[2], window[3]]},
        },
        "flags": [str(f) for f in response.flags],
    }
    return out


def _pad(coeffs, n):
    import numpy as np

    out = np.zeros((n, *coeffs.shape[1:]))
    out[: coeffs.shape[0]] = coeffs
    return out


def _per_realization(response, values):
    import numpy as np

    out = np.zeros((response.count, 3))
    for k in range(3):
        out[:, k] = np.bincount(response.owner, weights=response.weights[:, k] * values, minlength=response.count)
    return out


def _print_envelope(out: dict) -> None:
    print(f"envelope eps(Q) for {out['shape']}, {out['metric']} within {out['tolerance']:g} over m = {out['magnitudes']}")
    print(f"  scale {out['scale']:.6g} (set by m = {out['worst_magnitude']:.2f})")
    for q, e in list(zip(out["charge_e"], out["epsilon_e"], strict=True))[:: max(1, len(out["charge_e"]) // 20)]:
        print(f"  Q = {q:10.4g} e-   eps = {e:.4g} e-")
