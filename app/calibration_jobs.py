"""The calibration capability's kinds of job (``job_kinds.KINDS`` holds them; docs/calibration.md):

- ``kernel``: the response kernel K(Q) of a star (POST /calibration/kernel);
- ``residual``: what an inline residual does to the star (POST /calibration/residual);
- ``requirement``: for a residual shape, two of scale, tolerance, magnitude give the third, or the envelope
  eps(Q) over a magnitude range (POST /calibration/requirement).

Each prepares the star's scene and reads it out (a simulation: about a second for the Roman default, many for
a magnitude scan), so each is a job like a simulation: queued, with progress, cancellable at each progress
report, its result stored under the request's hash. Everything a request can get wrong without the simulation
is checked when it is validated (in the web process, at table cost): the star's request as POST /solve reads
it, the residual's shape, the coefficients' shapes and values. What needs the star -- a curve that does not
reach its charge levels, coefficients that do not cover the pixels its measurement reads, a correction that is
not monotonic over its signal range -- fails the job with the field named (a 422 to the submitter). All
physics is in ``nlpsf.calibration``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from nlpsf.checks import InputError, check_magnitude
from nlpsf.serialise import json_safe

from .calibration_models import STAR_FIELDS
from .job_parts import JobKind, solve_body, solve_request

KERNEL_KIND = "kernel"
RESIDUAL_KIND = "residual"
REQUIREMENT_KIND = "requirement"

#: The residual's members, one of which a request gives.
RESIDUAL_MEMBERS = ("curve", "polynomial", "shape", "linearity")
#: A magnitude the star's request is resolved at when the magnitude is what is solved for (the scene and the
#: readout do not depend on it).
PLACEHOLDER_MAGNITUDE = 20.0


def _star_body(fields: dict[str, Any], given: set[str]) -> dict[str, Any]:
    """The star's fields as POST /solve's body (the exposure and ramp fit only when given)."""
    body = {name: fields[name] for name in STAR_FIELDS if name in fields}
    return solve_body(body, given)


def star_request(body: dict[str, Any]):
    """The library's typed request of the star (``SolveRequest``; the triple is the residual's, so the
    request only resolves the star, its scene and its readout, as ``nlpsf kernel`` does)."""
    magnitude = body.get("magnitude")
    values = {**body, "precision": 0.01, "tolerance": None}
    values["magnitude"] = PLACEHOLDER_MAGNITUDE if magnitude is None else check_magnitude(magnitude)
    return solve_request(values)


def _named(field: str, error: InputError) -> InputError:
    """``error`` naming ``field`` (the request's nesting), keeping its reason."""
    return InputError(field, error.reason)


def residual_of(spec: dict[str, Any]) -> tuple[str, Any, str]:
    """(member, residual r(Q) or None for two calibrations' polynomials, description) of a request's residual;
    InputError naming ``residual.<member>``."""
    from nlpsf.calibration import residuals

    given = [name for name in RESIDUAL_MEMBERS if spec.get(name) is not None]
    if len(given) != 1:
        raise InputError("residual", f"give exactly one of {', '.join(RESIDUAL_MEMBERS)} (got {', '.join(given) or 'none'})")
    member = given[0]
    if spec.get("scale") is not None and member != "shape":
        raise InputError("residual.scale", "a scale goes with a shape")
    if member == "linearity":
        applied, reference = polynomials_of(spec["linearity"])
        if applied.coeffs.shape[1:] != reference.coeffs.shape[1:]:
            raise InputError(
                "residual.linearity.reference",
                f"covers {reference.coeffs.shape[1]} x {reference.coeffs.shape[2]} pixels, the applied calibration "
                f"{applied.coeffs.shape[1]} x {applied.coeffs.shape[2]}: give both for the same pixels",
            )
        return member, None, "two calibrations' per-pixel polynomials"
    if member == "shape" and (spec.get("scale") is None or not math.isfinite(spec["scale"])):
        raise InputError("residual.scale", "give the shape's scale (a finite number)")
    try:
        if member == "curve":
            curve = spec["curve"]
            residual = residuals.from_curve(curve["charge_e"], curve["residual_e"], "the curve")
            return member, residual, f"a curve of {len(curve['charge_e'])} points"
        if member == "polynomial":
            coefficients = [float(v) for v in spec["polynomial"]]
            return member, residuals.from_polynomial(coefficients), f"polynomial {coefficients} (r = sum a_k Q^k, e-)"
        description, shape = residuals.family(spec["shape"])
    except InputError as error:
        raise _named(f"residual.{member}", error) from None
    scale = float(spec["scale"])
    return member, (lambda q: scale * shape(q)), f"{description}, s = {scale:g}"


def polynomials_of(linearity: dict[str, Any]):
    """The two calibrations' polynomials of a request's ``linearity`` member (``PixelPolynomials``)."""
    from nlpsf.calibration import residuals

    row, column = linearity["first_row"], linearity["first_column"]
    return tuple(
        residuals.PixelPolynomials.inline(linearity[name], row, column, f"the {name} calibration", f"residual.linearity.{name}")
        for name in ("applied", "reference")
    )


def _validate_kernel(fields: dict[str, Any], given: set[str], settings: Any) -> dict[str, Any]:
    body = _star_body(fields, given)
    request = star_request(body)
    return {"kind": KERNEL_KIND, KERNEL_KIND: {"request": {**body, "band": request.band}}}


def _validate_residual(fields: dict[str, Any], given: set[str], settings: Any) -> dict[str, Any]:
    body = _star_body(fields, given)
    request = star_request(body)
    spec = {k: v for k, v in fields["residual"].items() if v is not None}
    residual_of(spec)
    return {"kind": RESIDUAL_KIND, RESIDUAL_KIND: {"request": {**body, "band": request.band}, "residual": spec}}


def _validate_requirement(fields: dict[str, Any], given: set[str], settings: Any) -> dict[str, Any]:
    from nlpsf.calibration import residuals

    body = _star_body(fields, given)
    request = star_request(body)
    try:
        residuals.family(fields["shape"])
    except InputError as error:
        raise _named("shape", error) from None
    arguments = {name: fields.get(name) for name in ("shape", "scale", "tolerance", "envelope")}
    if fields.get("envelope") is not None:
        if fields.get("tolerance") is None:
            raise InputError("tolerance", "an envelope needs the tolerance")
        others = [name for name in ("scale", "magnitude") if fields.get(name) is not None]
        if others:
            raise InputError(others[0], "an envelope is for a tolerance over a magnitude range: leave scale and magnitude out")
    else:
        named = [name for name in ("scale", "tolerance", "magnitude") if fields.get(name) is not None]
        if len(named) != 2:
            raise InputError("scale", f"give exactly two of scale, tolerance, magnitude (got {', '.join(named) or 'none'})")
        if fields.get("scale") is not None and not (math.isfinite(fields["scale"]) and fields["scale"] != 0):
            raise InputError("scale", "must be a finite, non-zero number")
    return {"kind": REQUIREMENT_KIND, REQUIREMENT_KIND: {"request": {**body, "band": request.band}, **arguments}}


def _stage(progress, fraction: float, message: str) -> None:
    if progress is not None:
        progress(fraction, message)


def _star(arguments: dict[str, Any], progress):
    """(typed request, prepared scene) of a job's star."""
    from nlpsf.calibration import requirement

    request = star_request(arguments["request"])
    _stage(progress, 0.02, "preparing the star's scene: optics at its position, its centroids")
    return request, requirement.scene_for(request)


def _run_kernel(arguments: dict[str, Any], progress) -> dict[str, Any]:
    from nlpsf.calibration import star_response

    request, scene = _star(arguments, progress)
    _stage(progress, 0.7, "reading the star out, correcting every resultant, the moments' response")
    kernel = star_response(scene, request.magnitude, request.beta0).kernel()
    out = {**kernel.to_dict(), "metric": request.metric}
    _stage(progress, 1.0, "done")
    return json_safe(out)


def _run_residual(arguments: dict[str, Any], progress) -> dict[str, Any]:
    from nlpsf.calibration import requirement, residuals, star_response

    spec = arguments["residual"]
    member, residual, description = residual_of(spec)
    request, scene = _star(arguments, progress)
    _stage(progress, 0.7, "reading the star out, correcting every resultant, the moments' response")
    response = star_response(scene, request.magnitude, request.beta0)
    if member == "linearity":
        applied, reference = polynomials_of(spec["linearity"])
        gain = spec["linearity"].get("gain")
        out = residuals.pixel_effect(response, applied, reference, gain, "residual.linearity")
    else:
        try:
            out = requirement.effect(response, residual, description).to_dict()
        except InputError as error:  # a curve that does not reach the star's charge levels
            raise _named(f"residual.{member}", error) from None
    _stage(progress, 1.0, "done")
    return json_safe({**out, "metric": request.metric})


def _run_requirement(arguments: dict[str, Any], progress) -> dict[str, Any]:
    from nlpsf.calibration import requirement, residuals

    request, scene = _star(arguments, progress)
    description, family = residuals.family(arguments["shape"])
    steps = _steps(progress)

    def shape(q):
        values = family(q)
        if not np.all(np.isfinite(values)):  # a power law of negative index at zero charge
            raise InputError("shape", f"{arguments['shape']} is not finite at every charge level the star's resultants reach")
        return values

    if arguments.get("envelope") is not None:
        out = requirement.envelope(
            scene, request.metric, shape, description, request.beta0, arguments["tolerance"], tuple(arguments["envelope"]),
            progress=steps,
        )  # fmt: skip
        out = {**out, "conditions": json_safe(scene.config.conditions())}
    else:
        magnitude = arguments["request"].get("magnitude")
        answer = requirement.solve_scale(
            scene, request.metric, shape, description, request.beta0, arguments.get("scale"), arguments.get("tolerance"),
            magnitude, progress=steps,
        )  # fmt: skip
        out = {**answer.to_dict(), "conditions": json_safe(scene.config.conditions())}
    _stage(progress, 1.0, "done")
    return json_safe(out)


def _steps(progress):
    """A library progress (done, total, message) as the job's fraction after the scene's preparation."""
    if progress is None:
        return None
    return lambda done, total, message: progress(0.05 + 0.95 * min(done / max(total, 1), 1.0), message)


def kinds() -> dict:
    """The calibration kinds, for ``job_kinds.KINDS``."""
    return {
        KERNEL_KIND: JobKind(KERNEL_KIND, _validate_kernel, _run_kernel, lambda _arguments: None),
        RESIDUAL_KIND: JobKind(RESIDUAL_KIND, _validate_residual, _run_residual, lambda _arguments: None),
        REQUIREMENT_KIND: JobKind(REQUIREMENT_KIND, _validate_requirement, _run_requirement, lambda _arguments: None),
    }
