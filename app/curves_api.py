"""Curves for plotting: slope vs magnitude per band, the metric vs beta and vs sigma_beta."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query

from nlpsf import defaults
from nlpsf.serialise import json_safe
from nlpsf.sim import detector
from nlpsf.slopes import fidelity, tables
from nlpsf.solve import solver

from . import data_models, models
from .errors import SafeJSONResponse
from .params import ERRORS, Band, Beta0, Exptime, FullWell, Magnitude, MetricQuery, ModeQuery, Points, Sca

router = APIRouter(prefix="/api/v1")


@router.get(
    "/curves/slope",
    response_model=data_models.SlopeCurves,
    responses=ERRORS,
    summary="Slope vs magnitude for every band (the paper's Figs. 3 and 5)",
)
def slope_curves(
    metric: MetricQuery = "size",
    mode: ModeQuery = "bias",
    sca: Sca = 18,
    exptime: Exptime = defaults.EXPTIME_S,
    beta0: Beta0 = defaults.BETA0,
    full_well: FullWell = defaults.FULL_WELL_E,
    bands: Annotated[list[models.Band] | None, Query(description="bands to include (no unit; default: all with tables)")] = None,
) -> SafeJSONResponse:
    chosen = list(dict.fromkeys(bands)) if bands else tables.load_tables().bands  # a band asked twice is one curve
    curves = [tables.curve(b, sca, metric, mode, exptime=exptime, beta0=beta0, full_well=full_well) for b in chosen]
    for curve in curves:
        # The table level's measured error beside the statistical one (the calculator quotes both).
        curve["fidelity_relative_uncertainty"], _ = fidelity.fidelity_error("table", curve["band"], metric, mode)
    return SafeJSONResponse(
        {
            "source": "table: the shipped slope tables, interpolated in magnitude and scaled to these conditions",
            "metric": metric,
            "mode": mode,
            "curves": json_safe(curves),
        }
    )


def _linear_curve(
    band: str, sca: int, metric: str, mode: str, magnitude: float, exptime: float, beta0: float, full_well: float, xs: list[float]
) -> dict[str, Any]:
    # The solver at precision 1 returns tolerance = |c(m)| beta0 and the signed slope c(m): the curve is
    # the line c(m) x through 0 (signed, since Delta e1 and Delta e2 can be negative).
    solution = solver.solve(
        band,
        sca=sca,
        metric=metric,
        mode=mode,
        beta0=beta0,
        exptime=exptime,
        precision=1.0,
        magnitude=magnitude,
        full_well=full_well,
        scene="paper",  # the shipped tables' curve (the paper's scene)
    ).to_dict()
    # The statistical part per point, the fidelity part as one relative number (the page shows both).
    at_beta0 = solution["tolerance"]
    statistical, systematic = solution["uncertainty_statistical"], solution["uncertainty_fidelity"]
    relative = abs((statistical or 0.0) / at_beta0) if at_beta0 else 0.0
    slope = solution["slope"] or 0.0
    values = [slope * x for x in xs]
    return {
        "values": values,
        "uncertainty": [abs(v) * relative for v in values],
        "fidelity_relative_uncertainty": abs(systematic / at_beta0) if at_beta0 and systematic is not None else None,
        "slope": solution["slope"],
        "flags": solution["flags"],
        "flag_codes": solution["flag_codes"],
        "saturation_magnitude": solution["saturation_magnitude"],
        "conditions": solution["conditions"],
    }


def _grid(top: float, points: int) -> list[float]:
    return [top * k / (points - 1) for k in range(points)]


@router.get(
    "/curves/beta",
    response_model=data_models.BetaCurve,
    responses=ERRORS,
    summary="Metric vs beta at one magnitude (the paper's Fig. 2)",
)
def beta_curve(
    band: Band = "H158",
    sca: Sca = 18,
    metric: MetricQuery = "size",
    magnitude: Magnitude = 18.3,
    exptime: Exptime = defaults.EXPTIME_S,
    beta0: Beta0 = defaults.BETA0,
    full_well: FullWell = defaults.FULL_WELL_E,
    beta_max: Annotated[
        float, Query(allow_inf_nan=False, gt=0, le=detector.MAX_ABS_BETA, description="largest beta in 1/e-")
    ] = 1.25e-6,
    points: Points = 26,
) -> SafeJSONResponse:
    betas = _grid(beta_max, points)
    curve = _linear_curve(band, sca, metric, "bias", magnitude, exptime, beta0, full_well, betas)
    return SafeJSONResponse(
        json_safe(
            {
                "source": "table, first order: metric = c(m) beta with c(m) the table's bias slope at beta0; "
                "POST /api/v1/simulations with several betas gives the full (nonlinear) response",
                "band": band.upper(),
                "sca": sca,
                "metric": metric,
                "magnitude": magnitude,
                "beta": betas,
                **curve,
            }
        )
    )


@router.get(
    "/curves/sigma_beta",
    response_model=data_models.SigmaBetaCurve,
    responses=ERRORS,
    summary="Scatter of the metric vs sigma_beta at one magnitude",
)
def sigma_beta_curve(
    band: Band = "H158",
    sca: Sca = 18,
    metric: MetricQuery = "size",
    magnitude: Magnitude = 18.3,
    exptime: Exptime = defaults.EXPTIME_S,
    beta0: Beta0 = defaults.BETA0,
    full_well: FullWell = defaults.FULL_WELL_E,
    sigma_beta_max: Annotated[
        float, Query(allow_inf_nan=False, gt=0, le=detector.MAX_ABS_BETA, description="largest sigma_beta in 1/e-")
    ] = 1e-7,
    points: Points = 26,
) -> SafeJSONResponse:
    sigmas = _grid(sigma_beta_max, points)
    curve = _linear_curve(band, sca, metric, "scatter", magnitude, exptime, beta0, full_well, sigmas)
    return SafeJSONResponse(
        json_safe(
            {
                "source": "table, first order: sigma(metric) = c_sigma(m) sigma_beta with c_sigma(m) the table's scatter slope; "
                "POST /api/v1/simulations with sigma_betas gives Monte Carlo values",
                "band": band.upper(),
                "sca": sca,
                "metric": metric,
                "magnitude": magnitude,
                "sigma_beta": sigmas,
                **curve,
            }
        )
    )
