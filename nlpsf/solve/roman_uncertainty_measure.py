"""Measuring the Roman default's model uncertainty part by part (``scripts/model_uncertainty_roman.py``
and the tests): each part's variant scene, the slopes inside the full default scene, and the joint fit
of nlpsf's optics to the official PSF statistics. What the answers read at run time, the shipped
file and its combination rule, is ``roman_uncertainty``'s; this module only makes that file."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from nlpsf.request import presets

from .roman_uncertainty import (
    BFE_COEFFICIENT,
    BFE_RESIDUAL_NL,
    DIFFUSION_SIGMA_PX,
    JITTER_PROBE_ARCSEC,
    JITTER_SIGMA_ARCSEC,
    METRICS,
    MODES,
    NL_SHAPE_COEFFICIENTS,
    OFFICIAL_ROUNDING,
    OFFICIAL_SED,
    OPTICS_BLUR_PROBE_ARCSEC2,
    OPTICS_PUPIL_PROBE,
    OPTICS_SCAS,
    SED_RANGE,
    pupil_log_scale,
)


def _metric_values(result) -> dict:
    """{mode: {metric: (value, error)}} of one experiment.SlopeResult; e = hypot(e1, e2)."""
    out = {"bias": {}, "scatter": {}}
    b = {k: (result.bias[k].mean, result.bias[k].stderr) for k in ("dR_over_R", "de1", "de2")}
    s = {k: (result.scatter[k]["value"], result.scatter[k]["uncertainty"]) for k in ("dR_over_R", "de1", "de2")}
    for mode, values in (("bias", b), ("scatter", s)):
        if any(v[0] is None or not math.isfinite(v[0]) for v in values.values()):
            out[mode] = None
            continue
        (r, re), (e1, e1e), (e2, e2e) = values["dR_over_R"], values["de1"], values["de2"]
        modulus = math.hypot(e1, e2)
        out[mode] = {
            "size": (r, re or 0.0),
            "e1": (e1, e1e or 0.0),
            "e2": (e2, e2e or 0.0),
            "e": (modulus, math.hypot((e1 * (e1e or 0.0)), (e2 * (e2e or 0.0))) / modulus if modulus else 0.0),
        }
    return out


def relative_change(base: dict, variant: dict) -> dict:
    """{metric: (change, error)} of ``variant`` against ``base`` (:func:`_metric_values` of one
    mode): size and e against their own base slope, e1 and e2 against the base |c_e|. The error is
    the two slopes' statistical errors in quadrature (ignoring that the draws are shared)."""
    if base is None or variant is None:
        return dict.fromkeys(METRICS)
    modulus = base["e"][0]
    out = {}
    for metric in METRICS:
        (b, be), (v, ve) = base[metric], variant[metric]
        scale = abs(modulus) if metric in ("e1", "e2") else abs(b)
        out[metric] = None if scale == 0 else ((v - b) / scale, math.hypot(be, ve) / scale)
    return out


def default_config(band: str, sca: int, realizations: int, seed: int, position=None):
    """The Roman default's simulation at (band, sca, position), as ``tablebuild`` builds it."""
    from nlpsf.slopes import tablebuild

    return tablebuild.TableSettings.roman(realizations=realizations, seed=seed).config(band, sca, position=position)


#: Each measured variant: (part or range, scale applied to its relative change). The optics'
#: two directions are sensitivities (per unit of v and of ln s), combined with the fit later.
def variant_configs(config) -> dict[str, tuple[object, float]]:
    """The configurations compared against the default, with the factor that turns the slope's
    relative change into the part's value: {name: (config, factor)}. Brighter-fatter's pair is
    :func:`bfe_pair`'s and the diffusion profile's scene :func:`prepare_sech_diffusion`'s."""
    scene = config.scene
    out: dict[str, tuple[object, float]] = {}
    jitter = math.sqrt(scene.jitter_arcsec**2 + OPTICS_BLUR_PROBE_ARCSEC2)
    out["optics_v"] = (replace(config, scene=replace(scene, jitter_arcsec=jitter)), 1.0 / OPTICS_BLUR_PROBE_ARCSEC2)
    log_scale = pupil_log_scale(config.band, config.sca, OPTICS_PUPIL_PROBE, config.pupil_scale)
    out["optics_s"] = (replace(config, pupil_scale=OPTICS_PUPIL_PROBE), 1.0 / log_scale)
    # Jitter: linear in the variance; the part is one standard deviation of it (2 j sigma_j).
    probe_variance = JITTER_PROBE_ARCSEC**2 - scene.jitter_arcsec**2
    out["jitter"] = (
        replace(config, scene=replace(scene, jitter_arcsec=JITTER_PROBE_ARCSEC)),
        2 * scene.jitter_arcsec * JITTER_SIGMA_ARCSEC / probe_variance,
    )
    out["charge_diffusion"] = (
        replace(config, scene=replace(scene, charge_diffusion_px=scene.charge_diffusion_px + DIFFUSION_SIGMA_PX)),
        1.0,
    )
    out["nl_shape"] = (replace(config, scene=replace(scene, nl_coefficients=NL_SHAPE_COEFFICIENTS)), 1.0)
    for end, sed in zip(("sed_cool", "sed_hot"), SED_RANGE, strict=True):
        out[end] = (replace(config, scene=replace(scene, sed=sed)), 1.0)
    return out


def bfe_pair(config):
    """(final frame without BFE, with BFE): the default scene read as one final frame of the same
    exposure, the comparison brighter-fatter is measured by (a ramp refuses it)."""
    frame = replace(config, ramp=None)
    return frame, replace(frame, scene=replace(frame.scene, bfe_coefficient=BFE_COEFFICIENT))


def sech_transfer(frequencies: np.ndarray, sigma_arcsec: float) -> np.ndarray:
    """Fourier transform of a unit-flux separable hyperbolic-secant profile of per-axis standard
    deviation ``sigma`` (density sech(pi x / (2 sigma)) / (2 sigma) per axis): sech(2 pi sigma k_x)
    sech(2 pi sigma k_y) on (f_y, f_x). To second order in k it is the Gaussian's of that sigma."""
    one = 1.0 / np.cosh(2.0 * math.pi * sigma_arcsec * np.asarray(frequencies, dtype=np.float64))
    return one[:, None] * one[None, :]


def prepare_sech_diffusion(config):
    """``experiment.prepare`` of ``config`` with its charge diffusion a separable sech profile of
    the same per-axis sigma instead of the Gaussian (the jitter stays Gaussian). Everything else is
    ``prepare``'s own code path; ``tests/library/test_roman_uncertainty.py`` checks that with the
    Gaussian put back it is ``prepare`` exactly."""
    return _prepare_with_diffusion(config, "sech")


def _prepare_with_diffusion(config, profile: str):
    import time

    from nlpsf import roman
    from nlpsf.sim import moments, optics, render
    from nlpsf.sim import scene as scenes
    from nlpsf.sim.experiment.prepared import Scene

    start = time.perf_counter()
    grid = config.grid
    psf = optics.effective_psf(config.optics, round(grid.field_arcsec(), 9))
    sigma = config.scene.charge_diffusion_px * roman.PIXEL_SCALE_ARCSEC
    if profile == "gaussian":
        psf = scenes.blur(psf, config.scene.blur_sigma_arcsec())
    else:
        psf = scenes.blur(psf, config.scene.jitter_arcsec)
        coefficients = psf.coefficients * sech_transfer(psf.frequencies, sigma)
        coefficients.setflags(write=False)
        psf = optics.EffectivePSF(psf.optics, psf.field_arcsec, psf.frequencies, coefficients, psf.wavelengths_nm, psf.weights)
    rng = np.random.default_rng(config.seed)
    offsets = render.draw_offsets(rng, config.realizations, config.oversampling)
    stamps = np.empty((config.realizations, grid.stamp, grid.stamp))
    for first in range(0, config.realizations, 256):
        stamps[first : first + 256] = render.draw(psf, grid, offsets[first : first + 256])
    unit_charge = None
    if config.scene.ipc is not None:
        unit_charge, stamps = stamps, scenes.apply_ipc(stamps, config.scene.ipc, config.oversampling)
    parts = [moments.fit(stamps[first : first + 256], config.moment_settings) for first in range(0, config.realizations, 256)]
    reference = moments.concatenate(parts)
    return Scene(config, psf, offsets, stamps, reference, time.perf_counter() - start, unit_charge)


def _slopes(config, magnitudes, linearise_at, scene=None, residual_nl: str = presets.RESIDUAL_NL):
    from nlpsf.sim import experiment

    try:
        results = experiment.slopes(config, list(magnitudes), linearise_at=linearise_at, scene=scene, residual_nl=residual_nl)
        return [_metric_values(r) for r in results]
    except Exception as error:  # a variant the simulator refuses is recorded, not fatal
        return [{"error": f"{type(error).__name__}: {error}"} for _ in magnitudes]


def measure_point(band: str, sca: int, magnitudes, realizations: int = 50, seed: int = 1) -> dict:
    """Every variant's signed relative change at (band, sca), per magnitude and mode, scaled to its
    part (:func:`variant_configs`): {"changes": {name: {mode: {metric: [[m, value, error], ...]}}},
    "base": ..., "pupil_log_scale": {rule: ln(s_rule / s_official)}}. ``optics_v`` and ``optics_s``
    are sensitivities (per arcsec^2, per unit ln s), the rest parts' values or a range's ends."""
    linearise = presets.LINEARISE_AT
    config = default_config(band, sca, realizations, seed)
    base = _slopes(config, magnitudes, linearise)
    runs: dict[str, tuple[list, list, float]] = {}
    for name, (variant, factor) in variant_configs(config).items():
        runs[name] = (base, _slopes(variant, magnitudes, linearise), factor)
    runs["diffusion_profile"] = (base, _slopes(config, magnitudes, linearise, prepare_sech_diffusion(config)), 1.0)
    frame, with_bfe = bfe_pair(config)
    # The per-resultant correction is not modelled with BFE: the pair's difference at the per-read residual.
    runs["brighter_fatter"] = (
        _slopes(frame, magnitudes, linearise, residual_nl=BFE_RESIDUAL_NL),
        _slopes(with_bfe, magnitudes, linearise, residual_nl=BFE_RESIDUAL_NL),
        1.0,
    )
    out: dict = {"band": band, "sca": sca, "magnitudes": list(magnitudes), "changes": {}, "errors": {}}
    for name, (reference, variant, factor) in runs.items():
        per_mode: dict = {mode: {metric: [] for metric in METRICS} for mode in MODES}
        for index, magnitude in enumerate(magnitudes):
            r, v = reference[index], variant[index]
            for mode in MODES:
                if "error" in r or "error" in v:
                    out["errors"][name] = r.get("error") or v.get("error")
                    change = dict.fromkeys(METRICS)
                else:
                    change = relative_change(r[mode], v[mode])
                for metric in METRICS:
                    c = change[metric]
                    per_mode[mode][metric].append(
                        [magnitude, None, None] if c is None else [magnitude, factor * c[0], abs(factor) * c[1]]
                    )
        out["changes"][name] = per_mode
    out["pupil_log_scale"] = {rule: pupil_log_scale(band, sca, rule) for rule in ("header", "galsim")}
    out["base"] = {
        f"{m:g}": {mode: None if b.get(mode) is None else {k: v[0] for k, v in b[mode].items()} for mode in MODES}
        for m, b in zip(magnitudes, base, strict=True)
        if "error" not in b
    }
    return out


# --- the optics fit ----------------------------------------------------------------------------


def _official_data(band: str, sca: int) -> list[tuple[str, str, float]]:
    """(statistic, centring, official value) of one (band, SCA); the FWHM once (centring-free)."""
    from nlpsf.sim import psfstats

    official = psfstats.official_statistics()
    rows = [("fwhm_arcsec", "center", official[(sca, band, "center")].fwhm_arcsec)]
    for name in ("n_eff_pixels", "peak_fraction", "total_flux"):
        for centring in psfstats.CENTRINGS:
            rows.append((name, centring, getattr(official[(sca, band, centring)], name)))
    return rows


def fit_with_scatter(y: np.ndarray, jacobian: np.ndarray, errors: np.ndarray):
    """Weighted linear least squares of ``y`` = ``jacobian`` theta with each datum's stated error and
    an intrinsic scatter s added to all in quadrature, s chosen so that chi^2 per degree of freedom
    is 1 (0 where the stated errors alone already give chi^2 <= dof): (theta, its covariance, chi^2,
    residuals, s). The usual way to let a model that cannot describe everything say how much it
    cannot, without narrowing the parameters' errors to the data's rounding."""

    def solve(scatter: float):
        w = 1.0 / (errors**2 + scatter**2)
        covariance = np.linalg.inv(jacobian.T @ (w[:, None] * jacobian))
        theta = covariance @ (jacobian.T @ (w * y))
        residual = y - jacobian @ theta
        return theta, covariance, float(np.sum(w * residual**2)), residual

    dof = len(y) - jacobian.shape[1]
    scatter = 0.0
    theta, covariance, chi2, residual = solve(0.0)
    if chi2 > dof:
        lo, hi = 0.0, float(np.max(np.abs(y))) + float(np.max(errors)) + 1.0
        for _ in range(200):  # chi^2 falls as the scatter grows: bisect chi^2 / dof = 1
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if solve(mid)[2] > dof else (lo, mid)
        scatter = hi
        theta, covariance, chi2, residual = solve(scatter)
    return theta, covariance, chi2, residual, scatter


def fit_optics(band: str, scas=OPTICS_SCAS) -> dict:
    """The joint fit of nlpsf's optics to the official PSF statistics of ``scas`` (see the module
    docstring): theta = (v [arcsec^2], ln s), its covariance, the intrinsic scatter, chi^2 and the
    data with their residuals. Linear: each statistic's log is linear in v (a probing blur of
    :data:`OPTICS_BLUR_PROBE_ARCSEC2`) and in ln s (the ``header`` rule against the ``official``)."""
    from nlpsf.sim import psfstats
    from nlpsf.sim import scene as scenes

    rows, y, jacobian, rounding = [], [], [], []
    for sca in scas:
        optical = psfstats.official_condition_psf(band, sca, OFFICIAL_SED, pupil_scale=presets.PUPIL_SCALE)
        ours = psfstats.statistics_of(optical, band, sca)
        blurred = psfstats.statistics_of(scenes.blur(optical, math.sqrt(OPTICS_BLUR_PROBE_ARCSEC2)), band, sca)
        header = psfstats.psf_statistics(band, sca, OFFICIAL_SED, pupil_scale=OPTICS_PUPIL_PROBE)
        log_scale = pupil_log_scale(band, sca, OPTICS_PUPIL_PROBE)
        for name, centring, theirs in _official_data(band, sca):
            value = getattr(ours[centring], name)
            y.append(math.log(theirs / value))
            jacobian.append(
                [
                    math.log(getattr(blurred[centring], name) / value) / OPTICS_BLUR_PROBE_ARCSEC2,
                    math.log(getattr(header[centring], name) / value) / log_scale,
                ]
            )
            rounding.append(OFFICIAL_ROUNDING[name] / math.sqrt(3) / theirs)
            rows.append({"sca": sca, "statistic": name, "centring": centring, "official": theirs, "nlpsf": value})
    y, jacobian, rounding = np.array(y), np.array(jacobian), np.array(rounding)
    theta, covariance, chi2, residual, scatter = fit_with_scatter(y, jacobian, rounding)
    dof = len(y) - jacobian.shape[1]
    for row, r in zip(rows, residual, strict=True):
        row["residual_log"] = float(r)
    return {
        "band": band,
        "scas": list(scas),
        "parameters": ["v_arcsec2", "ln_pupil_scale"],
        "theta": theta.tolist(),
        "covariance": covariance.tolist(),
        "sigma": np.sqrt(np.diag(covariance)).tolist(),
        "intrinsic_scatter_log": scatter,
        "chi2": chi2,
        "dof": dof,
        "data": rows,
        "sed": OFFICIAL_SED,
    }
