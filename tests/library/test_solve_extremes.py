"""Extreme tolerances and precisions: every request gets an answer or an InputError naming its field.

The Roman default's slope grows toward faint stars (its sky's own NL is a pedestal whose weight in
the moments goes as 1 / flux), so a tolerance its faintest grid star misses is met by no star; the
paper's scene has no sky and its answers are extrapolated in proportion to the flux. The checks
read the field grid and the tables directly, not the magnitude scan.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from nlpsf import cli, defaults, fieldgrid, tables
from nlpsf.checks import InputError
from nlpsf.flags import FlagCode
from nlpsf.request import SolveRequest
from nlpsf.solver import answer

POSITION = (1000.0, 3000.0)
PRECISION = 0.01


def _default(tolerance: float, position=POSITION, precision: float = PRECISION, **extra) -> SolveRequest:
    scene = {} if position is None else {"position": list(position)}
    return SolveRequest.from_json({"band": "H158", "precision": precision, "tolerance": tolerance, "scene": scene, **extra})


def _grid_error(magnitudes, precision: float = PRECISION) -> np.ndarray:
    """|c(m)| p beta0 at the position, from the shipped field grid's own reader."""
    grid = fieldgrid.shipped_grid()
    values, _ = grid.slope("H158", 18, POSITION, "size", "bias", np.asarray(magnitudes, dtype=float))
    return np.abs(values) * precision * defaults.BETA0


def _faint_end() -> float:
    return fieldgrid.shipped_grid().magnitude_range("H158", 18)[1]


def test_the_defaults_error_grows_toward_faint_stars_at_the_grids_faint_end():
    # The premise of the refusals below: fainter than the grid, no star does better.
    faint = _faint_end()
    at_end, brighter = _grid_error([faint, faint - 0.5])
    assert at_end > brighter > 0


@pytest.mark.parametrize("tolerance", [1e-7, 1e-6, 1e-5])
def test_a_tolerance_no_default_star_meets_names_the_tolerance(tolerance):
    smallest = float(_grid_error([_faint_end()])[0])
    assert tolerance < smallest  # the faintest star the grid holds already misses it
    with pytest.raises(InputError) as raised:
        answer(_default(tolerance))
    assert raised.value.argument == "tolerance"
    assert math.isclose(raised.value.smallest, smallest, rel_tol=1e-6)


def test_just_above_the_smallest_reachable_tolerance_every_fainter_star_meets_it():
    faint = _faint_end()
    tolerance = 1.02 * float(_grid_error([faint])[0])
    solution = answer(_default(tolerance))
    assert solution.binding_limit == "nonlinearity"
    fainter = np.arange(solution.magnitude + 0.01, faint + 1e-9, 0.01)
    assert np.all(_grid_error(fainter) <= tolerance)  # the answer's promise, on the grid itself
    assert _grid_error([solution.magnitude - 0.02])[0] > tolerance  # and it is the brightest such star
    assert FlagCode.SLOPE_CHANGES_SIGN in [f.code for f in solution.flags]  # the default's size slope crosses zero


def test_without_a_position_the_sca_range_refuses_it_too():
    with pytest.raises(InputError) as raised:
        answer(_default(1e-7, position=None))
    assert raised.value.argument == "tolerance"


def test_a_shear_budget_that_no_star_meets_names_the_budget():
    request = SolveRequest.from_json(
        {"band": "H158", "precision": PRECISION, "shear_m": 1e-7, "size_ratio": 1.5, "scene": {"position": list(POSITION)}}
    )
    with pytest.raises(InputError) as raised:
        answer(request)
    assert raised.value.argument == "shear_m"


@pytest.mark.parametrize("precision", [defaults.PRECISION_RANGE[0], 1e-6])
def test_a_fine_precision_leaves_saturation_binding_for_the_default(precision):
    solution = answer(_default(1e-3, precision=precision))
    codes = [f.code for f in solution.flags]
    assert solution.binding_limit == "saturation"
    assert FlagCode.BELOW_TOLERANCE_EVERYWHERE in codes
    assert float(_grid_error(np.arange(14.2, _faint_end(), 0.05), precision).max()) < 1e-3


def _paper(tolerance: float, precision: float = PRECISION) -> SolveRequest:
    return SolveRequest.from_json({"band": "H158", "precision": precision, "tolerance": tolerance, "scene": "paper"})


def test_the_paper_scene_answers_tolerance_1e_7_inside_its_table():
    solution = answer(_paper(1e-7))
    table = tables.load_tables().get("H158", 18)
    value, _, region = table.slope("size", "bias", solution.magnitude, defaults.EXPTIME_S, defaults.BETA0)
    assert region[0] == 0 and solution.binding_limit == "nonlinearity"
    assert math.isclose(abs(float(value[0])) * PRECISION * defaults.BETA0, 1e-7, rel_tol=1e-4)


@pytest.mark.parametrize("tolerance", [1e-10, 1e-13])
def test_the_paper_scene_extrapolates_in_proportion_to_the_flux(tolerance):
    solution = answer(_paper(tolerance))
    codes = [f.code for f in solution.flags]
    assert FlagCode.EXTRAPOLATED_ANSWER in codes
    table = tables.load_tables().get("H158", 18)
    faint = table.grid_range(defaults.EXPTIME_S, defaults.BETA0)[1]
    value, _, _ = table.slope("size", "bias", faint, defaults.EXPTIME_S, defaults.BETA0)
    # Linear regime: the error falls as the flux, 10^(-0.4 dm), from the table's faint end.
    at_answer = abs(float(value[0])) * PRECISION * defaults.BETA0 * 10 ** (-0.4 * (solution.magnitude - faint))
    assert math.isclose(at_answer, tolerance, rel_tol=1e-9)
    assert (FlagCode.FAINTER_THAN_40 in codes) == (solution.magnitude > 40)


def test_the_cli_names_the_option(capsys):
    argv = ["solve", "--band", "H158", "--precision", "0.01", "--tolerance", "1e-7", "--json"]
    assert cli.main([*argv, "--position", "1000,3000"]) == 2
    assert "--tolerance" in capsys.readouterr().err
    assert cli.main([*argv, "--scene", "paper"]) == 0


def test_a_simulated_default_refuses_alike_and_its_bound_is_its_own_slope_there():
    # Another beta0 than the grid's: the default is simulated, and its scan reads its own slopes
    # (the paper tables' c(m) has neither its sign change nor its growth toward faint stars).
    body = {"band": "H158", "precision": PRECISION, "beta0": 1e-6, "scene": {"position": list(POSITION)}}
    with pytest.raises(InputError) as raised:
        answer(SolveRequest.from_json({**body, "tolerance": 1e-7}))
    assert raised.value.argument == "tolerance"
    # The bound is the NL error of a star at that faintest magnitude, solved for directly.
    there = answer(SolveRequest.from_json({**body, "magnitude": raised.value.faintest}))
    assert math.isclose(raised.value.smallest, there.tolerance, rel_tol=1e-9)
