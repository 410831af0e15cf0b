"""The Roman default read from the shipped field grid, where one is installed, against a fresh
simulation of the same scene (the solver's own simulation, fidelity linear, is the independent path:
it never reads the grid)."""

from dataclasses import replace

import pytest

from nlpsf.request import presets as roman_default
from nlpsf.slopes import fieldgrid
from nlpsf.solve import solver

pytestmark = pytest.mark.skipif(fieldgrid.shipped_grid() is None, reason="no shipped Roman field grid installed")


def _covered(band: str, sca: int) -> bool:
    return f"{band}_{sca:02d}" in fieldgrid.shipped_grid().meta["tables"]


@pytest.mark.parametrize(("band", "sca", "position"), [("H158", 9, (1500.0, 2500.0)), ("F184", 1, (600.0, 3400.0))])
def test_the_default_at_a_position_reads_the_grid_within_its_target(band, sca, position):
    if not _covered(band, sca):
        pytest.skip(f"the installed grid has no {band} SCA {sca}")
    scene = replace(roman_default.base_scene(), position=position)
    grid = solver.solve(band, sca, magnitude=20.0, precision=0.01, scene=scene)
    fresh = solver.solve(band, sca, magnitude=20.0, precision=0.01, scene=scene, fidelity="linear")
    assert grid.fidelity == "table" and "default_from_grid" in [f.code for f in grid.flags]
    assert fresh.fidelity == "linear" and "default_from_grid" not in [f.code for f in fresh.flags]
    # The target for the field interpolation: 1 % in size.
    assert grid.slope == pytest.approx(fresh.slope, rel=0.01)


def test_the_range_over_the_sca_reads_the_grid_nodes():
    if not _covered("H158", 9):
        pytest.skip("the installed grid has no H158 SCA 9")
    answer = solver.solve("H158", 9, magnitude=20.0, precision=0.01)
    span = answer.conditions["sca_range"]
    assert span["slopes_from"] == ["field grid"] and len(span["nodes"]) == 9
    assert span["most_demanding"]["tolerance"] == answer.tolerance >= span["least_demanding"]["tolerance"]


def test_the_defaults_saturation_is_its_own_stars_not_the_paper_tables():
    """Where the grid answers, the saturation limits are the Roman default's star: its brightest pixel
    (through the default's optics, diffusion and IPC, on its sky) reaching the full well, computed here
    from the peak of a fresh preparation of that scene -- not from the paper table's sharper star."""
    from nlpsf.roman import photometry
    from nlpsf.sim import experiment
    from nlpsf.slopes import tablebuild

    position = (1000.0, 3000.0)
    readout = roman_default.readout("H158", 18)
    answer = solver.solve(
        "H158", 18, magnitude=19.0, precision=0.01, scene=replace(roman_default.base_scene(), position=position)
    )
    assert "default_from_grid" in [f.code for f in answer.flags]
    config = tablebuild.TableSettings.roman(realizations=4).config("H158", 18, position=position)
    peak_fraction = float(experiment.prepare(config).star_peak_fraction)
    # The star whose brightest pixel, on top of the sky, reaches the full well. A fine pixel samples
    # the pixel-convolved PSF per fine-pixel area: a native pixel there collects N^2 times it.
    flux = (config.full_well_e - readout.background_e) / (peak_fraction * config.oversampling**2)
    final = float(photometry.electrons_to_magnitude(flux, "H158", config.exptime_s, sca=18, throughput=config.throughput))
    assert answer.final_frame_saturation_magnitude == pytest.approx(final, abs=0.01)
    shift = readout.ramp.saturation_shift_mag(readout.exptime_s, config.full_well_e, config_beta0(), readout.background_e)
    assert answer.saturation_magnitude == pytest.approx(final - shift, abs=0.01)
    # The paper table's star is sharper (no diffusion, one wavelength): its limit is fainter.
    paper = solver.solve("H158", 18, magnitude=19.0, precision=0.01, scene="paper", exptime=readout.exptime_s)
    assert paper.final_frame_saturation_magnitude > answer.final_frame_saturation_magnitude + 0.1


def config_beta0() -> float:
    from nlpsf import defaults

    return defaults.BETA0
