"""Extreme tolerances and precisions: every request gets an answer or an InputError naming its field.

The Roman default's slope falls in proportion to the flux at the field grid's faint end (the linear
regime, once the sky's own NL is removed with the local sky estimate, docs/ramps.md), so a tolerance
its faintest grid star misses is met by a fainter star, extrapolated by that law (flagged), as the
paper's scene extrapolates its tables. The checks read the field grid and the tables directly, not
the magnitude scan. (Where |c| does not fall toward fainter stars no star meets such a tolerance:
``test_magnitude_scan_rule`` checks that refusal on an analytic c(m).)
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from nlpsf import cli, defaults
from nlpsf.flags import FlagCode
from nlpsf.request.resolve import SolveRequest
from nlpsf.slopes import fieldgrid, tables
from nlpsf.solve.solver import answer

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


def test_the_defaults_error_falls_as_the_flux_at_the_grids_faint_end():
    # The premise of the extrapolations below: half a magnitude fainter, 10^(-0.2) of the error.
    faint = _faint_end()
    at_end, brighter = _grid_error([faint, faint - 0.5])
    assert at_end / brighter == pytest.approx(10**-0.2, rel=0.02)


@pytest.mark.parametrize("tolerance", [1e-9, 1e-13])
def test_a_tolerance_fainter_than_the_grid_is_extrapolated_as_the_flux(tolerance):
    faint = _faint_end()
    assert tolerance < float(_grid_error([faint])[0])  # the faintest star the grid holds misses it
    solution = answer(_default(tolerance))
    codes = [f.code for f in solution.flags]
    assert FlagCode.EXTRAPOLATED_ANSWER in codes and solution.binding_limit == "nonlinearity"
    at_answer = float(_grid_error([faint])[0]) * 10 ** (-0.4 * (solution.magnitude - faint))
    assert math.isclose(at_answer, tolerance, rel_tol=1e-6)
    assert (FlagCode.FAINTER_THAN_40 in codes) == (solution.magnitude > 40)


def test_just_above_the_faint_ends_error_every_fainter_star_meets_it():
    faint = _faint_end()
    tolerance = 1.02 * float(_grid_error([faint])[0])
    solution = answer(_default(tolerance))
    assert solution.binding_limit == "nonlinearity"
    assert FlagCode.EXTRAPOLATED_ANSWER not in [f.code for f in solution.flags]
    fainter = np.arange(solution.magnitude + 0.01, faint + 1e-9, 0.01)
    assert np.all(_grid_error(fainter) <= tolerance)  # the answer's promise, on the grid itself
    assert _grid_error([solution.magnitude - 0.02])[0] > tolerance  # and it is the brightest such star


def test_without_a_position_the_sca_range_extrapolates_alike():
    solution = answer(_default(1e-9, position=None))
    codes = [f.code for f in solution.flags]
    assert FlagCode.SCA_RANGE in codes and FlagCode.EXTRAPOLATED_ANSWER in codes


def test_a_shear_budget_is_answered_from_the_grid():
    request = SolveRequest.from_json(
        {"band": "H158", "precision": PRECISION, "shear_m": 1e-7, "size_ratio": 1.5, "scene": {"position": list(POSITION)}}
    )
    solution = answer(request)
    assert solution.binding_limit == "nonlinearity"
    # m = 2 dR/R / rho^2 for a PSF size error (rho = R_gal / R_psf = 1.5): the tolerance on dR/R is m rho^2 / 2.
    assert float(_grid_error([solution.magnitude])[0]) == pytest.approx(1e-7 * 1.5**2 / 2, rel=1e-3)


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


def test_the_cli_answers_beyond_the_grid_with_its_flag(capsys):
    argv = ["solve", "--band", "H158", "--precision", "0.01", "--tolerance", "1e-9", "--json"]
    for extra in (["--position", "1000,3000"], ["--scene", "paper"]):
        assert cli.main([*argv, *extra]) == 0
        assert "extrapolated_answer" in capsys.readouterr().out


def test_a_simulated_default_extrapolates_alike_from_its_own_slopes():
    # Another beta0 than the grid's: the default is simulated, and its scan reads its own slopes.
    body = {"band": "H158", "precision": PRECISION, "beta0": 1e-6, "scene": {"position": list(POSITION)}}
    solution = answer(SolveRequest.from_json({**body, "tolerance": 1e-9}))
    assert FlagCode.EXTRAPOLATED_ANSWER in [f.code for f in solution.flags]
    # The NL error of a star at the answer, solved for directly, is the tolerance.
    there = answer(SolveRequest.from_json({**body, "magnitude": solution.magnitude}))
    assert math.isclose(there.tolerance, 1e-9, rel_tol=1e-3)


def test_a_star_fainter_than_the_grid_is_read_by_the_flux_law_and_agrees_with_a_simulation():
    from dataclasses import replace

    from nlpsf import solve
    from nlpsf.request import presets as roman_default

    extrapolated = answer(
        SolveRequest.from_json({"band": "H158", "magnitude": 30.0, "precision": PRECISION, "scene": {"position": list(POSITION)}})
    )
    assert FlagCode.EXTRAPOLATED_FAINT in [f.code for f in extrapolated.flags]
    scene = replace(roman_default.base_scene(), position=POSITION)
    # The simulation runs the residual model the grid holds (its answer names it).
    model = extrapolated.conditions["residual_nl"]
    fresh = solve("H158", 18, "size", magnitude=30.0, precision=PRECISION, fidelity="linear", scene=scene, residual_nl=model)
    assert extrapolated.slope == pytest.approx(fresh.slope, rel=1e-3)
