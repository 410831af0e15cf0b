"""Request and response models of the calibration endpoints (``calibration_api``; docs/calibration.md).

The star is described by the very fields of POST /solve (``models.SolveRequest``: band, SCA, magnitude,
scene with its position, readout, exposure, beta0, full well, ...), taken from that one definition, so a
kernel or a residual is asked for the star a solve answers for. What is the calibration's: a residual given
inline -- a curve, a polynomial, a shape family with its scale, or the per-pixel correction polynomials of two
calibrations around the star (never a file on the server) -- and, for the requirement, a residual shape and
two of scale, tolerance, magnitude (or an envelope's magnitude range). Ranges are the library's
(``nlpsf.calibration``); these models publish them and refuse the wrong types.
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, create_model

from nlpsf import defaults, roman
from nlpsf.calibration import kernel, residuals

from . import models

_STRICT = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)

#: The fields of POST /solve that describe the star and its readout (their definitions are
#: ``models.SolveRequest``'s; ``solve_api`` answers for the same star).
STAR_FIELDS = (
    "band",
    "sca",
    "metric",
    "beta0",
    "exptime",
    "magnitude",
    "full_well",
    "scene",
    "throughput",
    "pupil_scale",
    "ramp",
    "ma_table",
    "ramp_fit",
    "read_noise",
)

_SOLVE = models.SolveRequest.model_fields

#: The star as POST /solve describes it, magnitude optional (the requirement may solve for it).
StarFields = create_model(
    "StarFields",
    __config__=_STRICT,
    __doc__="The star and its readout, as POST /solve takes them.",
    **{name: (_SOLVE[name].annotation, _SOLVE[name]) for name in STAR_FIELDS},
)

_Magnitude = Field(
    ge=defaults.MAGNITUDE_RANGE[0],
    le=defaults.MAGNITUDE_RANGE[1],
    description="magnitude of the star in AB mag in the band; accepted "
    f"[{defaults.MAGNITUDE_RANGE[0]:g}, {defaults.MAGNITUDE_RANGE[1]:g}]",
)

_EXAMPLE_STAR = {"band": "H158", "sca": 7, "magnitude": 19.0, "scene": {"position": [900.0, 3100.0]}}


class KernelRequest(StarFields):
    """The response kernel K(Q) of a star (``nlpsf kernel``)."""

    model_config = ConfigDict(**_STRICT, json_schema_extra={"examples": [_EXAMPLE_STAR]})

    magnitude: float = _Magnitude


_Number = Annotated[float, Field(allow_inf_nan=False)]
_Coefficient = Annotated[float, Field(allow_inf_nan=False)]
#: At most this many pixels along a side of inline per-pixel polynomials (the body limit binds first).
MAX_BLOCK_PIXELS = 64


class ResidualCurve(BaseModel):
    """r(Q), linear between its points; it must cover every charge level the star's resultants reach."""

    model_config = _STRICT

    charge_e: list[_Number] = Field(
        min_length=2,
        max_length=residuals.MAX_CURVE_POINTS,
        description="charge levels Q in e-, strictly increasing (about 1500 points fit the default 64 kB body limit)",
    )
    residual_e: list[_Number] = Field(
        min_length=2,
        max_length=residuals.MAX_CURVE_POINTS,
        description="residual r(Q) = corrected signal - true charge at each level, in e-",
    )


_Block = list[
    Annotated[
        list[Annotated[list[_Coefficient], Field(min_length=1, max_length=MAX_BLOCK_PIXELS)]],
        Field(min_length=1, max_length=MAX_BLOCK_PIXELS),
    ]
]


class PixelCoefficients(BaseModel):
    """Two calibrations' correction polynomials for the pixels around the star, as romancal's linearity
    reference files hold them (``coeffs``: F_c = sum_k c_k F^k per pixel, F in DN)."""

    model_config = ConfigDict(**_STRICT, json_schema_extra={"examples": [{"applied": "[n][rows][cols]", "first_row": 3096}]})

    applied: _Block = Field(
        min_length=2,
        max_length=residuals.MAX_COEFFICIENTS,
        description="the calibration applied: coefficients [n][rows][cols], c_k in DN^(1-k); they must cover the pixels "
        "the star's measurement reads (the 9 x 9 around its own in H158; a 422 names them); pixels beyond those are "
        "what the sky estimate reads",
    )
    reference: _Block = Field(
        min_length=2,
        max_length=residuals.MAX_COEFFICIENTS,
        description="the calibration it is compared with (the truth), the same pixels, [n][rows][cols]",
    )
    first_row: models.BoundedInt((1, roman.SCA_PIXELS)) = Field(
        description=f"science pixel row (1-{roman.SCA_PIXELS}) of the coefficients' [.][0][.]"
    )
    first_column: models.BoundedInt((1, roman.SCA_PIXELS)) = Field(
        description=f"science pixel column (1-{roman.SCA_PIXELS}) of the coefficients' [.][.][0]"
    )
    gain: float | None = Field(
        None,
        ge=residuals.GAIN_RANGE[0],
        le=residuals.GAIN_RANGE[1],
        description=f"e-/DN; default {residuals.DEFAULT_GAIN:g} ({residuals.DEFAULT_GAIN_SOURCE})",
    )


#: A shape family as ``residuals.family`` reads it (its parameter's range is the library's).
SHAPE_PATTERN = r"^(constant_fraction|quadratic|power_law:-?[0-9.eE+-]{1,16}|polynomial:[0-9]{1,2})$"
SHAPES = (
    "a shape family (no unit): constant_fraction (r = s Q), power_law:ALPHA (r = s (Q / 1e5 e-)^ALPHA), quadratic "
    "(r = -s Q^2, s the solver's Delta_beta), polynomial:N (r = s Q^N)"
)


class ResidualSpec(BaseModel):
    """One residual: a curve, a polynomial, a shape family with its scale, or two calibrations' polynomials."""

    model_config = ConfigDict(
        **_STRICT,
        json_schema_extra={
            "examples": [
                {"polynomial": [0.0, 0.0, -2e-9]},
                {"curve": {"charge_e": [0.0, 1e5], "residual_e": [0.0, 20.0]}},
                {"shape": "power_law:2", "scale": 5.0},
            ]
        },
    )

    curve: ResidualCurve | None = Field(None, description="r(Q) as points (charge_e, residual_e), in e-")
    polynomial: list[_Coefficient] | None = Field(
        None,
        min_length=1,
        max_length=residuals.MAX_COEFFICIENTS,
        description="r(Q) = sum_k a_k Q^k, a_k in e-^(1-k) (Q and r in e-)",
    )
    shape: str | None = Field(None, max_length=32, pattern=SHAPE_PATTERN, description=f"{SHAPES}; with scale")
    scale: float | None = Field(None, description="the shape's scale s (unit: the shape's, so that r is in e-)")
    linearity: PixelCoefficients | None = Field(None, description="two calibrations' per-pixel polynomials around the star")


class ResidualRequest(KernelRequest):
    """What a calibration residual does to a star's PSF (``nlpsf residual``)."""

    model_config = ConfigDict(
        **_STRICT, json_schema_extra={"examples": [{**_EXAMPLE_STAR, "residual": {"polynomial": [0.0, 0.0, -2e-9]}}]}
    )

    residual: ResidualSpec = Field(description="the residual, inline (one of its members)")


class RequirementRequest(StarFields):
    """The requirement in the calibrator's terms: for a residual shape, two of scale, tolerance, magnitude give
    the third; or, with ``envelope`` and the tolerance, the largest residual allowed at each charge level."""

    model_config = ConfigDict(
        **_STRICT,
        json_schema_extra={
            "examples": [
                {"band": "H158", "sca": 7, "magnitude": 19.0, "shape": "power_law:2", "tolerance": 1e-4, "metric": "size"},
                {"band": "H158", "sca": 7, "shape": "power_law:2", "tolerance": 1e-4, "envelope": [18.0, 21.0]},
            ]
        },
    )

    shape: str = Field(max_length=32, pattern=SHAPE_PATTERN, description=SHAPES)
    scale: float | None = Field(None, description="the shape's scale s (unit: the shape's, so that r is in e-)")
    tolerance: float | None = Field(
        None,
        ge=defaults.TOLERANCE_RANGE[0],
        le=defaults.TOLERANCE_RANGE[1],
        description="tolerated error of the metric, dimensionless (dR/R, de1, de2 or |de|)",
    )
    envelope: list[Annotated[float, Field(ge=defaults.MAGNITUDE_RANGE[0], le=defaults.MAGNITUDE_RANGE[1])]] | None = Field(
        None,
        min_length=2,
        max_length=2,
        description="[brightest, faintest] in AB mag: with tolerance, eps(Q) for every star in the range (no scale, no "
        "magnitude)",
    )


# --- responses -------------------------------------------------------------------------------------


def _f(description: str, default: Any = ...) -> Any:
    return Field(default, description=description)


class ValueWithError(BaseModel):
    value: float | None = _f("the value, dimensionless (dR/R, de1, de2, |de|)")
    uncertainty: float | None = _f("its 1-sigma statistical uncertainty (standard error over the centroids), dimensionless", None)


class KernelResponse(BaseModel):
    """K(Q) on charge nodes: the columns of the CLI's ECSV by the same names, and what the kernel is for."""

    model_config = ConfigDict(extra="allow")

    columns: dict[str, list[float | None]] = _f(
        "charge_e in e-; per metric (" + ", ".join(kernel.KERNEL_METRICS) + ") K in 1/e- and <metric>_err its standard "
        "error: Delta metric = integral K(Q) r(Q) dQ (trapezoid rule on the nodes), r in e-"
    )
    fractional_bins: dict[str, list[float | None]] = _f(
        "the kernel in tenths of a decade of charge: edges_e (e-), and per metric the change of the metric were the "
        "residual the whole charge (r = Q) in a bin, with <metric>_err (dimensionless; a fractional residual eps there "
        "changes the metric by eps times it)"
    )
    meta: dict[str, Any] = _f(
        "magnitude (AB mag), flux_electrons (e-), full_well_e (e- of signal), saturation_e (the full well in e- of charge), "
        "realizations (count), quadratic_slopes (integral K (-Q^2) dQ per metric, in e-: the solver's slope), "
        "signal_range_e (e-: where the central signal_fraction of the quadratic residual's effect comes from), units, "
        "flags, flag_codes, conditions"
    )
    ecsv: str | None = _f("where the same kernel downloads as ECSV (a path of this API)", None)


class ResidualResponse(BaseModel):
    model_config = ConfigDict(extra="allow")

    magnitude: float = _f("star magnitude in AB mag")
    bias: dict[str, ValueWithError] = _f(
        "the residual's effect on size (dR/R), e1, e2 and |e| (the modulus of the e1 and e2 means), dimensionless; with "
        "two calibrations' polynomials, the part their average over the measured pixels makes"
    )
    total: dict[str, ValueWithError] | None = _f("two calibrations: each pixel its own polynomials (dimensionless)", None)
    scatter: dict[str, ValueWithError] | None = _f(
        "two calibrations: the pixel-to-pixel part, the rms over centroids of total less bias (dimensionless)", None
    )
    conditions: dict[str, Any] = _f("the star, its scene and readout, the residual and the method")
    flags: list[str] = _f("warnings about the answer's validity (text)")
    flag_codes: list[str] = _f("the code of each flag, in the same order")


class RequirementResponse(BaseModel):
    """For a residual shape: the two-of-three answer (scale, tolerance, magnitude), or the envelope eps(Q)."""

    model_config = ConfigDict(extra="allow")

    metric: str = _f("the PSF metric (no unit)")
    shape: str = _f("the residual's shape family, as a formula (text)")
    tolerance: float = _f("the tolerated error of the metric, dimensionless")
    scale: float | None = _f("the shape's scale s (unit: the shape's, so that r is in e-)", None)
    magnitude: float | None = _f("the star's magnitude, AB mag (solved for, or given)", None)
    solved_for: str | None = _f("scale, tolerance or magnitude (no unit); absent for an envelope", None)
    response_per_unit_scale: float | None = _f("the metric's change per unit scale, integral K(Q) shape(Q) dQ", None)
    response_uncertainty: float | None = _f("its 1-sigma statistical uncertainty", None)
    charge_e: list[float] | None = _f("envelope: the charge levels Q, in e-", None)
    epsilon_e: list[float] | None = _f("envelope: eps(Q), the largest residual of the shape allowed at each Q, in e-", None)
    worst_magnitude: float | None = _f("envelope: the magnitude (AB mag) whose response sets the scale", None)
    magnitudes: list[float] | None = _f("envelope: [brightest, faintest] in AB mag", None)
    conditions: dict[str, Any] = _f("the star's scene, readout and settings")
