"""The public entry points: ``simulate`` (metrics at each magnitude and beta) and ``slopes`` (Figs. 3 and 5)."""

from __future__ import annotations

import math
import time
from collections.abc import Sequence

import numpy as np

from nlpsf import defaults
from nlpsf.checks import InputError, check_choice, check_number, check_numbers
from nlpsf.flags import FlagCode, make
from nlpsf.sim import detector, moments
from nlpsf.threads import single_blas

from .config import (
    CORRECTED_MONTE_CARLO_STEP,
    CORRECTED_RESIDUAL,
    LINEARISE_STATES,
    METRICS,
    PAPER_BETA_STEP,
    Progress,
    SimulationConfig,
)
from .correction import RESIDUAL_DESCRIPTIONS, RESIDUAL_MODELS, check_model, corrected_effect
from .kernels import _finite_difference_slopes, _linear_slopes, _simulate_bias, _simulate_scatter
from .prepared import Scene, _peak_electrons, prepare, star_peak_electrons
from .readout import RampEffect, ramp_effect
from .results import SimulationResult, SlopeResult, Statistic
from .validity import _failure_flag, _scene_flags, _validity_flags, _zero_flag


def check_magnitudes(values) -> list[float]:
    return check_numbers(values, "magnitude", *defaults.MAGNITUDE_RANGE)


def check_sigma_beta(sigma_beta) -> float:
    return check_number(sigma_beta, "sigma_beta", 0.0, detector.MAX_ABS_BETA)


@single_blas
def simulate(
    config: SimulationConfig,
    magnitudes: Sequence[float] | float,
    betas: Sequence[float] | float,
    sigma_beta: float = 0.0,
    beta_convention: str = "paper",
    scene: Scene | None = None,
    progress: Progress | None = None,
    saturation_beta: float | None = None,
    residual_nl: str | None = None,
) -> list[SimulationResult]:
    """Change of ΔR/R, Δe1, Δe2 for every (magnitude, beta) pair, magnitude outermost.

    ``saturation_beta``: the raw detector's beta (paper convention) a ramp's "signal" saturation rule
    sees, when it is not the beta simulated (a residual NL after the linearity correction).

    ``residual_nl="per_resultant_correction"`` (``experiment.correction``): the detector's raw NL is
    ``saturation_beta`` (default beta0), corrected on every resultant as romancal does, and each ``beta``
    is the calibration error Delta_beta it leaves, r(Q) = -Delta_beta Q^2; the metrics are against the
    linear image. None / "per_read_beta": ``beta`` is the NL on every read, as before.

    With ``sigma_beta`` > 0 each fine pixel gets its own beta ~ N(beta, sigma_beta^2) and, as in
    the paper, the centroid is fixed (the first realization's) while the ``realizations`` are
    independent draws of the beta map; the metrics' ``std`` is then the scatter over those draws.
    """
    mags = check_magnitudes(magnitudes)
    given_betas = check_numbers(betas, "beta")
    paper_betas = [detector.to_paper_beta(b, beta_convention) for b in given_betas]
    sigma_beta = check_sigma_beta(sigma_beta)
    if residual_nl is not None:
        check_choice(residual_nl, "residual_nl", RESIDUAL_MODELS)
    corrected = residual_nl == "per_resultant_correction"
    if corrected and saturation_beta is None:
        saturation_beta = defaults.BETA0
    scene = _prepared_for(config, scene)
    conditions = _simulation_conditions(config, residual_nl if corrected else None, saturation_beta)
    settings = config.moment_settings
    scene_flags = _scene_flags(scene)
    results: list[SimulationResult] = []
    total = len(mags) * len(paper_betas)
    share = scene.elapsed_s / total
    for m_index, magnitude in enumerate(mags):
        flux = float(config.electrons(magnitude))
        charge_scale = flux * config.oversampling**2
        for b_index, (beta_given, beta) in enumerate(zip(given_betas, paper_betas, strict=True)):
            start = time.perf_counter()
            if progress:
                progress(m_index * len(paper_betas) + b_index, total, f"m={magnitude:g} beta={beta_given:g}")
            seed = m_index * 7919 + b_index
            result = _bias_or_scatter(scene, charge_scale, beta, sigma_beta, settings, seed, saturation_beta, corrected)
            status = result.status
            results.append(
                SimulationResult(
                    conditions=conditions,
                    magnitude=magnitude,
                    beta=beta_given,
                    beta_convention=beta_convention,
                    beta_paper=beta,
                    sigma_beta=sigma_beta,
                    realizations=config.realizations,
                    flux_electrons=flux,
                    peak_electrons=result.peak_electrons,
                    reference=result.reference,
                    dR_over_R=Statistic.of(result.dR_over_R),
                    de1=Statistic.of(result.de1),
                    de2=Statistic.of(result.de2),
                    failed_realizations=int(np.sum(status != moments.MomentStatus.OK)),
                    flags=scene_flags + result.flags + _failure_flag(status) + _zero_flag(result.dR_over_R),
                    elapsed_s=time.perf_counter() - start + share,
                    centroid_offset=result.centroid_offset,
                    extras=result.extras,
                )
            )
    if progress:
        progress(total, total, "done")
    return results


@single_blas
def slopes(
    config: SimulationConfig,
    magnitudes: Sequence[float] | float,
    beta0: float = defaults.BETA0,
    sigma_beta: float | None = None,
    beta_convention: str = "paper",
    scene: Scene | None = None,
    progress: Progress | None = None,
    linearise_at: str = "beta0",
    residual_nl: str | None = None,
) -> list[SlopeResult]:
    """Bias and scatter slopes at ``beta0`` for each magnitude (paper Figs. 3 and 5).

    ``linearise_at`` (:data:`LINEARISE_STATES`): "beta0", the paper's, the slope of the uncorrected
    detector at beta0; "corrected", the slope a calibration error acts through once the pipeline has
    corrected the NL, modelled by ``residual_nl`` (``experiment.correction.RESIDUAL_MODELS``; None: the
    default, "per_resultant_correction"): the raw beta0 read by read, IPC, resultants, the correction on
    every resultant as romancal applies it, and the slope d metric / d Delta_beta of the residual
    r(Q) = -Delta_beta Q^2 about a perfect calibration; or "per_read_beta", the earlier model, a residual
    CORRECTED_RESIDUAL x beta0 on every read before IPC. Either way a ramp's saturation flags are those of
    the raw beta0 (docs/ramps.md). The scatter keeps sigma_beta (a per-pixel calibration error).

    ``monte_carlo``: the paper's method. The bias slope is the finite difference over
    beta0 * {0.99, 1.01} (identical to its 3-point linear fit) for each centroid; the scatter slope
    is the spread of the metrics over ``realizations`` draws of per-pixel beta ~ N(beta0,
    sigma_beta^2) at a fixed centroid, divided by sigma_beta (default sigma_beta = 0.1 beta0), with
    the standard error of a standard deviation.

    ``linear``: exact derivatives at beta0 from the gradient of the moments at the NL-distorted
    image: slope = g(I_beta0) . dI/dbeta and scatter slope = ||g (.) dI/dbeta||, averaged over the
    centroid realizations (uncertainty: their standard error).
    """
    mags = check_magnitudes(magnitudes)
    check_choice(linearise_at, "linearise_at", LINEARISE_STATES)
    model = check_model(residual_nl, linearise_at)
    corrected = model == "per_resultant_correction"
    raw, beta, sigma_beta = _slope_betas(beta0, beta_convention, linearise_at, sigma_beta)
    if corrected:
        beta = 0.0  # about a perfect calibration; the raw beta0 is corrected on every resultant
    scene = _prepared_for(config, scene)
    conditions = _slope_conditions(config, linearise_at, beta, raw, model)
    settings = config.moment_settings
    scene_flags = _scene_flags(scene)
    out: list[SlopeResult] = []
    share = scene.elapsed_s / len(mags)
    for index, magnitude in enumerate(mags):
        start = time.perf_counter()
        if progress:
            progress(index, len(mags), f"m={magnitude:g}")
        flux = float(config.electrons(magnitude))
        charge_scale = flux * config.oversampling**2
        effect, flags, extras = _readout_at(scene, charge_scale, raw, corrected)
        flags = scene_flags + flags
        bias, scatter, status, basis = _method_slopes(
            scene, settings, magnitude, charge_scale, beta, raw, sigma_beta, effect, flags, model
        )
        out.append(
            SlopeResult(
                conditions=conditions,
                magnitude=magnitude,
                beta0=beta0,
                beta_convention=beta_convention,
                flux_electrons=flux,
                peak_electrons=star_peak_electrons(scene, charge_scale),
                bias=bias,
                scatter=scatter,
                scatter_basis=basis,
                failed_realizations=int(np.sum(status != moments.MomentStatus.OK)),
                flags=flags + _failure_flag(status),
                elapsed_s=time.perf_counter() - start + share,
                extras=extras,
            )
        )
    if progress:
        progress(len(mags), len(mags), "done")
    return out


def _prepared_for(config: SimulationConfig, scene: Scene | None) -> Scene:
    """``scene`` (prepared now where None), checked to be ``config``'s."""
    scene = scene or prepare(config)
    if scene.config != config:
        raise InputError("scene", "the scene was prepared for a different configuration")
    return scene


def _simulation_conditions(config: SimulationConfig, residual_nl: str | None, saturation_beta: float | None) -> dict:
    """The configuration's conditions, with the residual model and the raw beta a corrected detector has."""
    conditions = config.conditions()
    if residual_nl is not None:
        conditions["residual_nl"] = residual_nl
        conditions["raw_beta"] = saturation_beta
    return conditions


def _bias_or_scatter(scene: Scene, charge_scale, beta, sigma_beta, settings, seed, saturation_beta, corrected):
    """One (magnitude, beta) of :func:`simulate`: the bias at a uniform beta, or with ``sigma_beta`` > 0
    the scatter over ``realizations`` draws of the beta map (``seed``: the pair's draws)."""
    if sigma_beta > 0:
        return _simulate_scatter(scene, charge_scale, beta, sigma_beta, settings, seed, saturation_beta, corrected)
    return _simulate_bias(scene, charge_scale, beta, settings, saturation_beta, corrected)


def _method_slopes(scene: Scene, settings, magnitude, charge_scale, beta, raw, sigma_beta, effect, flags, model):
    """(bias, scatter, status, scatter basis) of one magnitude by the configuration's method: the
    paper's Monte Carlo, or the linear response at beta0."""
    if scene.config.method == "monte_carlo":
        return _monte_carlo_slopes(scene, magnitude, charge_scale, beta, raw, sigma_beta, effect, flags, model)
    bias, scatter, status = _linear_slopes(scene, charge_scale, beta, settings, effect)
    return bias, scatter, status, "linear response at beta0: ||g . dI/dbeta|| averaged over centroid realizations"


def _readout_at(scene: Scene, charge_scale: float, raw: float, corrected: bool) -> tuple[RampEffect | None, list, dict]:
    """(the readout's effect at this flux, its validity flags, its extras): the ramp's factors and flags at
    the raw beta0, and the per-resultant correction when the residual is modelled that way."""
    config = scene.config
    peak = _peak_electrons(scene, charge_scale)
    effect = ramp_effect(scene, charge_scale, beta=raw) if config.ramp is not None else None
    flags = _validity_flags(scene, charge_scale, np.full(1, raw * (1 + PAPER_BETA_STEP)), peak, ramp_effect=effect)
    extras = {} if effect is None else dict(effect.extras)
    if corrected:
        effect = corrected_effect(scene, charge_scale, raw, effect)
    return effect, flags, extras


def _slope_conditions(config: SimulationConfig, linearise_at: str, beta: float, raw: float, model: str | None) -> dict:
    """The configuration's conditions with the state a slope is taken at and its residual model."""
    conditions = config.conditions()
    if linearise_at != "beta0":
        conditions["linearised_at"] = {"state": linearise_at, "beta": beta, "saturation_beta": raw, "residual_nl": model}
        conditions["residual_nl"] = model
        conditions["residual_nl_description"] = RESIDUAL_DESCRIPTIONS[model]
    return conditions


def _cut_jump_flags(
    scene: Scene,
    charge_scale: float,
    beta: float,
    settings: moments.MomentSettings,
    bias: dict[str, Statistic],
    effect: RampEffect | None = None,
) -> list[str]:
    """Flag finite-difference slopes that a hard weight cut made jumpy.

    With the weight cut at rho^2 = 25, a pixel that crosses the cut between beta0 x 0.99 and x 1.01
    changes the moments by a step (w = e^-12.5 of its value), which the 2 % beta step turns into a
    slope error; the symmetric difference itself is otherwise exact to (1 %)^2. The exact derivative
    at beta0 (the linear method) has no such step, so the two are compared and a difference above
    0.1 % is reported. Measured (50 centroids, H158/J129/F184, m = 18.5-22.5): the two agree to 1e-8
    unless a realization crosses the cut, which moves the e slopes by 0.1-1.8 % and, being one
    outlier, also sets the stated standard error (the difference is then 1.0 standard error).
    """
    if not math.isfinite(scene.config.weight_cut_rho2):
        return []
    exact, _, _ = _linear_slopes(scene, charge_scale, beta, settings, effect)
    off = []
    for name in METRICS:
        fd, lin = bias[name], exact[name]
        if fd.mean is None or lin.mean is None or lin.mean == 0:
            continue
        difference = abs(fd.mean - lin.mean)
        if difference > 1e-3 * abs(lin.mean):
            off.append(f"{name} {100 * difference / abs(lin.mean):.2g} %")
    if not off:
        return []
    return [make(FlagCode.JUMPY_FINITE_DIFFERENCE, differences=", ".join(off), cut=scene.config.weight_cut_rho2)]


def _monte_carlo_slopes(
    scene: Scene,
    magnitude: float,
    charge_scale: float,
    beta: float,
    raw: float,
    sigma_beta: float,
    effect,
    flags: list,
    model: str | None = None,
):
    """The paper's slopes at one magnitude: the bias by finite differences over centroids, the scatter
    as the spread over per-pixel beta maps at a fixed centroid; adds their flags to ``flags``. Under the
    per-resultant correction the difference is over Delta_beta = +-CORRECTED_MONTE_CARLO_STEP x beta0 about a
    perfect calibration (the image is exactly linear in Delta_beta, so only the moments' curvature separates it
    from the derivative; see the constant for why not smaller)."""
    config = scene.config
    settings = config.moment_settings
    step = CORRECTED_MONTE_CARLO_STEP * abs(raw) if model == "per_resultant_correction" else None
    bias, status = _finite_difference_slopes(scene, charge_scale, beta, settings, effect, step)
    flags += _cut_jump_flags(scene, charge_scale, beta, settings, bias, effect)
    scatter_runs = simulate(
        config, [magnitude], [beta], sigma_beta=sigma_beta, scene=scene, saturation_beta=raw, residual_nl=model
    )[0]
    scatter = {}
    for name in METRICS:
        stat: Statistic = getattr(scatter_runs, name)
        if stat.std is None or stat.count < 2:
            scatter[name] = {"value": None, "uncertainty": None}
        else:
            value = stat.std / sigma_beta
            scatter[name] = {"value": value, "uncertainty": value / math.sqrt(2 * (stat.count - 1))}
    basis = (
        f"Monte Carlo: spread over {config.realizations} per-pixel beta maps with sigma_beta={sigma_beta:g} "
        "at a fixed centroid (the paper's method)"
    )
    flags += [f for f in scatter_runs.flags if f not in flags]
    return bias, scatter, status, basis


def _slope_betas(beta0: float, beta_convention: str, linearise_at: str, sigma_beta: float | None):
    """(raw beta0 in the paper's convention, the beta the slope is taken at, sigma_beta), checked."""
    raw = detector.to_paper_beta(beta0, beta_convention)
    if raw == 0:
        raise InputError("beta0", "slopes are taken at beta0, which must not be zero")
    # The beta the slope is taken at; the raw beta0 still sets what saturates.
    beta = raw if linearise_at == "beta0" else CORRECTED_RESIDUAL * raw
    if sigma_beta is None:
        sigma_beta = defaults.SIGMA_BETA_FRACTION * abs(raw)
    sigma_beta = check_sigma_beta(sigma_beta)
    if sigma_beta == 0:
        raise InputError("sigma_beta", "the scatter slope needs sigma_beta > 0")
    return raw, beta, sigma_beta
