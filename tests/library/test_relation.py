"""nlpsf.solve.relation: the quadratic's monotonicity limit from the star's peak charge, and the
precision an effect's slope change asks for, from T = |c| p beta0."""

import functools
import math

import pytest

from nlpsf.checks import InputError
from nlpsf.slopes import tables
from nlpsf.solve import relation, solver

from .. import shipped

# The paper's scene and tables (the default is the Roman star's): preset "paper" also underlies a scene given.
paper_solve = functools.partial(solver.solve, preset="paper")

TABLES = tables.load_tables()


def _peak_charge(band: str, sca: int, magnitude: float, exptime: float) -> float:
    # The star's brightest pixel, read from the shipped table's peak_electrons column (astropy) and
    # scaled as the flux is, 10^(-0.4 m) T: no photometry code and no nlpsf.slopes.tables look-up.
    return float(shipped.peak_electrons(band, sca, magnitude, exptime))


@pytest.mark.parametrize(
    ("band", "sca", "beta0", "exptime", "background"), [("H158", 18, 5e-7, 168.1, 0.0), ("J129", 3, 2e-6, 60.0, 3e4)]
)
def test_the_nl_invalid_magnitude_is_where_2_beta0_q_reaches_one(band, sca, beta0, exptime, background):
    m = relation.nl_invalid_magnitude(band, sca, beta0, exptime, background)
    assert 2 * beta0 * (_peak_charge(band, sca, m, exptime) + background) == pytest.approx(1.0, rel=1e-12)
    # dS/dQ = 1 - 2 beta0 Q: positive just fainter, negative just brighter.
    for step, sign in ((0.01, 1), (-0.01, -1)):
        assert sign * (1 - 2 * beta0 * (_peak_charge(band, sca, m + step, exptime) + background)) > 0


def test_the_nl_invalid_magnitude_scales_as_beta0_and_the_exposure_do():
    # Q_peak is proportional to the flux, 10^(-0.4 m) T: doubling beta0 halves the limit charge
    # (2.5 log10 2 fainter), doubling the exposure doubles the flux (the same).
    base = relation.nl_invalid_magnitude("Y106", 7, 5e-7, 100.0)
    shift = 2.5 * math.log10(2)
    assert relation.nl_invalid_magnitude("Y106", 7, 1e-6, 100.0) == pytest.approx(base + shift, abs=1e-12)
    assert relation.nl_invalid_magnitude("Y106", 7, 5e-7, 200.0) == pytest.approx(base + shift, abs=1e-12)
    with pytest.raises(InputError) as error:
        relation.nl_invalid_magnitude("Y106", 7, 5e-7, 100.0, background_e=2e6)
    assert error.value.argument == "background"


def test_the_solver_refuses_the_quadratic_where_the_limit_says():
    m = relation.nl_invalid_magnitude("H158", 18, 5e-6)
    with pytest.raises(InputError) as error:
        paper_solve("H158", beta0=5e-6, precision=0.01, magnitude=round(m - 0.02, 6))
    assert error.value.argument == "magnitude" and "not monotonic" in error.value.reason
    # Just fainter the star is still past the tables' bright end (1.5 mag past saturation), but for that reason.
    with pytest.raises(InputError) as error:
        paper_solve("H158", beta0=5e-6, precision=0.01, magnitude=round(m + 0.02, 6))
    assert "not monotonic" not in error.value.reason and "past the tables" in error.value.reason


@pytest.mark.parametrize("impact", [0.25, -0.2, -1.5, 3.0])
def test_precision_with_impact_keeps_the_tolerance(impact):
    # T = |c| p beta0 at fixed T and beta0, with the slope c -> (1 + impact) c.
    c, p, beta0 = -1234.5, 0.01, 5e-7
    tolerance = abs(c) * p * beta0
    p_with = relation.precision_with_impact(p, impact)
    assert abs((1 + impact) * c) * p_with * beta0 == pytest.approx(tolerance, rel=1e-12)


def test_precision_with_impact_where_the_slope_vanishes():
    assert relation.precision_with_impact(0.01, -1.0) == math.inf  # no NL error: any precision does
    with pytest.raises(InputError) as error:
        relation.precision_with_impact(0.0, 0.1)
    assert error.value.argument == "precision"
