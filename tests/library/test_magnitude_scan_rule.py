"""The magnitude scan's rule at the faint end, on analytic c(m) (no simulation: the rule is arithmetic).

c(m) = A 10^(-0.4 (m - 20)) is the linear regime (|c| in proportion to the flux): a tolerance the
faintest scanned star misses is met by a fainter one, at the magnitude the flux law gives. Adding a
term that grows toward faint stars, P 10^(+0.4 (m - 20)) (what a sky's NL left in the image did),
makes a tolerance the faintest star misses unreachable: an InputError naming it, with the smallest
tolerance reachable.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from nlpsf.flags import FlagCode
from nlpsf.solve.magnitude_scan import ToleranceUnreachable, scan_magnitude

BRIGHT, FAINT = 14.0, 28.0
DELTA_BETA = 5e-9  # 1 % of 5e-7


class _AnalyticGrid:
    """A field grid's reading interface over an analytic c(m)."""

    def __init__(self, c):
        self.c = c

    def magnitude_range(self, band, sca):
        return BRIGHT, FAINT

    def slope(self, band, sca, position, metric, mode, magnitudes):
        values = self.c(np.asarray(magnitudes, dtype=float))
        return values, np.zeros_like(values)

    def value(self, band, sca, position, metric, mode, magnitudes):
        return self.slope(band, sca, position, metric, mode, magnitudes)[0]


def _slopes(c):
    return SimpleNamespace(
        grid=_AnalyticGrid(c),
        band="H158",
        sca=18,
        scene_model=SimpleNamespace(position=(1000.0, 3000.0)),
        metric="size",
        mode="bias",
        ramp=object(),
        fidelity="table",
        ramp_factor=None,
        ramp_bases=set(),
        at=lambda m: (float(c(np.asarray(m))), 0.0, None),
    )


def linear(m):
    return 2e4 * 10 ** (-0.4 * (np.asarray(m) - 20.0))


def test_inside_the_range_the_answer_is_where_the_flux_law_meets_the_tolerance():
    tolerance = 1e-5
    scan = scan_magnitude(_slopes(linear), DELTA_BETA, tolerance, m_sat=BRIGHT)
    expected = 20.0 + 2.5 * math.log10(2e4 * DELTA_BETA / tolerance)
    assert scan.magnitude == pytest.approx(expected, abs=1e-3)
    assert FlagCode.EXTRAPOLATED_ANSWER not in [f.code for f in scan.flags]


def test_fainter_than_the_range_the_answer_is_extrapolated_as_the_flux():
    tolerance = 1e-9
    scan = scan_magnitude(_slopes(linear), DELTA_BETA, tolerance, m_sat=BRIGHT)
    assert FlagCode.EXTRAPOLATED_ANSWER in [f.code for f in scan.flags]
    assert abs(linear(scan.magnitude)) * DELTA_BETA == pytest.approx(tolerance, rel=1e-9)
    assert scan.magnitude > FAINT


def test_an_error_growing_toward_faint_stars_makes_a_tolerance_unreachable():
    def growing(m):
        return linear(m) + 3.0 * 10 ** (0.4 * (np.asarray(m) - 20.0))

    at_faint_end = abs(growing(FAINT)) * DELTA_BETA
    with pytest.raises(ToleranceUnreachable) as raised:
        scan_magnitude(_slopes(growing), DELTA_BETA, 0.5 * at_faint_end, m_sat=BRIGHT)
    assert raised.value.argument == "tolerance"
    assert raised.value.smallest == pytest.approx(at_faint_end, rel=1e-12)
    assert raised.value.faintest == FAINT


def test_a_fresh_scan_whose_widened_bracket_reaches_a_saturated_star_says_so():
    # The tables' bracket [16.8, 17.05] does not hold the simulated crossing and a magnitude brighter
    # the star has no slope (NaN, saturated): a SimulationError naming both, not scipy's ValueError.
    from nlpsf.checks import SimulationError
    from nlpsf.solve.magnitude_scan import _secant_root

    def excess(m: float) -> float:  # below the tolerance down to m = 16.5, saturated brighter
        return float("nan") if m < 16.5 else -0.2 - (m - 16.5)

    with pytest.raises(SimulationError, match="saturates"):
        _secant_root(excess, 16.8, 17.05)
    # Saturated at the bracket itself: said too, never a NaN root from the secant.
    with pytest.raises(SimulationError, match="saturates"):
        _secant_root(excess, 16.4, 17.05)
    # Where the widened bracket holds the crossing, it is found (the root of m - 16.0 at 16.0).
    assert _secant_root(lambda m: m - 16.0, 16.8, 17.05) == pytest.approx(16.0, abs=1e-4)


def test_a_fresh_final_frame_scan_stops_at_the_saturation_magnitude():
    # The paper scene simulated in another state (linearise_at="corrected", Z087 SCA 3 at precision
    # 0.01, tolerance 1e-3) had its job fail: the tables' bracket of the crossing lies brighter than
    # saturation (m = 18.45), the simulated error stays below the tolerance there, and a magnitude
    # brighter the quadratic is not monotonic (NaN). With the saturation magnitude the search ends
    # there: below the tolerance at saturation is "saturation binds" (None), not a failure.
    from nlpsf.solve.magnitude_scan import _secant_root

    saturation = 18.45

    def below(m: float) -> float:  # the error below the tolerance everywhere it is defined
        return float("nan") if m < 16.5 else -0.2 - 0.1 * (m - 16.5)

    assert _secant_root(below, 16.8, 17.05, saturation=saturation) is None

    # The error reaching the tolerance fainter than saturation (at 18.6: log excess 18.6 - m): found
    # there, although the tables' bracket was all brighter than saturation.
    def fainter(m: float) -> float:
        return float("nan") if m < 16.5 else 18.6 - m

    assert _secant_root(fainter, 16.8, 17.05, saturation=saturation) == pytest.approx(18.6, abs=1e-4)

    # The error above the tolerance at saturation (17.5 here) and below it at the widened faint end:
    # the crossing between them, at 18.0.
    def crossing(m: float) -> float:
        return float("nan") if m < 16.5 else 18.0 - m

    assert _secant_root(crossing, 16.8, 17.05, saturation=17.5) == pytest.approx(18.0, abs=1e-4)


def test_the_corrected_state_paper_solve_is_answered_with_saturation_binding():
    from nlpsf.flags import FlagCode, codes
    from nlpsf.solve import solver

    answer = solver.solve("Z087", 3, tolerance=1e-3, precision=0.01, scene="paper", linearise_at="corrected")
    paper = solver.solve("Z087", 3, tolerance=1e-3, precision=0.01, scene="paper")
    # The same saturation magnitude as the tables' (the final frame's rule does not depend on the
    # state), bound by it, with the simulated error there below the tolerance and said.
    assert answer.binding_limit == "saturation" and answer.magnitude == paper.saturation_magnitude
    error = abs(answer.slope) * 0.01 * answer.conditions["beta0"]
    assert 0 < error < 1e-3
    assert FlagCode.BELOW_TOLERANCE_EVERYWHERE in codes(answer.flags)
