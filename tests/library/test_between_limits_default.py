"""The Roman default between the saturation limits (issue 28, item 1).

Between the ramp's saturation limit and the final frame's, pixels lose resultants and the slope
changes with each that does; the field grid's interpolation misses a fresh simulation there by a
median 2.9 % (size) and 12-23 % (e), up to 25 % / 540 % (docs/field.md). So at a position there the
default answer is simulated afresh with the grid's own settings, and says so. The truth here is the
grid's build recipe itself (``TableSettings.roman().config`` simulated by ``experiment.slopes``),
not the solver's path."""

from dataclasses import replace

import numpy as np
import pytest

from nlpsf import SolveRequest, answer
from nlpsf.flags import FlagCode, codes
from nlpsf.request import presets
from nlpsf.sim import experiment
from nlpsf.slopes import fieldgrid, providers, tablebuild
from nlpsf.solve.validity import between_limits

BAND, SCA, POSITION = "Y106", 4, (2174.0, 3177.0)


@pytest.fixture(scope="module")
def grid():
    grid = fieldgrid.shipped_grid()
    if grid is None or not grid.covers(BAND, SCA):
        pytest.skip("no shipped field grid")
    return grid


def _request(**kwargs):
    scene = replace(presets.base_scene(), position=kwargs.pop("position", POSITION))
    return SolveRequest(BAND, sca=SCA, metric=kwargs.pop("metric", "size"), scene=scene, **kwargs)


def _recipe_slope(position, magnitude, metric="dR_over_R"):
    settings = tablebuild.TableSettings.roman()
    config = settings.config(BAND, SCA, position=position)
    result = experiment.slopes(
        config, [magnitude], beta0=settings.beta0, linearise_at=settings.linearise_at, residual_nl=settings.residual_nl
    )[0]
    return result.bias[metric].mean, result.bias[metric].stderr, result.extras["ramp"]


def test_between_the_limits_the_answer_is_the_grids_recipe_simulated_at_the_position(grid):
    ramp, final = grid.saturation_magnitude(BAND, SCA, POSITION), grid.final_frame_saturation_magnitude(BAND, SCA, POSITION)
    magnitude = round(ramp + 0.4 * (final - ramp), 3)
    s = answer(_request(magnitude=magnitude, precision=0.01))
    value, stderr, summary = _recipe_slope(POSITION, magnitude)
    assert summary["fitted_on_fewer"] > 0  # pixels do lose resultants here
    assert s.slope == pytest.approx(value, rel=1e-9)
    assert s.slope_uncertainty == pytest.approx(stderr, rel=1e-9)
    assert s.fidelity == "linear" and FlagCode.DEFAULT_BETWEEN_LIMITS in codes(s.flags)
    assert FlagCode.DEFAULT_FROM_GRID not in codes(s.flags)
    assert s.conditions["realizations"] == grid.conditions(BAND, SCA)["settings"]["realizations"]


def test_outside_the_limits_and_at_a_node_the_grid_answers(grid):
    final = grid.final_frame_saturation_magnitude(BAND, SCA, POSITION)
    fainter = answer(_request(magnitude=final + 0.5, precision=0.01))
    assert fainter.fidelity == "table" and FlagCode.DEFAULT_FROM_GRID in codes(fainter.flags)
    node = fieldgrid.grid_positions(int(grid.conditions(BAND, SCA)["grid"]))[6][2]
    ramp, final = grid.saturation_magnitude(BAND, SCA, node), grid.final_frame_saturation_magnitude(BAND, SCA, node)
    assert between_limits(grid, BAND, SCA, node, (ramp + final) / 2) is None
    at_node = answer(_request(position=node, magnitude=(ramp + final) / 2, precision=0.01))
    assert at_node.fidelity == "table"


def test_a_magnitude_the_grid_puts_between_the_limits_is_solved_again_afresh(grid):
    import numpy as np

    final = grid.final_frame_saturation_magnitude(BAND, SCA, POSITION)
    faint = np.arange(final, 27.0, 0.01)
    c, _ = grid.slope(BAND, SCA, POSITION, "size", "bias", faint)
    # A tolerance every star fainter than the final frame's limit meets: the answer lies brighter.
    tolerance = 1.05 * float(np.nanmax(np.abs(c))) * 0.01 * 5e-7
    s = answer(_request(precision=0.01, tolerance=tolerance))
    assert FlagCode.DEFAULT_BETWEEN_LIMITS in codes(s.flags) and s.fidelity == "linear"
    assert s.conditions["between_limits"]["limits"][0] <= s.conditions["between_limits"]["grid_magnitude"] < final
    value, _, _ = _recipe_slope(POSITION, s.magnitude if s.binding_limit == "nonlinearity" else s.saturation_magnitude)
    assert s.slope == pytest.approx(value, rel=1e-6)


def test_at_table_cost_it_refuses_and_says_why(grid):
    ramp, final = grid.saturation_magnitude(BAND, SCA, POSITION), grid.final_frame_saturation_magnitude(BAND, SCA, POSITION)
    with pytest.raises(providers.NeedsSimulation) as refused:
        answer(_request(magnitude=(ramp + final) / 2, precision=0.01), simulate=False)
    assert refused.value.argument == "magnitude" and providers.REFUSAL in refused.value.reason
    assert f"{ramp:.2f}" in refused.value.reason and f"{final:.2f}" in refused.value.reason


def test_the_recipe_rows_between_the_limits_and_leaves_the_paper_tables_alone():
    from astropy.table import Table

    import nlpsf

    rows = tablebuild.magnitude_grid(14.4, between=(14.4, 17.8), between_step=tablebuild.BETWEEN_LIMITS_STEP)
    step, margin = tablebuild.BETWEEN_LIMITS_STEP, tablebuild.BETWEEN_LIMITS_MARGIN_MAG
    # Every row from a step before (limit - margin) to a step after (final + margin) is a step apart.
    inside = rows[(rows >= 14.4 - margin - step) & (rows <= 17.8 + margin + step)]
    assert inside.min() <= 14.4 - margin and inside.max() >= 17.8 + margin
    assert max(abs(d - step) for d in inside[1:] - inside[:-1]) < 1e-9
    assert tablebuild.TableSettings.roman().between_step == tablebuild.BETWEEN_LIMITS_STEP
    # The paper's recipe and fingerprint are the shipped tables' own.
    shipped = Table.read(next(iter(nlpsf.__path__)) + "/data/tables/slopes.ecsv", format="ascii.ecsv")
    assert tablebuild.TableSettings().fingerprint() == shipped.meta["fingerprint"]
    h158 = shipped[(shipped["band"] == "H158") & (shipped["sca"] == 18)]
    m_sat = float(shipped.meta["per_table"]["H158 18"]["saturation_magnitude"])
    assert list(tablebuild.magnitude_grid(m_sat)) == pytest.approx(sorted(h158["magnitude"]), abs=1e-9)


def test_accuracy_between_the_limits_simulates_enough_centroids(grid):
    from nlpsf.solve import accuracy

    ramp, final = grid.saturation_magnitude(BAND, SCA, POSITION), grid.final_frame_saturation_magnitude(BAND, SCA, POSITION)
    magnitude = round(ramp + 0.33 * (final - ramp), 3)
    s = answer(_request(magnitude=magnitude, precision=0.01, accuracy=0.01))
    assert FlagCode.ACCURACY_CENTROIDS in codes(s.flags)
    used = s.conditions["realizations"]
    assert accuracy.BETWEEN_LIMITS_PILOT <= used <= accuracy.MAX_REALIZATIONS
    # The pilot is the grid's own 100 draws: the recipe's value and error there, independently.
    _, pilot_error, _ = _recipe_slope(POSITION, magnitude)
    value, _, _ = _recipe_slope(POSITION, magnitude)
    relative = abs(pilot_error / value)
    assert used == min(accuracy.MAX_REALIZATIONS, max(100, int(np.ceil(100 * (relative / 0.005) ** 2))))
    # Its stated statistical error is the pilot's scaled by sqrt(100 / N) (to the sampling of the
    # error itself, 25 %), and where the count fits the rule it is within half the accuracy.
    stated = s.slope_uncertainty / abs(s.slope)
    assert stated == pytest.approx(relative * (100 / used) ** 0.5, rel=0.25)
    flag = next(f for f in s.flags if getattr(f, "code", None) == FlagCode.ACCURACY_CENTROIDS)
    if used < accuracy.MAX_REALIZATIONS:
        assert stated <= 0.005 * 1.25 and "within it" in flag
    else:
        assert "above it" in flag
    fainter = answer(_request(magnitude=final + 0.7, precision=0.01, accuracy=0.01))
    assert FlagCode.ACCURACY_CENTROIDS not in codes(fainter.flags)
    assert fainter.conditions["realizations"] == accuracy.ANSWER_REALIZATIONS


def test_accuracy_says_when_no_affordable_count_fits(grid):
    ramp, final = grid.saturation_magnitude(BAND, SCA, POSITION), grid.final_frame_saturation_magnitude(BAND, SCA, POSITION)
    s = answer(_request(metric="e2", magnitude=round(ramp + 0.33 * (final - ramp), 3), precision=0.01, accuracy=0.01))
    flag = next(f for f in s.flags if getattr(f, "code", None) == FlagCode.ACCURACY_CENTROIDS)
    assert "above it" in flag and s.conditions["realizations"] == 800
