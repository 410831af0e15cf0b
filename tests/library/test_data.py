"""The shipped Roman data is what SOURCES.md says it is, and photometry follows from it."""

import gzip
import hashlib
from importlib import resources
from pathlib import Path

import astropy.units as u
import numpy as np
import pytest
from astropy.constants import h
from astropy.table import Table

from nlpsf import roman
from nlpsf.checks import InputError
from nlpsf.roman import photometry
from nlpsf.sim import experiment

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


_OFFICIAL_MASKS = {"H158": "pupilmask_obsc_skinny_mask.ecsv", "F184": "pupilmask_obsc_F184_mask.ecsv"}


def test_official_pupil_mask_copies_are_unchanged():
    folder = DATA / "rti_pupil_masks"
    for line in (folder / "sha256.txt").read_text().splitlines():
        digest, name = line.split()
        assert hashlib.sha256((folder / name).read_bytes()).hexdigest() == digest, name
    assert sorted(p.name for p in folder.glob("*.ecsv")) == sorted(_OFFICIAL_MASKS.values())


@pytest.mark.parametrize("band", sorted(_OFFICIAL_MASKS))
def test_official_pupil_scale_gives_every_sca_the_official_clear_area(band):
    """The truth is the official table, read here with astropy's ECSV reader (nlpsf parses it with
    numpy). The area is measured on what the optics compute with: the open pixels of the pupil
    function the PSF is drawn from, and, independently of any pixel count, the on-axis intensity
    of the aberration-free PSF, which for unit flux is A / lambda^2 (Parseval)."""
    from nlpsf.sim import optics

    table = Table.read(DATA / "rti_pupil_masks" / _OFFICIAL_MASKS[band], format="ascii.ecsv")
    official = {int(s): float(a) for s, a in zip(table["sca"], table["exit_pupil_clear"], strict=True) if str(s).isdigit()}
    assert sorted(official) == list(range(1, 19))
    wavelength_nm = 1500.0
    for sca, area in official.items():
        pupil = roman.pupil(sca, band, scale_rule="official")
        transmission, _u, _v = optics._clear_aperture(pupil)
        assert transmission.sum() * pupil.scale_m**2 == pytest.approx(area, rel=5e-3), sca
        peak = optics.psf_intensity(pupil, np.zeros(23), wavelength_nm, np.zeros(1))[0, 0]  # per arcsec^2
        from_peak = peak * (wavelength_nm * 1e-9 * optics.ARCSEC_PER_RADIAN) ** 2
        assert from_peak == pytest.approx(area, rel=5e-3), sca


def test_neither_older_pupil_scale_rule_gives_the_official_area_on_both_masks():
    # Why the official rule exists: measured on the binned masks, galsim is 8 % short of the
    # skinny mask's area on SCA 18, header 3-6 % high on the F184 mask of SCAs 4, 7, 9, 18.
    def ratio(sca, band, rule):
        p = roman.pupil(sca, band, scale_rule=rule)
        return p.transmission.sum() * p.scale_m**2 / roman.official_clear_area_m2(sca, band)

    assert ratio(18, "H158", "galsim") < 0.93
    assert ratio(18, "F184", "header") > 1.04


def test_official_files_match_the_published_package():
    # sha256.txt holds the digests of the files in roman-technical-information 1.5.0 (the same
    # ones its wheel's RECORD lists); the effective areas are stored gzipped, so compare contents.
    folder = DATA / "roman_technical_information"
    for line in (folder / "sha256.txt").read_text().splitlines():
        digest, upstream = line.split()
        name = upstream.rsplit("/", 1)[-1]
        path = folder / name if (folder / name).exists() else folder / f"{name}.gz"
        content = gzip.decompress(path.read_bytes()) if path.suffix == ".gz" else path.read_bytes()
        assert hashlib.sha256(content).hexdigest() == digest, name


def _official_zero_points() -> dict[tuple[int, str], float]:
    table = Table.read(DATA / "roman_technical_information" / "Roman_zeropoints_20240301.ecsv", format="ascii.ecsv")
    official = {v: k for k, v in roman.OFFICIAL_FILTER_NAMES.items()}
    return {
        (int(str(d)[3:]), official[str(f)]): float(z)
        for d, f, z in zip(table["detector"], table["element"], table["ABMag"], strict=True)
    }


def test_electrons_reproduce_the_official_zero_points_on_every_sca_and_band():
    """The official AB zero point of a detector and filter is the magnitude that gives one count
    per second (synphot 1.4 ``unit_response`` on the same effective-area curves); nlpsf's electrons
    for that magnitude, per second, must be one, on all 18 x 8."""
    official = _official_zero_points()
    assert len(official) == 144
    residuals = []
    for (sca, band), zp in official.items():
        rate = photometry.magnitude_to_electrons(zp, band, 1.0, sca=sca, throughput="roman-2024")
        residuals.append(2.5 * np.log10(rate))
    assert np.max(np.abs(residuals)) < 1e-3


def test_official_throughput_differs_by_sca_and_galsim_2021_does_not():
    new = [photometry.zero_point("H158", sca=s, throughput="roman-2024") for s in (1, 18)]
    old = [photometry.zero_point("H158", sca=s, throughput="galsim-2021") for s in (1, 18)]
    assert old[0] == old[1]
    # The numbers: SCA 1 is about 0.13 mag fainter than SCA 18; GalSim's 2021 curve is
    # 0.054 mag more sensitive than the official SCA 18 one in H158.
    assert new[1] - new[0] == pytest.approx(0.13, abs=0.02)
    assert old[1] - new[1] == pytest.approx(0.054, abs=0.002)


@pytest.mark.parametrize("throughput", roman.THROUGHPUTS)
def test_electrons_follow_from_the_effective_area_by_hand(throughput):
    band, sca = "J129", 7
    curve = roman.throughput(band, sca=sca, source=throughput)
    # Midpoint sum instead of the module's trapezoid, with the AB definition written out:
    # 3631 Jy rounds the 48.60 of the definition m = -2.5 log10 f_nu - 48.60 by 6.6e-5 mag.
    lam = 0.5 * (curve.wavelength_nm[1:] + curve.wavelength_nm[:-1]) * u.nm
    area = 0.5 * (curve.effective_area_m2[1:] + curve.effective_area_m2[:-1]) * u.m**2
    dlam = np.diff(curve.wavelength_nm) * u.nm
    fnu = 3631 * u.Jy * 10 ** (-0.4 * 20.0)
    expected = (np.sum(fnu / (h * lam) * area * dlam) * 100 * u.s).to(u.dimensionless_unscaled).value
    got = photometry.magnitude_to_electrons(20.0, band, 100.0, sca=sca, throughput=throughput)
    assert got == pytest.approx(expected, rel=2e-3)


@pytest.mark.parametrize("throughput", roman.THROUGHPUTS)
def test_magnitude_is_only_a_label_for_flux(throughput):
    for band in roman.BANDS:
        e = photometry.magnitude_to_electrons([18.3, 20.8], band, 168.1, sca=3, throughput=throughput)
        assert e[0] / e[1] == pytest.approx(10, rel=1e-12)
        back = photometry.electrons_to_magnitude(e, band, 168.1, sca=3, throughput=throughput)
        assert back == pytest.approx([18.3, 20.8], abs=1e-12)
        # Exposure time scales the electrons and nothing else.
        twice = photometry.magnitude_to_electrons(20.0, band, 2 * 168.1, sca=3, throughput=throughput)
        assert twice == pytest.approx(2 * e[1] * 10 ** (0.4 * 0.8), rel=1e-12)


@pytest.mark.parametrize("throughput", roman.THROUGHPUTS)
def test_effective_wavelengths_lie_inside_their_bands(throughput):
    for sca in (1, 18):
        for band in roman.BANDS:
            c = roman.throughput(band, sca=sca, source=throughput)
            assert c.blue_limit_nm < c.effective_wavelength_nm < c.red_limit_nm
    assert roman.throughput("H158", sca=18, source="galsim-2021").effective_wavelength_nm == pytest.approx(1579.1, abs=0.5)


def test_unknown_throughput_is_refused_by_name():
    with pytest.raises(InputError, match="throughput"):
        roman.throughput("H158", sca=1, source="cycle-5")
    with pytest.raises(InputError, match="throughput"):
        experiment.SimulationConfig(throughput="newest")


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
        photometry.magnitude_to_electrons(20, "H158", exptime, sca=18, throughput="roman-2024")


def test_negative_flux_has_no_magnitude():
    with pytest.raises(InputError, match="flux_electrons"):
        photometry.electrons_to_magnitude(-5.0, "H158", 168.1, sca=18, throughput="roman-2024")


@pytest.mark.parametrize("throughput", roman.THROUGHPUTS)
def test_si_constants_give_astropys_units_arithmetic(throughput):
    """photometry writes the SI constants out (no astropy import on the simulation path): the same
    trapezoid done with astropy's units and constants gives the same rate to rounding."""
    reference = {"roman-2024": (0.0 * u.ABmag).to(u.Jy), "galsim-2021": 3631.0 * u.Jy}[throughput]
    for band, sca in [("R062", 1), ("H158", 18), ("K213", 9)]:
        curve = roman.throughput(band, sca=sca, source=throughput)
        lam = curve.wavelength_nm * u.nm
        rate = np.trapezoid(reference / (h * lam) * curve.effective_area_m2 * u.m**2, lam).to(1 / u.s).value
        got = photometry.electrons_per_second_at_zero_magnitude(band, sca=sca, throughput=throughput)
        assert got == pytest.approx(rate, rel=1e-12)


@pytest.mark.parametrize("sca", [1, 9, 18])
def test_packed_pupils_equal_the_fits_masks(sca):
    """The shipped packed masks (read with numpy alone) are the FITS masks binned as GalSim bins them."""
    for kind in ("short", "long"):
        from_fits, scale_fits = roman._pupil_from_fits(sca, kind, roman.PUPIL_COMPANION_BIN)
        packed, scale_packed = roman._pupil_from_companion(sca, kind)
        np.testing.assert_array_equal(packed, from_fits.astype(np.float64))
        assert scale_packed == scale_fits
