"""nlpsf's optical model against the official Roman PSF summary statistics.

STScI's ``SummaryPSFstats_{center,corner}.ecsv`` (roman-technical-information 1.5.0, post-CDR
optical design, WebbPSF/STPSF) give, for SCA 1 and 18 at the detector centre in every filter, a
K0V star sampled over the band and 8 mas FWHM Gaussian pointing jitter:

- FWHM [arcsec] of the 8x oversampled PSF (STPSF's ``measure_fwhm``: a Gaussian of fixed centre
  fitted to the pixels above 10 % of the peak);
- N_eff = 1 / sum(p_i^2) over native pixels, and the peak native-pixel value, with p normalised
  to the flux entering the telescope (the ~7" images hold 97-99 % of it);
- the flux inside the image, ``tot_flux``.

:func:`psf_statistics` computes the same four numbers from nlpsf's optics (GalSim's Cycle-9
Zernikes and pupil masks) under the same conditions, so the two optical models can be compared.
The K0V star is the vendored Pickles (1998) K0V spectrum (``nlpsf.roman.seds``, ``--sed k0v``), the
star the official statistics state and the Roman default's star (``roman_default``).
``sed="blackbody:5270"`` is the 5270 K blackbody stand-in (Pecaut & Mamajek's K0V effective
temperature) used before the spectrum was vendored; it keeps ``nlpsf/data/optical_model_uncertainty.json``
(the paper scene's optical-model part) reproducible. Against the spectrum it moves N_eff by up to
2.3 % (W146: the blackbody lacks the K dwarf's H- bump near 1.6 um), ``flat`` is flat f_nu.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from functools import cache, partial
from typing import Any

import numpy as np
from scipy.optimize import curve_fit

from nlpsf import roman
from nlpsf.checks import InputError
from nlpsf.roman import seds
from nlpsf.sim import optics, render
from nlpsf.sim import scene as scenes

#: K0V effective temperature [K] (Pecaut & Mamajek 2013) for the blackbody stand-in SED.
K0V_TEMPERATURE_K = 5270.0
#: The blackbody stand-in for the K0V star, by its scene name (the Roman default's star before
#: the Pickles spectrum was vendored; the paper scene's optical-model part was measured with it).
K0V_STANDIN = f"blackbody:{K0V_TEMPERATURE_K:g}"
#: The official PSFs' pointing jitter: Gaussian of 8 mas FWHM.
OFFICIAL_JITTER_FWHM_ARCSEC = 0.008
#: The official images: ~7 arcsec square; 64 native pixels is 7.04".
OFFICIAL_IMAGE_PIXELS = 64
#: STPSF's measure_fwhm: pixels above this fraction of the peak enter the Gaussian fit.
FWHM_FIT_THRESHOLD = 0.1
CENTRINGS = ("center", "corner")
#: The SEDs the official-condition PSF takes: "K0V" (the official statistics' star, the vendored
#: Pickles K0V), the 5270 K blackbody stand-in, flat f_nu.
SEDS = ("K0V", K0V_STANDIN, "flat")


@dataclass(frozen=True)
class PSFStatistics:
    band: str
    sca: int
    centring: str
    fwhm_arcsec: float
    n_eff_pixels: float
    peak_fraction: float
    total_flux: float


def blackbody_flambda(temperature_k: float):
    """f_lambda of a blackbody (arbitrary normalisation) as a function of wavelength in nm
    (``scene.planck_flambda`` at this temperature)."""
    return partial(scenes.planck_flambda, temperature_k=temperature_k)


def sed_flambda(sed: str, curve: roman.Throughput):
    """f_lambda of one of :data:`SEDS` as a function of wavelength [nm] (None: flat f_nu)."""
    if sed == "K0V":
        return optics.tabulated_sed(curve, seds.table("k0v"))
    if sed == K0V_STANDIN:
        return blackbody_flambda(K0V_TEMPERATURE_K)
    if sed == "flat":
        return None
    raise InputError("sed", f"must be one of {', '.join(SEDS)}, got {sed!r}")


@cache
def official_statistics() -> dict[tuple[int, str, str], PSFStatistics]:
    """The official table, keyed by (sca, band, centring). Bands use nlpsf's names."""
    out = {}
    band_of = {v: k for k, v in roman.OFFICIAL_FILTER_NAMES.items()}
    for centring in CENTRINGS:
        # The files' YAML header does not parse as ECSV; the body is plain CSV.
        path = roman.official_data_dir() / f"SummaryPSFstats_{centring}.ecsv"
        rows = [line for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
        names = [n.strip() for n in rows[0].split(",")]
        for line in rows[1:]:
            values = dict(zip(names, (v.strip() for v in line.split(",")), strict=True))
            band = band_of[values["Filter"]]
            sca = int(values["SCA"])
            out[(sca, band, centring)] = PSFStatistics(
                band=band,
                sca=sca,
                centring=centring,
                fwhm_arcsec=float(values["FWHM"]),
                n_eff_pixels=float(values["N_Eff_Pix"]),
                peak_fraction=float(values["peak_flux"]),
                total_flux=float(values["tot_flux"]),
            )
    return out


def _gaussian_blur(psf: optics.EffectivePSF, fwhm_arcsec: float) -> optics.EffectivePSF:
    """The PSF convolved with a round Gaussian of this FWHM (``scene.blur``, which takes the rms)."""
    return scenes.blur(psf, fwhm_arcsec / (2.0 * math.sqrt(2.0 * math.log(2.0))))


def fwhm_gaussian_fit(image: np.ndarray, scale_arcsec: float, threshold: float = FWHM_FIT_THRESHOLD) -> float:
    """FWHM of a centred PSF image as STPSF measures it: a Gaussian of fixed centre (the image
    centre) fitted to the radii and values of the pixels above ``threshold`` of the peak."""
    image = image / image.max()
    n = image.shape[0]
    c = (np.arange(n) - (n - 1) / 2) * scale_arcsec
    r = np.hypot(c[None, :], c[:, None])
    keep = image > threshold
    (_amplitude, sigma), _ = curve_fit(
        lambda x, a, s: a * np.exp(-0.5 * (x / s) ** 2), r[keep], image[keep], p0=(1.0, 0.4 * r[keep].max())
    )
    return float(2.0 * math.sqrt(2.0 * math.log(2.0)) * abs(sigma))


def psf_statistics(band: str, sca: int, sed: str = "K0V", **conditions: Any) -> dict[str, PSFStatistics]:
    """nlpsf's PSF statistics under the official conditions, for both centrings (``conditions``:
    :func:`official_condition_psf`'s wavelengths, jitter, throughput and pupil rule)."""
    return statistics_of(official_condition_psf(band, sca, sed, **conditions), band, sca)


def official_condition_psf(
    band: str,
    sca: int,
    sed: str = "K0V",
    n_wavelengths: int = 10,
    jitter_fwhm_arcsec: float = OFFICIAL_JITTER_FWHM_ARCSEC,
    throughput: str = roman.DEFAULT_THROUGHPUT,
    pupil_scale: str = "galsim",
) -> optics.EffectivePSF:
    """nlpsf's optical PSF (no pixel) under the official conditions, on the official image field."""
    band, sca = roman.check_band(band), roman.check_sca(sca)
    curve = roman.throughput(band, sca=sca, source=throughput)
    wavelengths, weights = optics.band_wavelengths_and_weights(curve, n_wavelengths, sed_flambda(sed, curve))
    pupil = roman.pupil(sca, band, 4, pupil_scale)
    aberrations = roman.aberrations(sca)
    field = OFFICIAL_IMAGE_PIXELS * roman.PIXEL_SCALE_ARCSEC
    return _gaussian_blur(
        optics.psf_from_pupil(pupil, aberrations, wavelengths, weights, field, pixel_response=False), jitter_fwhm_arcsec
    )


def statistics_of(optical: optics.EffectivePSF, band: str, sca: int) -> dict[str, PSFStatistics]:
    """FWHM, N_eff, peak and flux of an optical PSF as the official table states them."""
    wavelengths, weights, field = optical.wavelengths_nm, optical.weights, optical.field_arcsec
    # The FWHM of the 8x oversampled optical PSF, centred on the image as STPSF's is.
    fine = render.Grid(8, 64)
    fwhm = fwhm_gaussian_fit(render.draw(optical, fine, np.zeros((1, 2)))[0], fine.scale_arcsec)
    # Native pixels: the pixel-convolved PSF sampled at pixel centres, centred on a pixel corner
    # (zero offset on an even stamp) or on a pixel centre (half a pixel off).
    pixel = np.sinc(roman.PIXEL_SCALE_ARCSEC * optical.frequencies)
    effective = optics.EffectivePSF(
        None, field, optical.frequencies, optical.coefficients * pixel[:, None] * pixel[None, :], wavelengths, weights
    )
    native = render.Grid(1, OFFICIAL_IMAGE_PIXELS)
    images = render.draw(effective, native, np.array([[0.5, 0.5], [0.0, 0.0]]))
    out = {}
    for centring, image in zip(CENTRINGS, images, strict=True):
        out[centring] = PSFStatistics(
            band=band,
            sca=sca,
            centring=centring,
            fwhm_arcsec=fwhm,
            n_eff_pixels=float(1.0 / np.sum(image**2)),
            peak_fraction=float(image.max()),
            total_flux=float(image.sum()),
        )
    return out


#: The probing blur of :func:`width_gap` [arcsec rms]: about the size of the gaps it measures.
WIDTH_PROBE_SIGMA_ARCSEC = 0.015


def width_gap(band: str, sca: int, pupil_scale: str = "official", sed: str = "K0V") -> dict:
    """How far nlpsf's PSF width is from the official statistics, as a Gaussian variance.

    ``n_eff_variance_arcsec2``: the variance of a Gaussian that, convolved with nlpsf's PSF (negative:
    removed from it), brings its N_eff (geometric mean of the two centrings) to the official one,
    linear in the variance from one probing blur (:data:`WIDTH_PROBE_SIGMA_ARCSEC`);
    ``fwhm_variance_arcsec2``: the same for the FWHM, (FWHM_off^2 - FWHM^2) / (8 ln 2) as for a
    Gaussian; ``variance_arcsec2``: the larger in modulus (the size residual the model must be
    perturbed by). ``sed``: the star (default the official statistics' K0V; :data:`SEDS`). Only SCAs
    with official statistics (1 and 18)."""
    official = official_statistics()
    if (sca, band, "center") not in official:
        raise InputError("sca", f"the official statistics cover SCA {sorted({k[0] for k in official})}, got {sca}")
    optical = official_condition_psf(band, sca, sed, pupil_scale=pupil_scale)
    ours = statistics_of(optical, band, sca)
    probe = statistics_of(scenes.blur(optical, WIDTH_PROBE_SIGMA_ARCSEC), band, sca)

    def mean_n_eff(stats: dict[str, PSFStatistics]) -> float:
        return math.sqrt(stats["center"].n_eff_pixels * stats["corner"].n_eff_pixels)

    theirs_n = math.sqrt(official[(sca, band, "center")].n_eff_pixels * official[(sca, band, "corner")].n_eff_pixels)
    n0, n1 = mean_n_eff(ours), mean_n_eff(probe)
    n_variance = WIDTH_PROBE_SIGMA_ARCSEC**2 * math.log(theirs_n / n0) / math.log(n1 / n0)
    f0, f_off = ours["center"].fwhm_arcsec, official[(sca, band, "center")].fwhm_arcsec
    f_variance = (f_off**2 - f0**2) / (8.0 * math.log(2.0))
    return {
        "band": band,
        "sca": sca,
        "pupil_scale": pupil_scale,
        "sed": sed,
        "n_eff_ratio": n0 / theirs_n,
        "fwhm_ratio": f0 / f_off,
        "n_eff_variance_arcsec2": n_variance,
        "fwhm_variance_arcsec2": f_variance,
        "variance_arcsec2": max(n_variance, f_variance, key=abs),
    }


def as_dict(stats: PSFStatistics) -> dict:
    return asdict(stats)
