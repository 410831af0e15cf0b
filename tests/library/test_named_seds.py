"""The vendored K0V spectrum (nlpsf.roman.seds, ``--sed k0v``), the Roman default's star, and its ``sed`` part."""

from dataclasses import replace
from importlib import resources

import numpy as np
import pytest

from nlpsf import roman
from nlpsf.checks import InputError
from nlpsf.request import presets as roman_default
from nlpsf.roman import seds
from nlpsf.sim import experiment, optics
from nlpsf.sim import scene as scenes
from nlpsf.slopes import tablebuild
from nlpsf.solve import model_part
from nlpsf.solve import roman_uncertainty as ru
from nlpsf.solve import roman_uncertainty_measure as measure


def _file_rows() -> np.ndarray:
    """The vendored file, read here on its own (not through nlpsf.roman.seds)."""
    text = (resources.files("nlpsf") / "data" / "seds" / "pickles_uk_31.txt").read_text()
    return np.array([[float(v) for v in line.split()] for line in text.splitlines() if line and line[0] != "#"])


def test_the_vendored_file_is_the_upstream_table():
    rows = _file_rows()
    wave, flux = rows.T
    # The rows 4000-25000 A of pickles_uk_31 on its 5 A grid, every flux positive.
    assert wave[0] == 4000.0 and wave[-1] == 25000.0 and np.all(np.diff(wave) == 5.0)
    assert np.all(flux > 0)
    # Values read off the upstream EXOSIMS pickles_uk_31.ascii (commit 528f012), by wavelength.
    upstream = {5000.0: 3.60158e-09, 5890.0: 3.22656e-09, 8540.0: 1.92664e-09, 15000.0: 7.31468e-10, 22000.0: 2.2775e-10}
    for w, f in upstream.items():
        assert flux[wave == w][0] == f
    # The units and the normalisation the header states: f_lambda of a V = 0 (vegamag) star, whose
    # flux density near 550 nm is Vega's, 3.6e-9 erg s^-1 cm^-2 A^-1 (Bessell 1998: 3.63e-9).
    v_band = flux[(wave >= 5400) & (wave <= 5700)].mean()
    assert v_band == pytest.approx(3.63e-9, rel=0.05)


def test_the_spectrum_the_scene_uses_is_the_file_in_nm():
    rows = _file_rows()
    wave, flux = scenes.SceneModel(sed="k0v").spectrum()
    assert np.array_equal(np.asarray(wave), rows[:, 0] / 10.0)
    assert np.allclose(flux, rows[:, 1] / rows[:, 1].max(), rtol=1e-15, atol=0)


def test_a_k0v_is_about_as_red_as_a_5250_k_blackbody_between_v_and_k():
    # The spectrum's continuum slope from 550 nm to 2.2 um against the Planck law at the K0V
    # T_eff of STPSF's lookup (5250 K): within 15 % (the spectrum has lines and the H- bump).
    rows = _file_rows()
    wave, flux = rows.T
    ratio = flux[wave == 22000.0][0] / flux[wave == 5500.0][0]
    planck = scenes.planck_flambda(np.array([2200.0, 550.0]), 5250.0)
    assert ratio == pytest.approx(planck[0] / planck[1], rel=0.15)


@pytest.mark.parametrize("band", roman.BANDS)
def test_photon_weights_integrate_the_k0v_over_every_band(band):
    # Binned weights of the band, sum 1, at the photon-weighted means of their bins: the mean
    # wavelength they give is the fine integral's (counts ~ A_eff f_lambda lambda), computed here.
    spectrum = scenes.SceneModel(sed="k0v").spectrum()
    waves, weights = optics.OpticsConfig(band=band, n_wavelengths=8, spectrum=spectrum).wavelengths_and_weights()
    assert weights.sum() == pytest.approx(1.0, abs=1e-12)
    curve = roman.throughput(band, sca=18)
    fine = np.linspace(curve.blue_limit_nm, curve.red_limit_nm, 4001)
    counts = np.interp(fine, curve.wavelength_nm, curve.effective_area_m2) * np.interp(fine, *spectrum) * fine
    mean = np.trapezoid(counts * fine, fine) / np.trapezoid(counts, fine)
    assert float(np.sum(waves * weights)) == pytest.approx(mean, rel=1e-4)


def test_h158_sees_the_k0v_redder_than_a_blackbody_of_its_temperature():
    # The H- opacity minimum near 1.6 um makes a K dwarf bright in H: its photons in H158 are
    # redder than a 5270 K blackbody's (Pecaut & Mamajek's K0V T_eff), by more than 5 nm.
    mean = {}
    for sed in ("k0v", "blackbody:5270"):
        spectrum = scenes.SceneModel(sed=sed).spectrum()
        w, p = optics.OpticsConfig(band="H158", n_wavelengths=8, spectrum=spectrum).wavelengths_and_weights()
        mean[sed] = float(np.sum(w * p))
    assert mean["k0v"] - mean["blackbody:5270"] > 5.0


def test_the_roman_default_star_is_the_vendored_k0v():
    rows = _file_rows()
    wave, flux = roman_default.base_scene().spectrum()
    assert np.array_equal(np.asarray(wave), rows[:, 0] / 10.0)
    assert np.allclose(flux, rows[:, 1] / rows[:, 1].max(), rtol=1e-15, atol=0)
    named = {v["name"]: v for v in roman_default.conditions()}["sed"]
    assert named["value"] == "k0v" and "Pickles 1998" in named["source"]


def test_k0v_is_a_named_sed_everywhere_a_scene_is_read(tmp_path):
    assert scenes.SceneModel(sed=" K0V ").sed == "k0v"
    assert scenes.SceneModel(sed="k0v").sed_units == "flambda"
    assert scenes.parse_sed("k0v") == {"sed": "k0v"}
    assert scenes.from_options(sed="k0v").sed == "k0v"
    assert scenes.from_request({"sed": "k0v"}).sed == "k0v"
    path = tmp_path / "scene.json"
    scenes.save(scenes.SceneModel(sed="k0v"), path)
    assert scenes.load(str(path)).sed == "k0v"
    with pytest.raises(InputError, match="k0v"):
        scenes.SceneModel(sed="k9v")
    assert seds.NAMED["k0v"].file == "pickles_uk_31.txt"


def test_sed_range_is_the_two_blackbody_ends_against_the_k0v():
    # The range's variants are the default scene with a 3500 K and a 10000 K blackbody and nothing
    # else changed; the default's own star is the K0V spectrum, and no stand-in part is left.
    config = tablebuild.TableSettings.roman(realizations=6, seed=3).config("H158", 18)
    assert config.scene.sed == "k0v"
    variants = measure.variant_configs(config)
    ends = [variants["sed_cool"][0], variants["sed_hot"][0]]
    assert [v.scene for v in ends] == [replace(config.scene, sed=f"blackbody:{t:g}") for t in (3500, 10000)]
    assert "sed_standin" not in ru.PART_NAMES and "sed" not in ru.PART_NAMES
    # Measured directly on other draws, the H158 bias-size change at m = 20 at each end has the sign
    # and size of the shipped SCA-18 range's.
    base, *changes = (
        experiment.slopes(c, [20.0], linearise_at=roman_default.LINEARISE_AT)[0].bias["dR_over_R"].mean for c in (config, *ends)
    )
    shipped = ru.shipped()["per_band"]["H158"]["bias"]["size"]["per_sca"]["18"]["ranges"]["sed"]
    row = next(r for r in shipped["by_magnitude"] if r[0] == 20.0)
    for end, value in zip(changes, row[1:], strict=True):
        change = end / base - 1.0
        assert change == pytest.approx(value, rel=0.25, abs=5e-4)
    assert abs(row[2]) > 1e-3


def test_a_request_with_its_own_sed_is_not_given_the_sed_range():
    # The old 5270 K blackbody stand-in is now a star of the request's own.
    scene = replace(roman_default.base_scene(), sed="blackbody:5270")
    info = model_part.shipped_model("H158", 18, "size", "bias", scene, "linear", default="roman")
    assert "sed" not in info["ranges"]
    dropped = {p["name"]: p for p in info["included"]}["sed"]
    assert dropped["impact"] is None and dropped["why"].startswith("set by the request")
    default = model_part.shipped_model("H158", 18, "size", "bias", None, "table", default="roman")
    assert "sed" in default["ranges"] and "sed_standin" not in [p["name"] for p in default["left_out"]]
