"""A simulated answer of the Roman default (another exposure, a modified scene, ``accuracy``) takes
its saturation limits from the star it simulates, not from the paper table's sharper star.

The expected limit is computed here from a fresh preparation of that scene (its brightest fine
pixel over every sub-pixel centroid) and the photometry, independently of the answer's path."""

from __future__ import annotations

from dataclasses import replace

import pytest

from nlpsf import defaults
from nlpsf.request import presets as roman_default
from nlpsf.roman import photometry
from nlpsf.sim import experiment
from nlpsf.slopes import tablebuild
from nlpsf.solve import solver

POSITION = (1000.0, 3000.0)


def _expected_limits(band: str, sca: int, exposure: float, **scene_changes) -> tuple[float, float, float]:
    """(final-frame limit, ramp limit, paper table's final-frame limit) of a fresh preparation."""
    config = tablebuild.TableSettings.roman(realizations=4, exptime_s=exposure).config(band, sca, position=POSITION)
    config = replace(config, scene=replace(config.scene, **scene_changes))
    peak_fraction = float(experiment.prepare(config).star_peak_fraction)
    background = config.scene.background_e
    # The star whose brightest pixel, on top of the sky, reaches the full well. A fine pixel samples
    # the pixel-convolved PSF per fine-pixel area: a native pixel there collects N^2 times it.
    flux = (defaults.FULL_WELL_E - background) / (peak_fraction * config.oversampling**2)
    final = float(photometry.electrons_to_magnitude(flux, band, exposure, sca=sca, throughput=config.throughput))
    shift = config.ramp.saturation_shift_mag(exposure, defaults.FULL_WELL_E, defaults.BETA0, background)
    return final, final - shift, background


def _scene(band, sca, exposure, **changes):
    background = roman_default.readout(band, sca, exposure).background_e
    return replace(roman_default.scene(POSITION, background), **changes)


def test_a_default_at_another_exposure_saturates_where_its_own_star_does():
    exposure = 300.0
    final, ramp_limit, _ = _expected_limits("H158", 18, exposure)
    answer = solver.solve("H158", 18, magnitude=20.0, precision=0.01, exptime=exposure, scene=_scene("H158", 18, exposure))
    assert answer.fidelity != "table"  # simulated: the grid holds the default's own exposure only
    assert answer.final_frame_saturation_magnitude == pytest.approx(final, abs=1e-6)
    assert answer.saturation_magnitude == pytest.approx(ramp_limit, abs=1e-6)
    assert answer.conditions["saturation_from"].startswith("the simulated scene's own star")
    # The paper table's star (one wavelength, no blurs) is sharper: its limit would be ~0.24 mag fainter.
    paper = solver.solve("H158", 18, magnitude=20.0, precision=0.01, scene="paper", exptime=exposure)
    assert paper.final_frame_saturation_magnitude > answer.final_frame_saturation_magnitude + 0.1


def test_an_accuracy_answer_of_a_modified_default_saturates_where_its_star_does():
    exposure = roman_default.exptime_s()
    changes = {"jitter_arcsec": 0.014, "sed": "blackbody:10000"}
    scene = _scene("J129", 9, exposure, **changes)
    answer = solver.solve("J129", 9, magnitude=20.0, precision=0.01, accuracy=0.01, scene=scene)
    # A modified default is band-integrated like the measured polychromatic level (nlpsf.solve.accuracy):
    # the star simulated integrates its SED over the wavelengths its conditions state.
    waves = answer.conditions["n_wavelengths"]
    assert waves >= 8
    final, ramp_limit, _ = _expected_limits("J129", 9, exposure, n_wavelengths=waves, **changes)
    assert answer.final_frame_saturation_magnitude == pytest.approx(final, abs=1e-6)
    assert answer.saturation_magnitude == pytest.approx(ramp_limit, abs=1e-6)
    assert "own star" in answer.conditions["saturation_from"]
