"""The solved quantity and its uncertainty, from the slopes at the request's conditions: the
brightest usable star (a magnitude scan against the saturation limits), or the tolerance or the
precision at a given magnitude; and the shear budget an answer implies. ``solver.answer`` wraps them
in the answer; ``sca_nodes`` repeats their arithmetic for every node of an SCA at once."""

from __future__ import annotations

import math
from dataclasses import dataclass

from nlpsf.flags import FlagCode, make
from nlpsf.request import shear

from . import model_part
from .magnitude_scan import scan_magnitude
from .solution import Uncertainty
from .validity import (
    _between_limits_flag,
    _binding,
    _magnitude_flags,
    _ramp_magnitude_flags,
    refuse_saturation_past_tables,
)


@dataclass
class Answer:
    """The solved triple, its slope and uncertainty, before the conditions are attached."""

    precision: float | None
    tolerance: float | None
    magnitude: float | None
    slope: float | None
    slope_error: float | None
    parts: Uncertainty
    model: dict | None
    brightest: float | None = None
    binding: str | None = None
    m_nl: float | None = None
    #: d ln|c| / dm at a magnitude answer (its uncertainty and conservative answer are carried by it).
    log_derivative: float | None = None


def answer_magnitude(request, slopes, limits, model_info: dict, systematic, flags: list, crossing=None) -> Answer:
    """Solve for the brightest usable star: the NL limit (a magnitude scan) against saturation.
    ``crossing``: what is known of the scan already (``magnitude_scan.NodeScan``)."""
    averaging = 1.0 / math.sqrt(request.stars)  # scatter: the PSF model averages `stars` independent draws
    precision, tolerance, beta0 = request.precision, request.target_tolerance, request.beta0
    field = "tolerance" if request.budget is None else f"shear_{request.budget.kind}"
    scan = scan_magnitude(slopes, precision * beta0 * averaging, tolerance, limits.saturation, field, crossing)
    flags += scan.flags
    m_nl, slope, slope_err, log_derivative = scan.magnitude, scan.slope, scan.slope_error, scan.log_derivative
    magnitude, binding = _binding(m_nl, limits.saturation, flags)
    if request.ramp is not None and magnitude < limits.final_frame:
        flags.append(_between_limits_flag(magnitude, limits.saturation, limits.final_frame))
    if binding == "nonlinearity" and log_derivative:
        model_info = model_part.model_at(model_info, slopes, m_nl)
        effects, pupil = (model_info[k] / abs(log_derivative) for k in model_part.MODEL_PARTS)
        parts = Uncertainty(
            statistical=(slope_err / abs(slope)) / abs(log_derivative),
            fidelity=None if systematic is None else systematic / abs(log_derivative),
            optical_model=model_part.optical_model_relative(slopes, m_nl, model_info=model_info) / abs(log_derivative),
            effects=effects,
            pupil_scale=pupil,
        )
    else:
        # Saturation sets the answer: it does not depend on the slope. Report the NL error there.
        parts = Uncertainty(0.0, 0.0, 0.0, 0.0, 0.0)
        slope, slope_err, region = slopes.at(limits.saturation)  # first: the model part reads the slopes there
        if region < 0 and request.ramp is None:
            refuse_saturation_past_tables(slopes, limits.saturation, beta0)
        model_info = model_part.model_at(model_info, slopes, limits.saturation)
        error = abs(slope) * precision * beta0 * averaging
        flags.append(
            make(FlagCode.ERROR_AT_SATURATION, metric=request.metric, mode=request.mode, error=error, tolerance=tolerance)
        )
    return Answer(precision, tolerance, magnitude, slope, slope_err, parts, model_info, magnitude, binding, m_nl, log_derivative)


def answer_at_magnitude(request, slopes, limits, model_info: dict, systematic, flags: list) -> Answer:
    """Solve for the tolerance or the precision at a given magnitude."""
    magnitude, beta0 = request.magnitude, request.beta0
    precision, tolerance = request.precision, request.target_tolerance
    if request.ramp is not None:
        flags += _ramp_magnitude_flags(magnitude, limits.saturation, limits.final_frame)  # refuses before simulating
    slope, slope_err, region = slopes.at(magnitude)
    if request.ramp is None:
        flags += _magnitude_flags(slopes, magnitude, region, limits.saturation, beta0)
    elif region > 0 and slopes.grid is not None:  # fainter than the field grid: its flux law (slope_source)
        faintest = slopes.grid.magnitude_range(request.band, request.sca)[1]
        flags.append(make(FlagCode.EXTRAPOLATED_FAINT, magnitude=magnitude, faintest=faintest))
    averaging = 1.0 / math.sqrt(request.stars)
    c, c_err = abs(slope) * averaging, slope_err * averaging
    model_info = model_part.model_at(model_info, slopes, magnitude) if region >= 0 else None
    # After model_at: the Roman default's parts hold the optical model's vintage, not counted twice.
    optical = model_part.optical_model_relative(slopes, magnitude, model_info=model_info) if region >= 0 else None
    effects, pupil = (None, None) if model_info is None else (model_info[k] for k in model_part.MODEL_PARTS)
    if request.solved_for == "tolerance":
        tolerance = c * precision * beta0
        statistical, scale = c_err * precision * beta0, tolerance
    elif c <= max(c_err, 1e-300):
        flags.append(
            make(FlagCode.SLOPE_CONSISTENT_WITH_ZERO, metric=request.metric, magnitude=magnitude, slope=slope, error=c_err)
        )
        return Answer(math.inf, tolerance, magnitude, slope, slope_err, Uncertainty.none(), model_info)
    else:
        precision = tolerance / (c * beta0)
        statistical, scale = precision * c_err / c, precision
    parts = Uncertainty(
        statistical=statistical,
        fidelity=None if systematic is None else scale * systematic,
        optical_model=None if optical is None else scale * optical,
        effects=None if effects is None else scale * effects,
        pupil_scale=None if effects is None else scale * pupil,
    )
    return Answer(precision, tolerance, magnitude, slope, slope_err, parts, model_info)


def shear_answer(metric: str, budget, ratio, tolerance: float, tolerance_uncertainty: float | None) -> dict:
    """The shear budget given, or the bias the tolerance implies for galaxies of this size ratio."""
    if budget is not None:
        return {**budget.to_dict(), "given": budget.kind}
    kind = shear.BUDGET_FOR_METRIC[metric]
    factor = (2.0 if kind == "m" else 1.0 / shear.RESPONSIVITY) / ratio.effective**2
    implied = shear.Budget(kind, tolerance * factor, ratio, tolerance).to_dict()
    implied["given"] = "tolerance"
    implied["uncertainty"] = None if tolerance_uncertainty is None else tolerance_uncertainty * factor
    return implied
