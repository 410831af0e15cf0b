"""Validity flags of a simulation: saturation, a non-monotonic NL, sampling, failed fits, float64 resolution."""

from __future__ import annotations

import math

import numpy as np

from nlpsf import defaults, roman
from nlpsf.flags import FlagCode, make
from nlpsf.sim import detector, moments

from .. import scene as scenes
from .config import METRICS
from .prepared import Scene, star_peak_electrons


def _validity_flags(
    scene: Scene, charge_scale: float, beta_map: np.ndarray, peak_electrons: np.ndarray, index=None, ramp_effect=None
) -> list[str]:
    """Plain-language warnings: saturation and a non-monotonic quadratic where the weight is.

    With a ramp, saturation is judged per resultant (``ramp_effect`` carries those flags) and the
    quadratic only has to be monotonic up to the charge of the last read each pixel's fit uses."""
    flags: list[str] = []
    config = scene.config
    over = peak_electrons > config.full_well_e
    star_peak = star_peak_electrons(scene, charge_scale)
    if ramp_effect is not None:
        flags += ramp_effect.flags
    elif star_peak > config.full_well_e:
        # Judged on the star (its brightest pixel over every sub-pixel centroid), so that the flag
        # does not depend on which centroids were drawn.
        flags.append(
            make(
                FlagCode.SATURATED,
                peak_e=star_peak,
                full_well_e=config.full_well_e,
                over=int(over.sum()),
                realizations=int(over.size),
            )
        )
    model = config.scene
    if ramp_effect is not None:
        worst = float(np.min(1.0 - 2.0 * np.max(beta_map) * ramp_effect.used_peak_e))
    elif not model.plain_detector:
        # dS/dQ of the polynomial at the charge the NL acts on (background, BFE, IPC-before included).
        pick = slice(None) if index is None else slice(index, index + 1)
        charge = scenes.charge_before_nl(scene.charge[pick], charge_scale, model, config.oversampling)
        b2 = beta_map if beta_map.size > 1 else float(beta_map.ravel()[0])
        slope = detector.response_slope(charge, b2, model.nl_coefficients)
        weighted = np.broadcast_to(scene.weighted_region[pick], np.broadcast_shapes(slope.shape, charge.shape))
        worst = float(np.where(weighted, slope, np.inf).min())
    elif beta_map.size == 1:
        peak = scene.weighted_peak_fraction if index is None else scene.weighted_peak_fraction[index]
        worst = float(np.min(1.0 - 2.0 * float(beta_map.ravel()[0]) * charge_scale * peak))
    else:
        weighted = scene.weighted_region[index]
        slope = 1.0 - 2.0 * beta_map * charge_scale * scene.stamps[index]
        worst = float(np.where(weighted, slope, np.inf).min())
    if worst <= 0:
        plain = model.plain_detector
        flags.append(
            make(
                FlagCode.NL_NOT_MONOTONIC,
                slope_name="1 - 2 beta Q" if plain else "dS/dQ",
                worst=worst,
                model="the quadratic model S = Q - beta Q^2" if plain else "the NL model",
            )
        )
    elif beta_map.size == 1 and beta_map.ravel()[0] < 0:
        flags.append(make(FlagCode.NEGATIVE_BETA))
    elif np.any(beta_map < 0):
        flags.append(make(FlagCode.NEGATIVE_PIXEL_BETAS, percent=float(100 * np.mean(beta_map < 0))))
    return flags


def _scene_flags(scene: Scene) -> list[str]:
    """Flags about the configuration itself: a grid too coarse for the PSF, a stamp too small for the weight."""
    config = scene.config
    flags = []
    # Nyquist: the effective PSF is band-limited at D / lambda; a fine pixel coarser than
    # lambda / (2 D) aliases it. Measured (linear slopes at m = 20, against N = 6): at q = 0.69-0.84
    # (Z087, Y106 at N = 2) the size slope is off by 0.5-0.7 % and e1 by 9-13 %; R062 at N = 2 (q = 0.49)
    # by 3.5 % and 10 %; at N = 1 the moments fail. At q >= 1 the error is below 0.02 %, but R062 at
    # N = 3 (q = 0.74) is 0.14 % and 1.6 % off.
    wavelength_nm = float(np.min(scene.psf.wavelengths_nm))
    nyquist_arcsec = wavelength_nm * 1e-9 / (2 * roman.DIAMETER_M) * 206264.80624709636
    q = nyquist_arcsec / config.grid.scale_arcsec
    if q < 1.0:
        needed = math.ceil(config.oversampling / q)
        flags.append(
            make(
                FlagCode.UNDERSAMPLED,
                pixel_mas=config.grid.scale_arcsec * 1e3,
                nyquist_mas=nyquist_arcsec * 1e3,
                wavelength_nm=wavelength_nm,
                q=q,
                needed=needed,
            )
        )
    # The weight window must fit in the stamp: a cut weight is a different estimator.
    n = config.stamp
    ok = scene.reference.ok
    if np.any(ok):
        params = scene.reference.parameters()[ok]
        cut = config.weight_cut_rho2 if math.isfinite(config.weight_cut_rho2) else defaults.GALSIM_WEIGHT_CUT_RHO2
        coords = np.arange(n) - (n - 1) / 2.0
        border = np.concatenate(
            [
                np.stack([coords, np.full(n, coords[0])], 1),
                np.stack([coords, np.full(n, coords[-1])], 1),
                np.stack([np.full(n, coords[0]), coords], 1),
                np.stack([np.full(n, coords[-1]), coords], 1),
            ]
        )
        x0, y0, mxx, mxy, myy = params.T
        det = mxx * myy - mxy**2
        dx = border[None, :, 0] - x0[:, None]
        dy = border[None, :, 1] - y0[:, None]
        rho2 = (myy[:, None] * dx**2 - 2 * mxy[:, None] * dx * dy + mxx[:, None] * dy**2) / det[:, None]
        inside = int(np.sum(rho2.min(axis=1) < cut))
        if inside:
            flags.append(make(FlagCode.STAMP_TOO_SMALL, cut=cut, n=n, inside=inside, fitted=int(ok.sum())))
    return flags


def _failure_flag(status: np.ndarray) -> list[str]:
    bad = status != moments.MomentStatus.OK
    if not np.any(bad):
        return []
    reasons = sorted({moments.STATUS_REASONS[moments.MomentStatus(s)] for s in status[bad]})
    rest = "no statistics are left" if np.all(bad) else "the statistics use the others"
    return [make(FlagCode.MOMENTS_FAILED, failed=int(bad.sum()), total=int(bad.size), reasons="; ".join(reasons), rest=rest)]


def _zero_flag(d_r: np.ndarray) -> list[str]:
    finite = d_r[np.isfinite(d_r)]
    if finite.size and np.all(finite == 0.0):
        return [make(FlagCode.NO_CHANGE)]
    return []


#: Smallest spread of a metric (Delta R / R, Delta e) that the Monte Carlo resolves: the differences of
#: two converged float64 fits carry ~1e-16 of noise, so a spread expected below 1e-13 is at least
#: 0.1 % noise (measured: at sigma_beta = 1e-20 the Monte Carlo gives 13368 per unit sigma_beta where
#: the linear response gives 2692).
MONTE_CARLO_SPREAD_FLOOR = 1e-13


def _noise_floor_flag(
    scene: Scene,
    charge_scale: float,
    beta: float,
    sigma_beta: float,
    settings: moments.MomentSettings,
    measured: np.ndarray,
    shape: np.ndarray | None = None,
) -> list[str]:
    """Flag a Monte Carlo scatter whose expected spread is below what float64 fits resolve.
    ``shape``: the NL pattern psi^2 (psi^2 c_2 after a ramp fit)."""
    stamp = scene.stamps[0]
    shape = stamp**2 if shape is None else shape
    reference0 = moments.select(scene.reference, slice(0, 1))
    if not reference0.ok[0]:
        return []
    gradient = moments.pixel_response(stamp[None], reference0, settings)[0]
    expected = np.sqrt(np.sum((gradient * shape) ** 2, axis=(1, 2))) * charge_scale * sigma_beta
    if np.all(expected >= MONTE_CARLO_SPREAD_FLOOR):
        return []
    return [
        make(
            FlagCode.BELOW_MONTE_CARLO_RESOLUTION,
            sigma_beta=sigma_beta,
            expected=", ".join(f"{n} {v:.2g}" for n, v in zip(METRICS, expected, strict=True)),
            floor=MONTE_CARLO_SPREAD_FLOOR,
            measured=", ".join(f"{v:.2g}" for v in measured),
            expected_spread=[float(v) for v in expected],
        )
    ]
