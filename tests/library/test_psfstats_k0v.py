"""The official-condition PSF's star is the official statistics' own K0V (the vendored Pickles
spectrum), checked against the spectrum file read and integrated here, independently of nlpsf's
SED reader and band binning; the 5270 K blackbody stand-in stays selectable."""

import math
from importlib import resources

import numpy as np
import pytest

from nlpsf import roman
from nlpsf.checks import InputError
from nlpsf.sim import optics, psfstats

# Planck's law by hand (h c / k in nm K), f_lambda up to a constant.
HC_OVER_K_NM_K = 1.438777e7


def _mean_wavelength(band: str, sca: int, flambda) -> float:
    """Photon-weighted mean wavelength [nm] over the band: photons ~ A_eff f_lambda lambda."""
    curve = roman.throughput(band, sca=sca, source=roman.DEFAULT_THROUGHPUT)
    wave = np.linspace(curve.blue_limit_nm, curve.red_limit_nm, 20001)
    photons = np.interp(wave, curve.wavelength_nm, curve.effective_area_m2) * flambda(wave) * wave
    return float(np.trapezoid(photons * wave, wave) / np.trapezoid(photons, wave))


def _pickles_k0v(wave_nm):
    with (resources.files("nlpsf") / "data" / "seds" / "pickles_uk_31.txt").open() as handle:
        rows = np.loadtxt(handle, comments="#")
    return np.interp(wave_nm, rows[:, 0] / 10.0, rows[:, 1])  # the file tabulates angstrom


def _blackbody(wave_nm, temperature=5270.0):
    return wave_nm**-5.0 / np.expm1(HC_OVER_K_NM_K / (wave_nm * temperature))


def _psf_mean_wavelength(band, sca, sed):
    curve = roman.throughput(band, sca=sca, source=roman.DEFAULT_THROUGHPUT)
    wavelengths, weights = optics.band_wavelengths_and_weights(curve, 10, psfstats.sed_flambda(sed, curve))
    return float(np.sum(wavelengths * weights))


@pytest.mark.parametrize("band", ["W146", "H158", "K213"])
def test_the_official_k0v_is_the_vendored_spectrum_not_the_blackbody(band):
    k0v = _mean_wavelength(band, 18, _pickles_k0v)
    standin = _mean_wavelength(band, 18, _blackbody)
    assert _psf_mean_wavelength(band, 18, "K0V") == pytest.approx(k0v, rel=2e-4)
    assert _psf_mean_wavelength(band, 18, psfstats.K0V_STANDIN) == pytest.approx(standin, rel=2e-4)
    # The two stars differ by more than that tolerance in these bands (so the check can tell them apart).
    assert abs(k0v / standin - 1.0) > 1e-3


@pytest.mark.slow
def test_the_official_condition_psf_integrates_the_k0v_by_default():
    optical = psfstats.official_condition_psf("W146", 18)
    mean = float(np.sum(optical.wavelengths_nm * optical.weights))
    assert mean == pytest.approx(_mean_wavelength("W146", 18, _pickles_k0v), rel=2e-4)
    assert psfstats.width_gap("W146", 18)["sed"] == "K0V"


def test_an_unknown_star_is_refused():
    with pytest.raises(InputError):
        psfstats.official_condition_psf("H158", 18, sed="blackbody:4000")
    assert math.isclose(psfstats.K0V_TEMPERATURE_K, 5270.0) and psfstats.K0V_STANDIN == "blackbody:5270"
