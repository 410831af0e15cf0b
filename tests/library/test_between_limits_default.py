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
from nlpsf.sim.experiment import results
from nlpsf.slopes import fieldgrid, providers, tablebuild
from nlpsf.solve import centroids, solver
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
    assert s.fidelity == "linear" and FlagCode.DEFAULT_BETWEEN_LIMITS in codes(s.flags)
    assert FlagCode.DEFAULT_FROM_GRID not in codes(s.flags)
    own = grid.conditions(BAND, SCA)["settings"]["realizations"]
    if abs(stderr / value) <= centroids.STATISTICAL_SHARE * centroids.DEFAULT_TARGET["size"]:
        # The grid's own centroids are enough: the answer is the recipe's, bit for bit.
        assert s.slope == pytest.approx(value, rel=1e-9)
        assert s.slope_uncertainty == pytest.approx(stderr, rel=1e-9)
        assert s.conditions["realizations"] == own
    else:
        assert s.conditions["realizations"] > own
        assert abs(s.slope - value) <= 4 * np.hypot(stderr, s.slope_uncertainty)


def test_between_the_limits_a_default_answer_simulates_enough_centroids_for_its_target():
    # H158, SCA 7: at m = 16.8 (the limits 14.06 and 17.48) the e slope's error over the grid's own
    # 100 centroids is ~8 % of it, above the 5 % (half the 10 % an e answer is held to here).
    band, sca, position, magnitude = "H158", 7, (1200.0, 2900.0), 16.8
    scene = replace(presets.base_scene(), position=position)
    s = answer(SolveRequest(band, sca=sca, metric="e", scene=scene, magnitude=magnitude, tolerance=1e-3))
    settings = tablebuild.TableSettings.roman()
    pilot = experiment.slopes(
        settings.config(band, sca, position=position), [magnitude], beta0=settings.beta0,
        linearise_at=settings.linearise_at, residual_nl=settings.residual_nl,
    )[0]  # fmt: skip
    value, error = pilot.slope("bias", ("de1", "de2"))
    target = centroids.STATISTICAL_SHARE * centroids.DEFAULT_TARGET["e"]
    assert abs(error / value) > target
    used = s.conditions["realizations"]
    flag = next(f for f in s.flags if getattr(f, "code", None) == FlagCode.DEFAULT_BETWEEN_LIMITS)
    assert 100 < used <= centroids.DEFAULT_MAX_REALIZATIONS and f"{used} centroids" in flag
    # A standard error falls as 1 / sqrt(N) (the spread over centroids is the pilot's, to its sampling).
    assert s.slope_uncertainty == pytest.approx(error * (100 / used) ** 0.5, rel=0.3)
    if used < centroids.DEFAULT_MAX_REALIZATIONS:
        assert s.slope_uncertainty / abs(s.slope) <= target * (1 + 1e-9) and flag.endswith("within it")
    assert abs(s.slope - value) <= 4 * np.hypot(error, s.slope_uncertainty)


def test_batches_of_centroids_pool_to_the_statistics_of_one_sample():
    rng = np.random.default_rng(5)
    whole = rng.standard_cauchy(2300)  # heavy-tailed, as slopes between the limits are
    parts = [experiment.Statistic.of(whole[a:b]) for a, b in ((0, 800), (800, 1600), (1600, 2300))]
    one, pooled = experiment.Statistic.of(whole), results.pooled_statistic(parts)
    assert pooled.count == one.count == 2300
    assert pooled.mean == pytest.approx(one.mean, rel=1e-12)
    assert pooled.std == pytest.approx(one.std, rel=1e-12) and pooled.stderr == pytest.approx(one.stderr, rel=1e-12)


def test_a_slope_of_more_centroids_than_a_batch_is_the_batches_pooled(monkeypatch):
    # 250 centroids in batches of 100 (seeds seed, seed + 1, seed + 2): the answer's slope is the
    # three simulations of the grid's recipe pooled, each run here on its own.
    from nlpsf.slopes import source

    monkeypatch.setattr(source, "BATCH_REALIZATIONS", 100)
    magnitude = 17.0
    settings = tablebuild.TableSettings.roman()
    config = settings.config(BAND, SCA, position=POSITION)
    ask = {"beta0": settings.beta0, "linearise_at": settings.linearise_at, "residual_nl": settings.residual_nl}
    runs = [
        experiment.slopes(replace(config, realizations=n, seed=config.seed + k), [magnitude], **ask)[0]
        for k, n in enumerate((100, 100, 50))
    ]
    pooled = [results.pooled_statistic([r.bias[m] for r in runs]) for m in ("dR_over_R", "de1")]
    request = _request(magnitude=magnitude, precision=0.01, fidelity="linear")
    the_plan = replace(solver.plan(request), realizations=250)
    slopes = source.Slopes.for_request(request, the_plan)
    value, error, _ = slopes.at(magnitude)
    assert value == pytest.approx(pooled[0].mean, rel=1e-12) and error == pytest.approx(pooled[0].stderr, rel=1e-12)
    assert slopes._results[magnitude].bias["de1"].count == 250 == pooled[1].count
    # 350 centroids of the same request, reusing those batches (100, 100 and 50): only the two it
    # does not hold (100 at seed + 2, 50 at seed + 3) are simulated, and the answer is the four pooled.
    more = source.Slopes.for_request(request, replace(the_plan, realizations=350))
    more.reuse_batches(slopes)
    value, _, _ = more.at(magnitude)
    assert len(more._batches) == 5
    rest = [replace(config, realizations=n, seed=config.seed + k) for k, n in ((2, 100), (3, 50))]
    four = [*runs[:2], *(experiment.slopes(c, [magnitude], **ask)[0] for c in rest)]
    assert value == pytest.approx(results.pooled_statistic([r.bias["dR_over_R"] for r in four]).mean, rel=1e-12)


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
    # The pilot's rule first; then the count is chosen again from the error it reached, so never fewer.
    assert used >= min(accuracy.MAX_REALIZATIONS, max(100, int(np.ceil(100 * (relative / 0.005) ** 2))))
    # A standard error falls as 1 / sqrt(N) (to the sampling of the spread itself, 30 %); where the
    # count stays under the cap the error reached is within half the accuracy, and the flag says so.
    stated = s.slope_uncertainty / abs(s.slope)
    assert s.slope_uncertainty == pytest.approx(pilot_error * (100 / used) ** 0.5, rel=0.3)
    flag = next(f for f in s.flags if getattr(f, "code", None) == FlagCode.ACCURACY_CENTROIDS)
    assert f"{stated:.2g} over {used}" in flag
    if used < accuracy.MAX_REALIZATIONS:
        assert stated <= 0.005 * (1 + 1e-9) and flag.endswith("within it)")
    else:
        assert "above it" in flag
    fainter = answer(_request(magnitude=final + 0.7, precision=0.01, accuracy=0.01))
    assert FlagCode.ACCURACY_CENTROIDS not in codes(fainter.flags)
    assert fainter.conditions["realizations"] == accuracy.ANSWER_REALIZATIONS


def test_accuracy_says_when_no_affordable_count_fits(grid, monkeypatch):
    from nlpsf.solve import accuracy

    # The cap lowered to two batches of centroids, so that the test runs in seconds.
    monkeypatch.setattr(accuracy, "MAX_REALIZATIONS", 1600)
    ramp, final = grid.saturation_magnitude(BAND, SCA, POSITION), grid.final_frame_saturation_magnitude(BAND, SCA, POSITION)
    s = answer(_request(metric="e2", magnitude=round(ramp + 0.33 * (final - ramp), 3), precision=0.01, accuracy=0.01))
    flag = next(f for f in s.flags if getattr(f, "code", None) == FlagCode.ACCURACY_CENTROIDS)
    assert "above it" in flag and s.conditions["realizations"] == accuracy.MAX_REALIZATIONS


def test_a_small_e_component_is_held_to_its_share_of_the_modulus():
    # F184 SCA 15 at m = 16.1: |c_e1| is small against |c_e| (flagged); its error is held to 5 % of
    # 0.3 |c_e|, the scale its model uncertainty has, not to 5 % of a slope near zero.
    position = (254.43815456037626, 687.7238603629428)
    scene = replace(presets.base_scene(), position=position)
    ask = {"sca": 15, "scene": scene, "magnitude": 16.099, "tolerance": 1e-3}
    s = answer(SolveRequest("F184", metric="e1", **ask))
    modulus = answer(SolveRequest("F184", metric="e", **ask))
    flag = next(f for f in s.flags if getattr(f, "code", None) == FlagCode.DEFAULT_BETWEEN_LIMITS)
    assert FlagCode.E_COMPONENT_SMALL in codes(s.flags) and "relative to 0.3 |c_e|" in flag
    target = centroids.STATISTICAL_SHARE * centroids.DEFAULT_TARGET["e1"]
    assert s.conditions["realizations"] < centroids.DEFAULT_MAX_REALIZATIONS and flag.endswith("within it")
    assert s.slope_uncertainty <= target * 0.3 * abs(modulus.slope) * 1.25
