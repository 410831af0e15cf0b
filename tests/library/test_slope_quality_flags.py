"""A simulated answer carries its slope's quality flags: where the Monte Carlo finite difference is
jumpy (a pixel crosses the moments' hard weight cut between the two beta values, K213 SCA 6 at
(701, 1403), m = 17.72: the stated slope error 0.060 against 0.0042 exact, 14x; it was 6.3, 1500x, while
the difference was taken over +-1e-4 beta0 rather than today's +-0.1 beta0; the case moves with the
physics: it was m = 17.9 before the sky was removed as a local sky estimate removes it, m = 17.84
before the calibration residual was modelled per resultant),
the answer says so, as the simulation does; the exact derivative (linear) raises no such flag."""

from __future__ import annotations

from dataclasses import replace

from nlpsf.flags import FlagCode, codes
from nlpsf.request import presets as roman_default
from nlpsf.solve import solver


def _answer(fidelity: str):
    scene = replace(roman_default.base_scene(), position=(701.0, 1403.0))
    return solver.solve("K213", 6, magnitude=17.72, precision=0.01, scene=scene, fidelity=fidelity)


def test_a_jumpy_monte_carlo_slope_is_flagged_in_the_answer():
    answer = _answer("polychromatic")
    assert FlagCode.JUMPY_FINITE_DIFFERENCE.value in codes(answer.flags)
    # The flag's reason: the slope's stated error is far above the exact derivative's.
    exact = _answer("linear")
    assert FlagCode.JUMPY_FINITE_DIFFERENCE.value not in codes(exact.flags)
    assert answer.slope_uncertainty > 10 * exact.slope_uncertainty
