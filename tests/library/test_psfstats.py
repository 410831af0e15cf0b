"""nlpsf's PSF statistics: the measurement methods on analytic cases, and the optics against the
official (independent, post-CDR) Roman PSF summary."""

import math

import numpy as np
import pytest

from nlpsf.sim import optics, psfstats, render


def test_fwhm_fit_returns_a_gaussian_s_fwhm():
    scale = 0.11 / 8
    c = (np.arange(64) - 31.5) * scale
    sigma = 0.05
    image = np.exp(-0.5 * (c[None, :] ** 2 + c[:, None] ** 2) / sigma**2)
    assert psfstats.fwhm_gaussian_fit(image, scale) == pytest.approx(2 * math.sqrt(2 * math.log(2)) * sigma, rel=1e-6)


def test_jitter_blur_of_a_gaussian_is_the_gaussian_with_the_variances_added():
    # A round Gaussian PSF given by its Fourier coefficients, blurred by the 8 mas jitter, drawn and
    # measured: its FWHM must be that of a Gaussian with sigma^2 = sigma0^2 + sigma_jitter^2.
    field, sigma0 = 4.0, 0.02
    f = optics.frequency_grid(field, 60.0)
    coefficients = np.exp(-2 * math.pi**2 * sigma0**2 * (f[:, None] ** 2 + f[None, :] ** 2)).astype(complex)
    psf = optics.EffectivePSF(None, field, f, coefficients, np.array([1000.0]), np.array([1.0]))
    blurred = psfstats._gaussian_blur(psf, psfstats.OFFICIAL_JITTER_FWHM_ARCSEC)
    grid = render.Grid(8, 64)
    image = render.draw(blurred, grid, np.zeros((1, 2)))[0]
    to_fwhm = 2 * math.sqrt(2 * math.log(2))
    expected = to_fwhm * math.hypot(sigma0, psfstats.OFFICIAL_JITTER_FWHM_ARCSEC / to_fwhm)
    assert psfstats.fwhm_gaussian_fit(image, grid.scale_arcsec) == pytest.approx(expected, rel=1e-6)


@pytest.mark.parametrize(("band", "sca"), [("H158", 18), ("Y106", 1)])
def test_optics_are_within_a_few_percent_of_the_official_psf_statistics(band, sca):
    """The official PSFs come from a later optical design (post-CDR) than GalSim's Cycle-9
    Zernikes; the issue expects agreement to a few percent in FWHM, N_eff and peak."""
    ours = psfstats.psf_statistics(band, sca)
    official = psfstats.official_statistics()
    for centring in psfstats.CENTRINGS:
        theirs = official[(sca, band, centring)]
        assert ours[centring].fwhm_arcsec == pytest.approx(theirs.fwhm_arcsec, rel=0.06)
        assert ours[centring].n_eff_pixels == pytest.approx(theirs.n_eff_pixels, rel=0.06)
        assert ours[centring].peak_fraction == pytest.approx(theirs.peak_fraction, rel=0.06)
        # The flux inside the 7" image (set by the PSF's far wings) agrees to a few 1e-3.
        assert ours[centring].total_flux == pytest.approx(theirs.total_flux, abs=3e-3)
