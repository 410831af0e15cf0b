"""The kernels: NL images, perturbed and linear-response fits for bias and per-pixel scatter, returning typed results."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import detector, moments, ramps
from .. import scene as scenes
from .config import METRICS, PAPER_BETA_STEP
from .correction import corrected_effect, star_free_correction
from .prepared import Scene, _peak_electrons, _weighted_region, star_peak_electrons
from .readout import RampEffect, _nl_shape, ramp_effect
from .results import Statistic, _metrics, _reference_summary
from .sky import star_free_level
from .validity import _noise_floor_flag, _validity_flags


@dataclass(frozen=True)
class KernelResult:
    """What a bias or scatter kernel measures at one (magnitude, beta): per realization (or per beta
    map) Delta R / R, Delta e1, Delta e2 (NaN where a fit failed) and the moments' status, with the
    flags, the star's peak charge [e-], the reference moments' summary, the fixed centroid (scatter)
    and extras (e.g. the ramp's summary)."""

    dR_over_R: np.ndarray
    de1: np.ndarray
    de2: np.ndarray
    status: np.ndarray
    flags: list
    peak_electrons: float
    reference: dict
    centroid_offset: list[float] | None
    extras: dict


def nl_images(
    scene: Scene,
    charge_scale: float,
    beta,
    count: int | None = None,
    effect: RampEffect | None = None,
    margin: int = 0,
    sky_beta: float | None = None,
):
    """The detector at one flux: (linear image, its reference fit, NL perturbation, d perturbation / d beta).

    All per unit flux, for the first ``count`` realizations (all by default). ``beta`` is b2, a
    scalar or per-pixel values. This is the one place the NL meets the stamps: the paper's scene
    keeps its plain expression (beta times the derivative -s psi^2); any other
    scene goes through ``scene.detector_chain`` (brighter-fatter, IPC before/after, polynomial NL,
    background). With brighter-fatter the NL-free image depends on the flux, and its reference fit
    is made here, from the stored one. Up the ramp (``effect``) the NL pattern is psi^2 c_2
    (``_nl_shape``); a ramp with the scene's detector effects is refused by the configuration.
    ``margin`` trims that many pixels from every side of the images (centre kept; see
    :func:`_perturbed_fit`); the paper's detector then computes only the core. With a sky, its own NL
    is removed as a local sky estimate removes it (``sky.star_free_level``), at the uniform
    ``sky_beta`` (default: ``beta``, or the mean of per-pixel values).
    """
    config = scene.config
    model = config.scene
    pick = slice(None) if count is None else slice(0, count)
    n = scene.stamps.shape[-1]
    core = (Ellipsis, slice(margin, n - margin), slice(margin, n - margin))
    reference = scene.reference if count is None else moments.select(scene.reference, pick)
    if effect is not None and effect.correction is not None:
        return _corrected_images(scene, charge_scale, beta, count, effect.correction, margin, reference, sky_beta)
    if model.plain_detector:
        stamps = scene.stamps[pick][core]
        # c_2 is per pixel (trimmed like the stamps), or one value broadcast over the stamp (a uniform ramp).
        factor = None if effect is None else effect.factor
        if factor is not None and factor.shape[-1] == n:
            factor = factor[core]
        shape = _nl_shape(stamps, factor)
        derivative = -charge_scale * shape
        return stamps, reference, beta * derivative, derivative
    stamps = scene.stamps[pick]
    if effect is not None and effect.scene_ramp is not None:
        # Up the ramp in a scene: each order's NL term times the measuring pixel's factor (ramps.scene_factors).
        sr = effect.scene_ramp
        if sr.margin and sr.margin != margin:
            sr = sr.whole()  # computed on the moments' core; this call needs more of the stamps
        if count is not None and sr.charge.shape[0] > count:
            sr = sr.head(count)
        perturbation, derivative = ramps.scene_perturbation(
            sr, beta, model.nl_coefficients, model.ipc, model.ipc_order, config.oversampling
        )
        level, level_derivative = _sky_level(scene, charge_scale, beta, sky_beta, up_the_ramp=True)
        if not sr.margin:
            perturbation, derivative = perturbation[core], derivative[core]
        return stamps[core], reference, perturbation / charge_scale - level, derivative / charge_scale - level_derivative
    shift, perturbation, derivative = scenes.detector_chain(scene.charge[pick], charge_scale, beta, model, config.oversampling)
    if shift is not None:
        reference = moments.fit_perturbed(stamps, shift, reference, config.moment_settings)
        stamps = stamps + shift
    level, level_derivative = _sky_level(scene, charge_scale, beta, sky_beta, up_the_ramp=False)
    return stamps[core], reference, perturbation[core] - level, derivative[core] - level_derivative


def _corrected_images(scene: Scene, charge_scale: float, beta, count: int | None, correction, margin: int, reference, sky_beta):
    """``nl_images`` under the per-resultant correction (``experiment.correction``): ``beta`` is the
    calibration error Delta_beta (scalar or per pixel), about a perfect calibration. The image is exactly
    linear in it: baseline + Delta_beta x (the residual -Q^2's image), each per unit flux, less what a
    local sky estimate removes (the star-free pixels' own corrected level, at the uniform ``sky_beta``)."""
    corr, trim = correction.at_margin(margin)
    baseline, direction = corr.baseline[trim], corr.quadratic[trim]
    if count is not None and baseline.shape[0] > count:
        baseline, direction = baseline[:count], direction[:count]
    n = scene.stamps.shape[-1]
    core = (Ellipsis, slice(margin, n - margin), slice(margin, n - margin))
    stamps = scene.stamps[slice(None) if count is None else slice(0, count)][core]
    level, level_derivative = star_free_correction(scene, correction.raw_beta)
    uniform = sky_beta if sky_beta is not None else float(np.mean(beta))
    perturbation = (baseline + beta * direction - (level + uniform * level_derivative)) / charge_scale
    return stamps, reference, perturbation, (direction - level_derivative) / charge_scale


def _sky_level(scene: Scene, charge_scale: float, beta, sky_beta: float | None, up_the_ramp: bool) -> tuple[float, float]:
    """The sky's own NL a local sky estimate removes (``sky.star_free_level``), at one uniform b2."""
    uniform = sky_beta if sky_beta is not None else float(np.mean(beta))
    return star_free_level(scene, charge_scale, uniform, up_the_ramp)


def _perturbed_fit(
    scene: Scene, charge_scale: float, beta: float, settings: moments.MomentSettings, effect: RampEffect | None = None
) -> tuple[moments.Moments, moments.Moments, np.ndarray, np.ndarray, np.ndarray]:
    """Adaptive moments of the NL images: (fit, reference fit, stamps, NL perturbation, d perturbation / d beta).

    The fits are made on the stamps' central core (``Scene.core_margin``), and the images returned
    are that core: the weight is zero beyond the cut, and a 96 x 96 stamp is mostly outside it,
    so building and adding the whole images cost more than the fits themselves. If any fit failed
    or left the core, the whole stamps are fitted instead; otherwise the answer is the one the
    whole stamps give.
    """
    margin = scene.core_margin
    stamps, reference, perturbation, derivative = nl_images(scene, charge_scale, beta, effect=effect, margin=margin)
    fit = moments.fit_perturbed(stamps, perturbation, reference, settings)
    cut = float(settings.weight_cut_rho2)
    if margin and not (np.all(moments.within(fit, stamps.shape[-1], cut)) and _inside_factor_region(effect, fit, margin, cut)):
        stamps, reference, perturbation, derivative = nl_images(scene, charge_scale, beta, effect=effect)
        fit = moments.fit_perturbed(stamps, perturbation, reference, settings)
    return fit, reference, stamps, perturbation, derivative


def _inside_factor_region(effect: RampEffect | None, fit: moments.Moments, margin: int, cut: float) -> bool:
    """Whether every fit's weight window lies where the ramp factors were computed (``SceneRamp.region``)."""
    sr = None if effect is None else effect.scene_ramp
    corr = None if effect is None else effect.correction
    if corr is not None and corr.region is not None and corr.margin == margin:
        sr = corr  # the correction was computed on its own region (the scene ramp's, when there is one)
    if sr is None or sr.region is None or sr.margin != margin:
        return True
    if not np.all(fit.ok):
        return False  # a failed fit: judged on the whole stamps' factors, as without a region
    window = _weighted_region(sr.region.shape[-1], fit.parameters(), cut)
    return bool(np.all(sr.region[: len(window)] | ~window))


def _simulate_bias(
    scene: Scene,
    charge_scale: float,
    beta: float,
    settings: moments.MomentSettings,
    saturation_beta: float | None = None,
    corrected: bool = False,
):
    """``corrected``: the per-resultant correction (``experiment.correction``) of a detector whose raw NL
    is ``saturation_beta``, ``beta`` being the calibration error Delta_beta."""
    config = scene.config
    peak = _peak_electrons(scene, charge_scale)
    state = beta if saturation_beta is None else saturation_beta
    effect = ramp_effect(scene, charge_scale, beta=state) if config.ramp is not None else None
    flags = _validity_flags(scene, charge_scale, np.full(1, state if corrected else beta), peak, ramp_effect=effect)
    extras: dict = {} if effect is None else dict(effect.extras)
    if corrected:
        effect = corrected_effect(scene, charge_scale, state, effect)
    if config.method == "monte_carlo":
        fit, reference, *_ = _perturbed_fit(scene, charge_scale, beta, settings, effect)
        d_r, d_e1, d_e2, status = _metrics(fit, reference)
    else:
        # First order at beta = 0: the gradient of the reference fit along the NL perturbation,
        # on the stamps' core when the reference fits' weight windows lie inside it.
        margin = scene.core_margin
        stamps, reference, perturbation, derivative = nl_images(scene, charge_scale, beta, effect=effect, margin=margin)
        if margin and not np.all(moments.within(reference, stamps.shape[-1], float(settings.weight_cut_rho2))):
            stamps, reference, perturbation, derivative = nl_images(scene, charge_scale, beta, effect=effect)
        if config.scene.plain_detector and not corrected:
            linear = moments.response_to(stamps, reference, derivative, settings)[0] * beta
        else:
            linear = moments.response_to(stamps, reference, perturbation, settings)[0]
        ok = reference.ok
        d_r, d_e1, d_e2 = (np.where(ok, linear[:, k], np.nan) for k in range(3))
        status = reference.status
    peak = star_peak_electrons(scene, charge_scale)
    return KernelResult(d_r, d_e1, d_e2, status, flags, peak, _reference_summary(scene), None, extras)


_SCATTER_CHUNK = 256


def _simulate_scatter(
    scene: Scene,
    charge_scale: float,
    beta: float,
    sigma_beta: float,
    settings: moments.MomentSettings,
    stream: int,
    saturation_beta: float | None = None,
    corrected: bool = False,
):
    """``corrected``: as in :func:`_simulate_bias`; each pixel's own coefficient error then changes that
    measured pixel alone."""
    config = scene.config
    draws = config.realizations
    stamp = scene.stamps[0]
    rng = np.random.default_rng([config.seed, 1, stream])
    betas = detector.draw_pixel_betas(rng, beta, sigma_beta, (draws, *stamp.shape))
    peak = np.full(draws, float(_peak_electrons(scene, charge_scale, 1)[0]))
    state = beta if saturation_beta is None else saturation_beta
    effect = ramp_effect(scene, charge_scale, index=0, beta=state) if config.ramp is not None else None
    flags = _validity_flags(scene, charge_scale, np.full(1, state) if corrected else betas, peak[:1], index=0, ramp_effect=effect)
    offset = [float(v) for v in scene.offsets[0]]
    extras: dict = {} if effect is None else dict(effect.extras)
    if corrected:
        effect = corrected_effect(scene, charge_scale, state, effect, index=0)
    model = config.scene
    plain = model.plain_detector and not corrected
    shape = _nl_shape(stamp, None if effect is None else effect.factor[0]) if plain else None
    stamp_ref, reference0, _, _ = nl_images(scene, charge_scale, beta, count=1)
    stamp = stamp_ref[0]
    if config.method == "monte_carlo":
        d_r, d_e1, d_e2, status = _scatter_monte_carlo(
            scene, charge_scale, beta, betas, stamp, shape, reference0, settings, effect if corrected else None
        )
    else:
        if plain:
            # First order about the uniform-beta image, as the linear slopes are (``slopes(method="linear")``):
            # metric(beta_k) = metric(beta) + g(I_beta) . (-(beta_k - beta) s psi^2), exact at the mean beta
            # (psi^2 c_2 after a ramp fit).
            reference0 = moments.select(scene.reference, slice(0, 1))
            uniform = -(beta * charge_scale) * shape[None]
            fit_beta = moments.fit_perturbed(stamp[None], uniform, reference0, settings)
            base = np.array(moments.differences(fit_beta, reference0))[:, 0]
            gradient = moments.pixel_response(stamp[None] + uniform, fit_beta, settings)[0]
            # The gradient of R is relative to R(beta); Delta R / R is relative to the unperturbed R0.
            gradient[0] *= float(fit_beta.sigma[0] / reference0.sigma[0])
            response = gradient * (-shape * charge_scale)  # d metric / d beta_k, shape (3, n, n)
        else:
            # The same about the scene's uniform-beta image; the per-pixel response goes back through IPC.
            stamps1, reference0, uniform, _ = nl_images(scene, charge_scale, beta, count=1, effect=effect if corrected else None)
            fit_beta = moments.fit_perturbed(stamps1, uniform, reference0, settings)
            base = np.array(moments.differences(fit_beta, reference0))[:, 0]
            gradient = moments.pixel_response(stamps1 + uniform, fit_beta, settings)[0]
            gradient[0] *= float(fit_beta.sigma[0] / reference0.sigma[0])
            response = _per_pixel_beta_response(scene, gradient, charge_scale, effect)
        linear = base[None, :] + np.einsum("kij,bij->bk", response, betas - beta)
        ok = bool(reference0.ok[0] and fit_beta.ok[0])
        d_r, d_e1, d_e2 = (np.full(draws, np.nan) if not ok else linear[:, k] for k in range(3))
        status = np.full(draws, reference0.status[0] if not fit_beta.ok[0] else fit_beta.status[0])
        closed = np.sqrt(np.sum(response**2, axis=(1, 2))) * sigma_beta
        extras["linear_scatter_closed_form"] = {"dR_over_R": float(closed[0]), "de1": float(closed[1]), "de2": float(closed[2])}
    if config.method == "monte_carlo":
        spread = np.array([np.nanstd(v) for v in (d_r, d_e1, d_e2)])
        flags += _noise_floor_flag(scene, charge_scale, beta, sigma_beta, settings, spread, shape)
    peak = star_peak_electrons(scene, charge_scale)
    return KernelResult(d_r, d_e1, d_e2, status, flags, peak, _reference_summary(scene, 0), offset, extras)


def _scatter_monte_carlo(
    scene: Scene,
    charge_scale: float,
    beta: float,
    betas,
    stamp,
    shape,
    reference0,
    settings: moments.MomentSettings,
    corrected: RampEffect | None = None,
):
    """Every per-pixel beta map (about the uniform ``beta``) fitted to convergence at the first centroid:
    (dR/R, de1, de2, status). ``corrected``: the first centroid's per-resultant correction (its effect)."""
    draws = scene.config.realizations
    model = scene.config.scene
    ref_params = reference0.parameters()[0]
    single_reference = moments.Moments(
        *(np.full(draws, v) for v in ref_params),
        amplitude=np.full(draws, reference0.amplitude[0]),
        iterations=np.zeros(draws, dtype=np.int32),
        last_step=np.zeros(draws),
        status=np.full(draws, reference0.status[0], dtype=np.int8),
    )
    parts = []
    for s in range(0, draws, _SCATTER_CHUNK):
        block = betas[s : s + _SCATTER_CHUNK]
        base = np.broadcast_to(stamp, block.shape)
        if model.plain_detector and corrected is None:
            perturbation = -(block * charge_scale) * shape
        else:
            perturbation = nl_images(scene, charge_scale, block, count=1, effect=corrected, sky_beta=beta)[2]
        parts.append(
            moments.fit_perturbed(
                base,
                perturbation,
                moments.select(single_reference, slice(s, s + block.shape[0])),
                settings,
            )
        )
    fit = moments.concatenate(parts)
    d_r, d_e1, d_e2, status = _metrics(fit, reference0, ref_index=0)
    return d_r, d_e1, d_e2, status


def _per_pixel_beta_response(
    scene: Scene, gradient: np.ndarray, charge_scale: float, effect: RampEffect | None = None
) -> np.ndarray:
    """d metric / d beta_k for the per-pixel beta of pixel k, (3, n, n), at the first centroid.

    The NL of pixel k changes it by -Q_k^2 (Q the charge it acts on); IPC after the NL then spreads
    that change to the neighbours, so the gradient is carried back through IPC's transpose. Up the
    ramp the measuring pixel's factor c_2 multiplies the gradient first (``ramps.scene_factors``).
    """
    model = scene.config.scene
    if effect is not None and effect.correction is not None:
        # The per-resultant correction: pixel k's own coefficient corrects pixel k's measured resultants
        # (after IPC), so its error changes that pixel alone, by Delta_beta_k times the residual's image.
        corr, _ = effect.correction.at_margin(0)
        return gradient * corr.quadratic[0] / charge_scale
    charge = scenes.charge_before_nl(scene.charge[:1], charge_scale, model, scene.config.oversampling)[0]
    pulled = gradient
    if effect is not None and effect.scene_ramp is not None:
        pulled = gradient * effect.scene_ramp.factors[0][0]
    if model.ipc is not None and model.ipc_order == "after":
        pulled = scenes.apply_ipc_adjoint(pulled, model.ipc, scene.config.oversampling)
    return pulled * (-(charge**2) / charge_scale)


def _finite_difference_slopes(
    scene: Scene,
    charge_scale: float,
    beta: float,
    settings: moments.MomentSettings,
    effect: RampEffect | None = None,
    step: float | None = None,
):
    """Symmetric difference over beta +- ``step`` (default: the paper's, beta0 x 1 %)."""
    # The paper's states as the paper's arithmetic (beta x 0.99, x 1.01: its answers bit for bit).
    states = [beta * (1 - PAPER_BETA_STEP), beta * (1 + PAPER_BETA_STEP)] if step is None else [beta - step, beta + step]
    step = PAPER_BETA_STEP * beta if step is None else step
    values = []
    statuses = []
    for state in states:
        fit, reference, *_ = _perturbed_fit(scene, charge_scale, state, settings, effect)
        d_r, d_e1, d_e2, status = _metrics(fit, reference)
        values.append(np.stack([d_r, d_e1, d_e2]))
        statuses.append(status)
    slope = (values[1] - values[0]) / (2 * step)
    status = np.where(statuses[0] != moments.MomentStatus.OK, statuses[0], statuses[1])
    return {name: Statistic.of(slope[k]) for k, name in enumerate(METRICS)}, status


def _linear_slopes(
    scene: Scene, charge_scale: float, beta: float, settings: moments.MomentSettings, effect: RampEffect | None = None
):
    # Everything at unit flux: the distorted image is psi - beta s psi^2 (moments ignore scale),
    # and d/d beta of the charge image divided by s is -s psi^2 (times c_2 after a ramp fit; scene
    # effects: ``nl_images``).
    fit, reference, stamps, perturbation, derivative = _perturbed_fit(scene, charge_scale, beta, settings, effect)
    distorted = stamps + perturbation
    bias_values, scatter_values = (v.T.copy() for v in moments.response_to(distorted, fit, derivative, settings))
    ok = fit.ok & reference.ok
    # The gradient of R is relative to R(beta0); Delta R / R is relative to the unperturbed R0.
    size_scale = fit.sigma / reference.sigma
    bias_values[0] *= size_scale
    scatter_values[0] *= size_scale
    bias = {name: Statistic.of(np.where(ok, bias_values[k], np.nan)) for k, name in enumerate(METRICS)}
    scatter = {}
    for k, name in enumerate(METRICS):
        stat = Statistic.of(np.where(ok, scatter_values[k], np.nan))
        scatter[name] = {"value": stat.mean, "uncertainty": stat.stderr}
    status = np.where(fit.ok, reference.status, fit.status)
    return bias, scatter, status
