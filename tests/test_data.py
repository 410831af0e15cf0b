"""The shipped Roman data is what SOURCES.md says it is, and photometry follows from it."""

import hashlib
from importlib import resources
from pathlib import Path

import astropy.units as u
import numpy as np
import pytest
from astropy.constants import h

from nlpsf import photometry, roman
from nlpsf.checks import InputError

DATA = Path(str(resources.files("nlpsf") / "data"))


def test_data_files_match_recorded_checksums():
    recorded = {}
    for line in (DATA / "roman_sha256.txt").read_text().splitlines():
        digest, name = line.split()
        recorded[name] = digest
    files = sorted(p.name for p in (DATA / "roman").iterdir())
    assert files == sorted(recorded)
    for name in files:
        assert hashlib.sha256((DATA / "roman" / name).read_bytes()).hexdigest() == recorded[name], name


def test_every_sca_and_band_has_a_pupil_and_aberrations():
    for sca in range(1, 19):
        for band in ("H158", "F184"):
            p = roman.pupil(sca, band)
            assert p.transmission.shape == (512, 512)
            assert 0.3 < p.transmission.mean() < 0.8
            assert p.mask_kind == ("long" if band == "F184" else "short")
        ab = roman.aberrations(sca)
        assert ab.shape == (23,)
        assert np.all(ab[:4] == 0)
        assert 0 < np.abs(ab).max() < 0.2  # waves at 1293 nm: a well-corrected telescope


def test_galsim_pupil_scale_puts_farthest_open_pixel_on_the_disc():
    p = roman.pupil(18, "H158", scale_rule="galsim")
    n = p.transmission.shape[0]
    c = np.arange(n) - n // 2
    r = np.hypot(c[None, :], c[:, None])[p.transmission > 0].max() * p.scale_m
    assert r == pytest.approx(roman.DIAMETER_M / 2, rel=1e-12)
    header = roman.pupil(18, "H158", scale_rule="header")
    # The header scale is 44.9 um x 26.27 = 1.18 mm per unbinned pixel.
    assert header.scale_m == pytest.approx(4 * 1.1798e-3, rel=1e-3)


def test_electrons_follow_from_the_effective_area_by_hand():
    band = "J129"
    curve = roman.throughput(band)
    # Midpoint sum instead of the module's trapezoid, with the AB definition written out.
    lam = 0.5 * (curve.wavelength_nm[1:] + curve.wavelength_nm[:-1]) * u.nm
    area = 0.5 * (curve.effective_area_m2[1:] + curve.effective_area_m2[:-1]) * u.m**2
    dlam = np.diff(curve.wavelength_nm) * u.nm
    fnu = 3631 * u.Jy * 10 ** (-0.4 * 20.0)
    expected = (np.sum(fnu / (h * lam) * area * dlam) * 100 * u.s).to(u.dimensionless_unscaled).value
    got = photometry.magnitude_to_electrons(20.0, band, 100.0)
    assert got == pytest.approx(expected, rel=2e-3)


def test_magnitude_is_only_a_label_for_flux():
    for band in roman.BANDS:
        e = photometry.magnitude_to_electrons([18.3, 20.8], band, 168.1)
        assert e[0] / e[1] == pytest.approx(10, rel=1e-12)
        assert photometry.electrons_to_magnitude(e, band, 168.1) == pytest.approx([18.3, 20.8], abs=1e-12)
        # Exposure time scales the electrons and nothing else.
        assert photometry.magnitude_to_electrons(20.0, band, 2 * 168.1) == pytest.approx(2 * e[1] * 10 ** (0.4 * 0.8), rel=1e-12)


def test_effective_wavelengths_lie_inside_their_bands():
    for band in roman.BANDS:
        c = roman.throughput(band)
        assert c.blue_limit_nm < c.effective_wavelength_nm < c.red_limit_nm
    assert roman.throughput("H158").effective_wavelength_nm == pytest.approx(1579.1, abs=0.5)


@pytest.mark.parametrize("bad", [0, 19, -3, 1.5, "18", True, None])
def test_bad_sca_is_refused_by_name(bad):
    with pytest.raises(InputError, match="sca"):
        roman.check_sca(bad)


@pytest.mark.parametrize("bad", ["H159", "", None, 158])
def test_unknown_band_is_refused_by_name(bad):
    with pytest.raises(InputError, match="band"):
        roman.check_band(bad)


@pytest.mark.parametrize("exptime", [0, -1, float("nan"), float("inf")])
def test_bad_exposure_is_refused(exptime):
    with pytest.raises(InputError, match="exptime"):
        photometry.magnitude_to_electrons(20, "H158", exptime)


def test_negative_flux_has_no_magnitude():
    with pytest.raises(InputError, match="flux_electrons"):
        photometry.electrons_to_magnitude(-5.0, "H158", 168.1)
