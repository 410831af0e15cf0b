"""``nlpsf kernel``: the response kernel K(Q) of a star to a calibration residual (docs/calibration.md)."""

from __future__ import annotations

import argparse

from .options import print_json


def configure(parser: argparse.ArgumentParser) -> None:
    from .solve import add_star_options

    # The star as the calculator reads it (band, SCA, scene, position, readout, ...), not what it is
    # solved for: a kernel is not a solve, and an option it would ignore is not offered.
    add_star_options(parser, over_field=False)
    parser.add_argument("--output", metavar="FILE.ecsv", help="write the kernel as ECSV (charge_e, one column per metric)")


def request_from(args: argparse.Namespace, magnitude_needed: bool = True):
    """The solve request of the options (its scene, readout and exposure resolved as ``nlpsf solve``'s)."""
    from nlpsf.request.resolve import SolveRequest

    from ..checks import InputError
    from .solve import _REQUEST_OPTIONS, _readout, _scene

    if magnitude_needed and args.magnitude is None:
        raise InputError("magnitude", "give the star's magnitude (--magnitude)")
    scene, preset = _scene(args)
    ramp, exptime = _readout(args, preset)
    values = {name: getattr(args, name) for name in _REQUEST_OPTIONS if hasattr(args, name)}
    # The triple is the residual's here: the request only resolves the star and its readout.
    values.update(precision=0.01, tolerance=None, magnitude=args.magnitude if args.magnitude is not None else 20.0)
    values.update(shear_m=None, shear_c=None)
    return SolveRequest.from_mapping({**values, "exptime": exptime, "scene": scene, "preset": preset, "ramp": ramp})


def run(args: argparse.Namespace) -> int:
    from ..calibration import requirement, star_response

    request = request_from(args)
    scene = requirement.scene_for(request)
    kernel = star_response(scene, request.magnitude, request.beta0).kernel()
    if args.output:
        kernel.table().write(args.output, format="ascii.ecsv", overwrite=True)
    if args.json:
        print_json(kernel.to_dict())
        return 0
    meta = kernel.meta()
    where = f"{request.band} SCA {request.sca}, m = {request.magnitude:g}"
    print(f"{where}: response kernel K(Q) on {kernel.charge_e.size} charge nodes")
    print(f"  full well (saturation threshold) {meta['full_well_e']:.6g} e- of signal = {meta['saturation_e']:.6g} e- of charge")
    for name, slope in meta["quadratic_slopes"].items():
        value, error = slope["value"], slope["uncertainty"]
        print(f"  integral K(Q) (-Q^2) dQ, {name:4s} {value:.6g} ± {error:.2g}  (the Delta_beta slope)")
    low, high = kernel.signal_range("size")
    if high > 0:
        share = round(100 * meta["signal_fraction"])
        print(f"  {share} % of the quadratic residual's size effect comes from charge levels {low:.4g}-{high:.4g} e-")
    if args.output:
        print(f"  written to {args.output}")
    return 0
