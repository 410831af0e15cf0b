"""Optics and rendering against analytic results: Zernikes, the Airy pattern, its OTF, shifts."""

import itertools
import math

import numpy as np
import pytest
from scipy.special import j1

from nlpsf import roman
from nlpsf.checks import InputError
from nlpsf.sim import optics, render

from ..conftest import requires_galsim


def circular_pupil(n_across: int = 400, diameter_m: float = 2.36) -> roman.Pupil:
    n = n_across + 8
    scale = diameter_m / n_across
    c = (np.arange(n) - n // 2) * scale
    r = np.hypot(c[None, :], c[:, None])
    return roman.Pupil(0, "test", (r <= diameter_m / 2).astype(float), scale)


def test_noll_indices_match_the_noll_1976_table():
    expected = {
        1: (0, 0),
        2: (1, 1),
        3: (1, -1),
        4: (2, 0),
        5: (2, -2),
        6: (2, 2),
        7: (3, -1),
        8: (3, 1),
        9: (3, -3),
        10: (3, 3),
        11: (4, 0),
        12: (4, 2),
        13: (4, -2),
        14: (4, 4),
        15: (4, -4),
        22: (6, 0),
    }
    for j, nm in expected.items():
        assert optics.noll_to_nm(j) == nm


def test_low_order_zernikes_are_the_textbook_polynomials():
    rng = np.random.default_rng(0)
    rho, theta = rng.random(50), rng.random(50) * 2 * np.pi
    assert optics.zernike(4, rho, theta) == pytest.approx(math.sqrt(3) * (2 * rho**2 - 1))
    assert optics.zernike(5, rho, theta) == pytest.approx(math.sqrt(6) * rho**2 * np.sin(2 * theta))
    assert optics.zernike(6, rho, theta) == pytest.approx(math.sqrt(6) * rho**2 * np.cos(2 * theta))
    assert optics.zernike(8, rho, theta) == pytest.approx(math.sqrt(8) * (3 * rho**3 - 2 * rho) * np.cos(theta))
    assert optics.zernike(11, rho, theta) == pytest.approx(math.sqrt(5) * (6 * rho**4 - 6 * rho**2 + 1))


def test_zernikes_are_orthonormal_on_the_unit_disc():
    n = 801
    x = np.linspace(-1, 1, n)
    xx, yy = np.meshgrid(x, x)
    rho, theta = np.hypot(xx, yy), np.arctan2(yy, xx)
    inside = rho <= 1
    basis = np.array([optics.zernike(j, rho[inside], theta[inside]) for j in range(1, 23)])
    gram = basis @ basis.T / inside.sum()
    assert np.abs(gram - np.eye(22)).max() < 0.01


def test_unaberrated_circular_pupil_gives_the_airy_pattern():
    pupil = circular_pupil()
    wavelength = 1500.0
    lam_over_d = wavelength * 1e-9 / 2.36 * optics.ARCSEC_PER_RADIAN
    theta = np.linspace(-4, 4, 81) * lam_over_d
    psf = optics.psf_intensity(pupil, np.zeros(23), wavelength, theta)
    area = pupil.transmission.sum() * pupil.scale_m**2
    # Peak: A / lambda^2 per steradian for a unit-flux PSF.
    peak = area / (wavelength * 1e-9) ** 2 / optics.ARCSEC_PER_RADIAN**2
    x = np.pi * np.hypot(theta[None, :], theta[:, None]) / lam_over_d * np.sqrt(area / (np.pi * 1.18**2))
    with np.errstate(invalid="ignore", divide="ignore"):
        airy = np.where(x > 0, (2 * j1(x) / x) ** 2, 1.0)
    assert psf[40, 40] == pytest.approx(peak, rel=1e-12)
    assert np.abs(psf / peak - airy).max() < 2e-3


def test_otf_of_a_circular_pupil_is_the_analytic_one():
    pupil = circular_pupil(300)
    wavelength = 1500.0
    cutoff = 2.36 / (wavelength * 1e-9) / optics.ARCSEC_PER_RADIAN
    field = 60 / cutoff  # 60 lambda/D: the Airy wings beyond it carry ~1 % of the flux
    f = np.linspace(0.05, 0.95, 10) * cutoff
    otf = optics._intensity_coefficients(pupil, np.zeros(23), wavelength, np.concatenate([[0.0], f]), field)
    nu = f / cutoff
    analytic = 2 / np.pi * (np.arccos(nu) - nu * np.sqrt(1 - nu**2))
    measured = otf[0, 1:].real
    assert np.abs(measured - analytic).max() < 4e-3
    assert np.abs(otf[0, 1:].imag).max() < 1e-12  # a centred symmetric PSF has a real OTF


def test_flux_in_field_grows_towards_one():
    cfg = optics.OpticsConfig("J129", 5)
    fractions = [optics.effective_psf(cfg, f).flux_in_field for f in (2.0, 4.0, 8.0, 16.0)]
    assert all(a < b for a, b in itertools.pairwise(fractions))
    assert 0.97 < fractions[-1] < 1.0


def test_integer_pixel_shift_is_exactly_a_translation():
    grid = render.Grid(3, 64)
    psf = optics.effective_psf(optics.OpticsConfig("Y106", 3), grid.field_arcsec())
    stamps = render.draw(psf, grid, np.array([[0.3, -0.2], [1.3, -0.2], [0.3, 1.8]]))
    assert np.abs(stamps[1, 10:-10, 11:-10] - stamps[0, 10:-10, 10:-11]).max() < 1e-13 * stamps.max()
    assert np.abs(stamps[2, 12:-10, 10:-10] - stamps[0, 10:-12, 10:-10]).max() < 1e-13 * stamps.max()


def test_oversampled_stamp_sums_to_the_flux_it_covers():
    # A wide stamp at N=2 holds nearly all of the flux kept in the field.
    grid = render.Grid(2, 160)
    psf = optics.effective_psf(optics.OpticsConfig("H158", 18), grid.field_arcsec())
    stamp = render.draw(psf, grid, np.zeros((1, 2)))[0]
    assert stamp.sum() == pytest.approx(psf.flux_in_field, rel=2e-2)
    assert stamp.sum() < psf.flux_in_field


def test_polychromatic_psf_is_a_weighted_sum_of_monochromatic_ones():
    cfg = optics.OpticsConfig("F184", 18, n_wavelengths=3)
    wavelengths, weights = cfg.wavelengths_and_weights()
    assert weights.sum() == pytest.approx(1.0)
    curve = roman.throughput("F184", sca=18)
    assert curve.blue_limit_nm < wavelengths[0] < wavelengths[-1] < curve.red_limit_nm
    poly = optics.effective_psf(cfg, 5.0)
    parts = [optics.effective_psf(optics.OpticsConfig("F184", 18, wavelength_nm=w), 5.0) for w in wavelengths]
    # Each monochromatic grid stops at its own cut-off (the reddest is smallest): compare there.
    n = parts[-1].frequencies.size

    def centre(coefficients):
        lo = (coefficients.shape[0] - n) // 2
        return coefficients[lo : lo + n, lo : lo + n]

    combined = sum(w * centre(p.coefficients) for w, p in zip(weights, parts, strict=True))
    assert np.abs(centre(poly.coefficients) - combined).max() < 1e-12 * np.abs(combined).max()


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"band": "U123"}, "band"),
        ({"sca": 0}, "sca"),
        ({"n_wavelengths": 0}, "n_wavelengths"),
        ({"wavelength_nm": float("nan")}, "wavelength_nm"),
        ({"pupil_bin": 3}, "pupil_bin"),
    ],
)
def test_bad_optics_arguments_are_named(kwargs, name):
    with pytest.raises(InputError, match=name):
        optics.effective_psf(optics.OpticsConfig(**kwargs), 5.0)


@requires_galsim
def test_zernikes_agree_with_galsim():
    import galsim.zernike

    rng = np.random.default_rng(3)
    u, v = rng.uniform(-1.1, 1.1, (2, 200))
    coefficients = np.zeros(23)
    coefficients[4:] = rng.normal(0, 0.05, 19)
    ours = optics.wavefront_waves(coefficients, u, v, 1.18)
    theirs = galsim.zernike.Zernike(coefficients, R_outer=1.18)(u, v)
    assert ours == pytest.approx(theirs, abs=1e-12)


@pytest.mark.slow
@requires_galsim
@pytest.mark.parametrize(("band", "sca"), [("H158", 18), ("F184", 1), ("Y106", 9)])
def test_rendered_psf_matches_galsim_at_converged_pupil_sampling(band, sca):
    """Same pupil, aberrations and wavelength; GalSim with the pupil plane padded 4x (converged)."""
    import galsim

    from nlpsf.sim import reference

    grid = render.Grid(3, 64)
    offsets = np.array([[0.0, 0.0], [0.37, -1.21]])
    config = optics.OpticsConfig(band, sca, throughput="galsim-2021")
    ours = render.draw(optics.effective_psf(config, grid.field_arcsec()), grid, offsets)
    wavelength = roman.throughput(band, sca=sca, source="galsim-2021").effective_wavelength_nm
    psf = reference._get_psf_oversampled(sca, band, wavelength, 4.0)
    effective = galsim.Convolve(psf, galsim.Pixel(0.11))
    for k, offset in enumerate(offsets):
        theirs = effective.drawImage(
            nx=64, ny=64, scale=grid.scale_arcsec, method="no_pixel", offset=tuple(offset), dtype=float
        ).array
        assert np.abs(ours[k] - theirs).max() < 5e-5 * theirs.max()


def test_polychromatic_weights_follow_the_sca_s_own_throughput_and_the_sed():
    from nlpsf.sim import psfstats

    def mean_wavelength(wavelengths, weights):
        return float(np.sum(wavelengths * weights))

    # Photon-weighted mean wavelength of a flat-f_nu star: integral A lambda^0 / integral A lambda^-1,
    # straight from the SCA's effective-area curve.
    for sca in (1, 18):
        curve = roman.throughput("W146", sca=sca, source="roman-2024")
        w, a = curve.wavelength_nm, curve.effective_area_m2
        expected = np.trapezoid(a, w) / np.trapezoid(a / w, w)
        got = mean_wavelength(*optics.OpticsConfig("W146", sca, n_wavelengths=8).wavelengths_and_weights())
        assert got == pytest.approx(expected, rel=1e-4)
    # A K0V star falls faster than flat f_nu in the near infrared: its photons are bluer.
    curve = roman.throughput("W146", sca=18, source="roman-2024")
    flat = mean_wavelength(*optics.band_wavelengths_and_weights(curve, 8))
    k0v = mean_wavelength(*optics.band_wavelengths_and_weights(curve, 8, psfstats.blackbody_flambda(5270.0)))
    assert k0v < flat - 20.0


def _brute_force_peak(psf: optics.EffectivePSF, oversampling: int, steps: int) -> tuple[float, np.ndarray]:
    """The brightest fine pixel over a dense scan of sub-pixel centroids (three passes: one fine
    pixel at 1/steps, then twice the best cell's neighbourhood again), rendered as a simulation renders."""
    grid = render.Grid(oversampling, 16)
    best, centre, width = -np.inf, np.zeros(2), 1.0
    for _ in range(3):
        axis = (
            centre[0] + np.linspace(-width / 2, width / 2, steps + 1),
            centre[1] + np.linspace(-width / 2, width / 2, steps + 1),
        )
        offsets = np.array([(x, y) for x in axis[0] for y in axis[1]])
        stamps = render.draw(psf, grid, offsets)
        k = int(np.argmax(stamps.max(axis=(1, 2))))
        best, centre, width = float(stamps[k].max()), offsets[k], 2 * width / steps
    return best, centre


@pytest.mark.parametrize(("band", "sca"), [("H158", 18), ("F184", 1), ("Y106", 7)])
def test_peak_value_is_the_brightest_pixel_over_a_dense_centroid_scan(band, sca):
    grid = render.Grid(3, 96)
    psf = optics.effective_psf(optics.OpticsConfig(band, sca), grid.field_arcsec())
    value, _position = optics.peak_value(psf)
    analytic = value * grid.scale_arcsec**2
    brute, _ = _brute_force_peak(psf, 3, 16)
    # A scan can only fall short of the true maximum, by ~ (cell / 2)^2 / (2 sigma^2) (1e-7 at most here).
    assert analytic >= brute * (1 - 1e-12)
    assert analytic == pytest.approx(brute, rel=3e-7)


def test_peak_value_follows_a_known_shift_and_the_airy_peak():
    # Unaberrated circular pupil, no pixel: the peak is A / lambda^2 per steradian, on axis; a
    # phase ramp on the coefficients moves it by exactly that shift.
    pupil = circular_pupil(200)
    wavelength = 1200.0
    psf = optics.psf_from_pupil(pupil, np.zeros(23), [wavelength], [1.0], 4.0, pixel_response=False)
    value, (x, y) = optics.peak_value(psf)
    area = pupil.transmission.sum() * pupil.scale_m**2
    airy = area / (wavelength * 1e-9 * optics.ARCSEC_PER_RADIAN) ** 2
    assert value == pytest.approx(airy, rel=2e-3)  # the field cut leaves the core
    assert abs(x) < 1e-9 and abs(y) < 1e-9
    dx, dy = 0.013, -0.021
    f = psf.frequencies
    phase = np.exp(-2j * np.pi * (dy * f[:, None] + dx * f[None, :]))
    shifted = optics.EffectivePSF(None, psf.field_arcsec, f, psf.coefficients * phase, psf.wavelengths_nm, psf.weights)
    value2, (x2, y2) = optics.peak_value(shifted)
    assert value2 == pytest.approx(value, rel=1e-10)
    assert (x2, y2) == pytest.approx((dx, dy), abs=1e-9)
