"""The Roman default read from the shipped field grid, where one is installed, against a fresh
simulation of the same scene (the solver's own simulation, fidelity linear, is the independent path:
it never reads the grid)."""

from dataclasses import replace

import pytest

from nlpsf import roman_default, solver

pytestmark = pytest.mark.skipif(roman_default.field_grid() is None, reason="no shipped Roman field grid installed")


def _covered(band: str, sca: int) -> bool:
    return f"{band}_{sca:02d}" in roman_default.field_grid().meta["tables"]


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
