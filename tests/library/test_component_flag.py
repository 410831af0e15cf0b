"""An ellipticity component whose slope is small against |c_e| (or consistent with zero) is flagged
in every answer, whatever is solved for, and the flag points to ``--metric e`` (issue 28, item 3).

The component's fraction of |c_e| = hypot(c_e1, c_e2) is computed here from the shipped slopes read
independently of the solver (the paper tables' ECSV by astropy and scipy, ``tests/shipped.py``; the
Roman default's field grid read node by node), never from the flag's own numbers."""

import functools
import json
import math

import numpy as np
import pytest

from nlpsf import cli
from nlpsf.flags import FlagCode, codes
from nlpsf.slopes import fieldgrid
from nlpsf.solve import solver
from nlpsf.solve.validity import COMPONENT_SMALL_FRACTION

from .. import shipped

paper_solve = functools.partial(solver.solve, scene="paper")


def _paper_fraction(band, sca, metric, magnitude):
    c1 = float(shipped.slope(band, sca, "e1", "bias", magnitude))
    c2 = float(shipped.slope(band, sca, "e2", "bias", magnitude))
    return abs(c1 if metric == "e1" else c2) / math.hypot(c1, c2)


def _paper_case(small: bool):
    """A (band, SCA, metric) of the paper tables whose component is (or is clearly not) small at
    m = 20, found by reading the ECSV, not the solver."""
    for band in ("H158", "J129", "Y106", "F184", "W146", "Z087", "K213", "R062"):
        for sca in range(1, 19):
            for metric in ("e1", "e2"):
                fraction = _paper_fraction(band, sca, metric, 20.0)
                if (small and fraction < 0.8 * COMPONENT_SMALL_FRACTION) or (not small and fraction > 0.6):
                    return band, sca, metric, fraction
    raise AssertionError("no such case in the shipped tables")


@pytest.mark.parametrize("kwargs", [{"precision": 0.01}, {"tolerance": 1e-6}])
def test_a_small_component_is_flagged_at_a_given_magnitude(kwargs):
    band, sca, metric, fraction = _paper_case(small=True)
    s = paper_solve(band, sca, metric=metric, magnitude=20.0, **kwargs)
    flags = [f for f in s.flags if getattr(f, "code", None) == FlagCode.E_COMPONENT_SMALL]
    assert len(flags) == 1
    assert flags[0].values["fraction"] == pytest.approx(fraction, rel=1e-6)
    assert "--metric e" in flags[0]
    assert f"< {COMPONENT_SMALL_FRACTION:g} |c_e|" in flags[0]


def test_a_small_component_is_flagged_when_the_magnitude_is_solved_for():
    band, sca, metric, _ = _paper_case(small=True)
    c = abs(float(shipped.slope(band, sca, metric, "bias", 20.0)))
    s = paper_solve(band, sca, metric=metric, precision=0.01, tolerance=c * 0.01 * 5e-7)
    assert s.solved_for == "magnitude" and abs(s.magnitude - 20.0) < 0.5
    assert _paper_fraction(band, sca, metric, s.magnitude) < COMPONENT_SMALL_FRACTION
    assert FlagCode.E_COMPONENT_SMALL in codes(s.flags)


def test_a_large_component_and_the_modulus_are_not_flagged():
    band, sca, metric, _ = _paper_case(small=False)
    s = paper_solve(band, sca, metric=metric, magnitude=20.0, precision=0.01)
    assert FlagCode.E_COMPONENT_SMALL not in codes(s.flags)
    small_band, small_sca, _, _ = _paper_case(small=True)
    e = paper_solve(small_band, small_sca, metric="e", magnitude=20.0, precision=0.01)
    assert FlagCode.E_COMPONENT_SMALL not in codes(e.flags)


def test_the_issues_case_is_flagged_with_its_fraction(capsys):
    # issue 28: R062 SCA 6 at (1784.7, 633.6), m = 21.07, e2 bias, tolerance solved for: U = 840 %
    # and no flag before. The fraction from the field grid's nodes, interpolated here by the
    # tensor-product Lagrange weights written out below (not the grid's reader).
    grid = fieldgrid.shipped_grid()
    if grid is None or not grid.covers("R062", 6):
        pytest.skip("no shipped field grid")
    position, magnitude = (1784.7, 633.6), 21.07
    n = grid.conditions("R062", 6)["grid"]
    axis = np.linspace(1.0, 4088.0, n)

    def lagrange(x):
        return np.array([np.prod([(x - axis[m]) / (axis[k] - axis[m]) for m in range(n) if m != k]) for k in range(n)])

    w = np.outer(lagrange(position[1]), lagrange(position[0]))  # [j (y), i (x)]
    c1 = float(np.sum(w * grid.node_values("R062", 6, "bias_e1", magnitude)))
    c2 = float(np.sum(w * grid.node_values("R062", 6, "bias_e2", magnitude)))
    fraction = abs(c2) / math.hypot(c1, c2)
    assert fraction < COMPONENT_SMALL_FRACTION
    assert cli.main(
        ["solve", "--band", "R062", "--sca", "6", "--magnitude", "21.07", "--precision", "0.01", "--metric", "e2",
         "--mode", "bias", "--position", "1784.7,633.6", "--json"]
    ) == 0  # fmt: skip
    out = json.loads(capsys.readouterr().out)
    assert "e_component_small" in out["flag_codes"]
    flag = out["flags"][out["flag_codes"].index("e_component_small")]
    assert f"|c_e2| = {fraction:.2f} |c_e|" in flag and "--metric e" in flag
