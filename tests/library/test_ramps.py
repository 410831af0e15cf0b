"""Up-the-ramp exposures: MA tables, per-read NL, resultants, slope fits, saturation per resultant.

The checks are analytic (one pixel's ramp done by hand), against an independent fit (numpy's
polyfit, an explicit generalised least-squares solve), or against the final-frame simulator
through the exact beta_eff mapping. The solver, the CLI, the service and the linearisation state
with a ramp: ``test_ramps_solver.py``.
"""

import functools
import json
import math

import numpy as np
import pytest

from nlpsf.checks import InputError
from nlpsf.flags import FlagCode, codes
from nlpsf.sim import experiment, ramps
from nlpsf.sim.experiment import SimulationConfig, simulate, slopes
from nlpsf.slopes import tablebuild
from nlpsf.solve import solver

# The paper's scene and tables (the default is the Roman star's): preset "paper" also underlies a scene given.
paper_solve = functools.partial(solver.solve, preset="paper")

T = 168.1
FULL_WELL = 1.1e5
BETA = 5e-7


def uniform(n, fit="ols", **kw):
    return ramps.Ramp.uniform(n, T, fit=fit, **kw)


#: nlpsf's rules before romancal's (saturation by the charge, one resultant fitted through zero):
#: the analytic checks of those rules keep them explicitly.
CHARGE_RULES = {"saturation": "charge", "single_resultant": "through_zero"}


# --- the MA table -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: ramps.MATable.uniform(0, T), "ramp"),
        (lambda: ramps.MATable(((1,), (), (3,)), 3.04), "ma_table.resultants"),
        (lambda: ramps.MATable(((1, 3), (2,)), 3.04), "ma_table.resultants"),  # out of order
        (lambda: ramps.MATable(((1, 2), (2, 3)), 3.04), "ma_table.resultants"),  # read in two resultants
        (lambda: ramps.MATable(((2, 1),), 3.04), "ma_table.resultants"),
        (lambda: ramps.MATable((), 3.04), "ma_table.resultants"),
        (lambda: ramps.MATable(((0,),), 3.04), "ma_table.resultants"),
        (lambda: ramps.MATable(((1,),), 0.0), "ma_table.frame_time_s"),
        (lambda: ramps.Ramp(ramps.MATable(((1,),), 3.04), fit="median"), "ramp_fit"),
        (lambda: ramps.Ramp(ramps.MATable(((1,),), 3.04), read_noise_e=-1.0), "read_noise"),
        (lambda: ramps.Ramp(ramps.MATable(((1,),), 3.04), fit="optimal", read_noise_e=0.0), "read_noise"),
        (lambda: ramps.load_ma_table("no-such-table"), "ma_table"),
        (lambda: uniform(500, "optimal"), "ramp_fit"),
        (lambda: ramps.MATable.uniform(ramps.MAX_READS + 1, T), "ramp"),
        (lambda: SimulationConfig(exptime_s=100.0, ramp=ramps.Ramp(ramps.load_ma_table("romanisim-109"))), "ma_table"),
        (lambda: SimulationConfig(exptime_s=100.0, ramp=uniform(4)), "ramp"),
    ],
)
def test_bad_ramps_are_errors_naming_the_field(make, field):
    with pytest.raises(InputError) as error:
        make()
    assert error.value.argument == field


def test_shipped_tables_load_fit_the_paper_exposure_and_are_documented():
    sources = (ramps.shipped_table_dir().parent / "SOURCES.md").read_text()
    names = ramps.shipped_table_names()
    assert names
    for name in names:
        table = ramps.load_ma_table(name)
        assert f"{name}.json" in sources
        assert table.source
        # The first three (older romanisim) use 3.04 s frames; romanisim 0.15.0's tables 3-17 use 3.16247 s.
        assert table.frame_time_s in (ramps.ROMAN_FRAME_TIME_S, 3.16247)
        table.check_exposure(table.duration_s)
    assert ramps.load_ma_table("ROMANISIM-109").n_reads == 40  # names are case-insensitive
    for name in ("romanisim-1", "romanisim-109", "romanisim-110", "romanisim-4"):
        ramps.load_ma_table(name).check_exposure(T)
    assert ramps.load_ma_table("c2a_img_hlwas") == ramps.load_ma_table("romanisim-4")  # the source's own name


def test_the_longest_uniform_ramp_is_cheap_and_exact():
    # 10^4 reads: O(K) running sums, no K x K matrix; still beta (1 + 1/N) to rounding.
    ramp = uniform(ramps.MAX_READS, **CHARGE_RULES)
    assert ramp.quadratic_factor(T) == pytest.approx(1 + 1 / ramps.MAX_READS, rel=1e-12)
    factors, usable = ramps.order_factors(np.array([1e3, 2e5]), ramp, T, FULL_WELL)
    assert usable[0] == ramps.MAX_READS and factors[0, 0] == pytest.approx(1 + 1 / ramps.MAX_READS, rel=1e-12)
    k = int(usable[1])  # the last read within the full well: tau_k = k / N <= 1.1e5 / 2e5
    assert k == math.floor(ramps.MAX_READS * FULL_WELL / 2e5)
    assert factors[0, 1] == pytest.approx((k + 1) / ramps.MAX_READS, rel=1e-9)  # (k + 1)/k x tau_k


def test_a_table_file_loads(tmp_path):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps({"read_pattern": [[1], [2, 3], [5]], "frame_time_s": 10.0}))
    table = ramps.load_ma_table(str(path))
    assert table.resultants == ((1,), (2, 3), (5,)) and table.duration_s == 50.0 and table.name == "mine"


# --- one pixel by hand ------------------------------------------------------------------------


@pytest.mark.parametrize("n", [2, 3, 7, 55])
def test_uniform_ols_is_the_final_frame_at_beta_times_one_plus_one_over_n(n):
    # Reads tau_i = i/n; the OLS slope of S_i = q tau_i - beta q^2 tau_i^2 against tau_i is
    # q - beta q^2 * slope(tau^2 vs tau) and slope(i^2 vs i) over i = 1..n is
    # cov(i^2, i)/var(i) = [(n+1)^2 (n-1)/12] / [(n+1)(n-1)/12] = n + 1, so slope(tau^2, tau) = (n+1)/n.
    ramp = uniform(n)
    assert ramp.quadratic_factor(T) == pytest.approx(1 + 1 / n, rel=1e-12)
    q = np.array([10.0, 3e3, 5e4, 1e5])  # all below the full well at the last read
    fitted = ramps.simulate_pixels(q, ramp, T, FULL_WELL, (BETA,))
    assert np.all(fitted.usable == n)
    np.testing.assert_allclose(fitted.image, q - BETA * (1 + 1 / n) * q**2, rtol=1e-12)


def test_one_pixel_with_saturated_resultants_dropped_has_the_analytic_slope():
    # Four uniform reads at tau = 1/4 .. 1. With the full well between 2/4 and 3/4 of q the pixel
    # keeps two resultants, and the line through two points has slope
    # (S2 - S1) / (tau2 - tau1) = q - beta q^2 (tau1 + tau2) = q - (3/4) beta q^2.
    ramp = uniform(4, **CHARGE_RULES)
    q = 1.8e5  # q/2 = 0.9e5 <= 1.1e5 < 3q/4 = 1.35e5
    fitted = ramps.simulate_pixels(np.array([q]), ramp, T, FULL_WELL, (BETA,))
    assert fitted.usable[0] == 2
    assert fitted.image[0] == pytest.approx(q - 0.75 * BETA * q**2, rel=1e-12)
    # Only the first resultant left: the reset is the intercept, slope = S1 / tau1 = q - beta q^2 / 4.
    q = 4e5  # q/4 = 1e5 <= 1.1e5 < q/2
    fitted = ramps.simulate_pixels(np.array([q]), ramp, T, FULL_WELL, (BETA,))
    assert fitted.usable[0] == 1 and fitted.image[0] == pytest.approx(q - 0.25 * BETA * q**2, rel=1e-12)
    # Saturated already at the first read: unusable.
    fitted = ramps.simulate_pixels(np.array([5e5]), ramp, T, FULL_WELL, (BETA,))
    assert fitted.usable[0] == 0 and fitted.unusable[0]


def test_romancal_rules_judge_the_signal_and_need_two_resultants():
    # The default rules (romancal's): a resultant is saturated when its *signal* S = Q - beta Q^2 reaches
    # the threshold, so q/2 = 1.15e5 e- of charge (signal 1.084e5 < 1.1e5) keeps its second read; and a
    # pixel left with one resultant has no slope (unusable).
    ramp = uniform(4)
    q = 2.3e5
    assert q / 2 > FULL_WELL > q / 2 - BETA * (q / 2) ** 2
    fitted = ramps.simulate_pixels(np.array([q]), ramp, T, FULL_WELL, (BETA,))
    assert fitted.usable[0] == 2
    assert fitted.image[0] == pytest.approx(q - 0.75 * BETA * q**2, rel=1e-12)
    assert ramps.simulate_pixels(np.array([q]), uniform(4, **CHARGE_RULES), T, FULL_WELL, (BETA,)).usable[0] == 1
    fitted = ramps.simulate_pixels(np.array([4e5]), ramp, T, FULL_WELL, (BETA,))  # one resultant left
    assert fitted.usable[0] == 0 and fitted.unusable[0]


def test_uneven_resultants_match_an_independent_least_squares_fit():
    table = ramps.load_ma_table("romanisim-109")
    ramp = ramps.Ramp(table)
    exptime = table.duration_s
    q = 4.0e5  # saturates part-way up the ramp
    fitted = ramps.simulate_pixels(np.array([q]), ramp, exptime, FULL_WELL, (BETA, 1e-12))
    k = int(fitted.usable[0])
    last = np.array([r[-1] for r in table.resultants]) * table.frame_time_s
    assert k == int(np.sum(q * last / exptime <= FULL_WELL)) and 1 < k < table.n_resultants
    times, means = [], []
    for reads in table.resultants[:k]:
        t = np.array(reads) * table.frame_time_s / exptime
        times.append(t.mean())
        means.append(np.mean(q * t - BETA * (q * t) ** 2 - 1e-12 * (q * t) ** 3))
    slope = np.polyfit(times, means, 1)[0]
    assert fitted.image[0] == pytest.approx(slope, rel=1e-10)


def _gls_slope(table, exptime, q, read_noise, k):
    """Slope of the generalised least-squares line, covariance built read by read (independent)."""
    tau = [np.array(r) * table.frame_time_s / exptime for r in table.resultants[:k]]
    C = np.empty((k, k))
    for i in range(k):
        for j in range(k):
            C[i, j] = q * np.mean(np.minimum.outer(tau[i], tau[j])) + (read_noise**2 / tau[i].size if i == j else 0.0)
    X = np.stack([np.ones(k), [t.mean() for t in tau]], axis=1)
    Ci = np.linalg.inv(C)
    return np.linalg.solve(X.T @ Ci @ X, X.T @ Ci)[1]


@pytest.mark.parametrize("q", [0.0, 50.0, 2e4, 3e5])
def test_optimal_weights_are_the_generalised_least_squares_fit(q):
    table = ramps.load_ma_table("romanisim-109")
    ramp = ramps.Ramp(table, fit="optimal", read_noise_e=10.0)
    exptime = 140.0
    usable = ramps.usable_resultants(np.array([q]), ramp, exptime, FULL_WELL)
    weights = ramps.slope_weights(np.array([q]), usable, ramp, exptime)[0]
    k = int(usable[0])
    np.testing.assert_allclose(weights[:k], _gls_slope(table, exptime, q, 10.0, k), rtol=1e-9, atol=1e-12)
    assert np.all(weights[k:] == 0)


def test_optimal_fit_limits_read_noise_gives_ols_and_poisson_gives_the_end_points():
    ramp_read = uniform(6, "optimal", read_noise_e=1e4)
    ols = ramps.slope_weights(np.array([1.0]), np.array([6]), uniform(6), T)
    read = ramps.slope_weights(np.array([1.0]), np.array([6]), ramp_read, T)
    np.testing.assert_allclose(read, ols, rtol=1e-6)
    # A random walk with an unknown start: the best slope uses the first and last read only.
    poisson = ramps.slope_weights(np.array([1e6]), np.array([6]), uniform(6, "optimal", read_noise_e=1e-4), T)[0]
    span = 1 - 1 / 6
    np.testing.assert_allclose(poisson, [-1 / span, 0, 0, 0, 0, 1 / span], atol=1e-6)


def test_optimal_uniform_ramp_keeps_beta_times_one_plus_one_over_n():
    # Read noise plus a random walk, reads evenly spaced: the covariance is symmetric under time
    # reversal (with the intercept free), so the GLS weights are antisymmetric about the middle,
    # w . (tau - centre)^2 = 0, and w . tau^2 = 2 centre = (n + 1)/n for every charge.
    n = 8
    q = np.geomspace(1.0, 1e5, 25)
    factors, usable = ramps.order_factors(q, uniform(n, "optimal"), T, FULL_WELL)
    assert np.all(usable == n)
    np.testing.assert_allclose(factors[0], 1 + 1 / n, rtol=1e-9)


@pytest.mark.parametrize("fit", ["ols", "optimal"])
def test_ramp_factors_equal_explicit_reads_for_a_cubic_nl_with_background(fit):
    ramp = ramps.Ramp(ramps.load_ma_table("romanisim-110"), fit=fit)
    q = np.geomspace(1.0, 2e6, 40)
    coefficients = (BETA, 3e-12)
    background = 250.0
    perturbation, usable = ramps.nonlinearity_perturbation(q, ramp, 140.0, FULL_WELL, coefficients, background)
    star = ramps.simulate_pixels(q, ramp, 140.0, FULL_WELL, coefficients, background)
    sky = ramps.simulate_pixels(np.zeros(1), ramp, 140.0, FULL_WELL, coefficients, background)
    np.testing.assert_array_equal(usable, star.usable)
    np.testing.assert_allclose(perturbation, star.image - sky.image[0] - q, rtol=1e-9, atol=1e-9 * q.max())


# --- the experiment ---------------------------------------------------------------------------


def _with(config, scene, **changes):
    """The same rendered stamps under another detector configuration (same seed and centroids)."""
    other = SimulationConfig(**{**{k: getattr(config, k) for k in config.__dataclass_fields__}, **changes})
    return other, experiment.Scene(other, scene.psf, scene.offsets, scene.stamps, scene.reference, 0.0)


@pytest.mark.parametrize("method", ["monte_carlo", "linear"])
@pytest.mark.parametrize("n", [2, 10])
def test_uniform_ols_ramp_metrics_equal_the_final_frame_at_beta_eff(paper_config, paper_scene, method, n):
    frame, frame_scene = _with(paper_config, paper_scene, method=method)
    ramp, ramp_scene = _with(paper_config, paper_scene, method=method, ramp=uniform(n))
    for magnitude in (18.3, 21.0):  # fainter than where any resultant saturates
        a = simulate(ramp, [magnitude], [BETA], scene=ramp_scene)[0]
        b = simulate(frame, [magnitude], [BETA * (1 + 1 / n)], scene=frame_scene)[0]
        for metric in ("dR_over_R", "de1", "de2"):
            assert getattr(a, metric).mean == pytest.approx(getattr(b, metric).mean, rel=1e-9, abs=1e-15)
        assert a.extras["ramp"]["fitted_on_fewer"] == 0 and a.extras["ramp"]["unusable"] == 0
        assert a.conditions["ramp"]["quadratic_beta_factor"] == pytest.approx(1 + 1 / n)
    # Per-pixel beta maps: beta_k c is a map drawn at (c beta, c sigma) from the same normal deviates.
    c = 1 + 1 / n
    a = simulate(ramp, [19.0], [BETA], sigma_beta=0.1 * BETA, scene=ramp_scene)[0]
    b = simulate(frame, [19.0], [BETA * c], sigma_beta=0.1 * BETA * c, scene=frame_scene)[0]
    for metric in ("dR_over_R", "de1", "de2"):
        assert getattr(a, metric).std == pytest.approx(getattr(b, metric).std, rel=1e-7)
    s_ramp = slopes(ramp, [19.0], scene=ramp_scene)[0]
    s_frame = slopes(frame, [19.0], beta0=BETA * (1 + 1 / n), scene=frame_scene)[0]
    for metric in ("dR_over_R", "de1", "de2"):
        # d metric / d beta = (1 + 1/n) d metric / d beta_eff at beta_eff
        assert s_ramp.bias[metric].mean == pytest.approx((1 + 1 / n) * s_frame.bias[metric].mean, rel=1e-6)


def test_a_single_read_is_the_final_frame(paper_config, paper_scene):
    ramp, ramp_scene = _with(paper_config, paper_scene, ramp=uniform(1))
    for magnitude in (18.3, 20.0):
        a = simulate(ramp, [magnitude], [BETA], scene=ramp_scene)[0]
        b = simulate(paper_config, [magnitude], [BETA], scene=paper_scene)[0]
        for metric in ("dR_over_R", "de1", "de2"):
            assert getattr(a, metric).mean == pytest.approx(getattr(b, metric).mean, rel=1e-12, abs=1e-18)
    scatter_a = simulate(ramp, [19.0], [BETA], sigma_beta=0.1 * BETA, scene=ramp_scene)[0]
    scatter_b = simulate(paper_config, [19.0], [BETA], sigma_beta=0.1 * BETA, scene=paper_scene)[0]
    assert scatter_a.dR_over_R.std == pytest.approx(scatter_b.dR_over_R.std, rel=1e-12)


def test_any_ols_table_maps_exactly_onto_the_final_frame(paper_config, paper_scene):
    table = ramps.load_ma_table("romanisim-109")
    ramp_cfg = ramps.Ramp(table)
    config, scene = _with(paper_config, paper_scene, ramp=ramp_cfg, exptime_s=table.duration_s, method="linear")
    frame, frame_scene = _with(paper_config, paper_scene, exptime_s=table.duration_s, method="linear")
    c = ramp_cfg.quadratic_factor(table.duration_s)
    a = simulate(config, [19.0], [BETA], scene=scene)[0]
    b = simulate(frame, [19.0], [BETA * c], scene=frame_scene)[0]
    assert a.dR_over_R.mean == pytest.approx(b.dR_over_R.mean, rel=1e-12)


@pytest.mark.parametrize(("rules", "needed"), [(CHARGE_RULES, 1), ({"saturation": "charge", "single_resultant": "unusable"}, 2)])
def test_the_ramp_saturation_magnitude_moves_by_the_time_of_the_resultant_a_slope_needs(paper_config, paper_scene, rules, needed):
    # The charge rule makes the limit exact: the brightest pixel's charge at the last read of the
    # resultant a slope needs (the first, or the second where one resultant gives no slope) is the full well.
    ramp_cfg = uniform(8, **rules)
    config, scene = _with(paper_config, paper_scene, ramp=ramp_cfg)
    # The final frame's flag is judged on the star (brightest pixel over every sub-pixel centroid),
    # the ramp's saturation on the centroids drawn (``ramp_effect``).
    final_frame = tablebuild.saturation_magnitude(paper_scene.star_peak_fraction, config)  # exposure T, full well
    drawn = tablebuild.saturation_magnitude(float(paper_scene.peak_fraction.max()), config)
    predicted = drawn - 2.5 * math.log10(T / (needed * T / 8))
    assert ramp_cfg.saturation_shift_mag(T) == pytest.approx(drawn - predicted, rel=1e-12)
    step = 0.05
    grid = np.round(np.arange(final_frame + 0.5, predicted - 0.5, -step), 6)
    results = simulate(config, list(grid), [BETA], scene=scene)
    frame_results = simulate(paper_config, list(grid), [BETA], scene=paper_scene)
    unusable = np.array([r.extras["ramp"]["unusable"] > 0 for r in results])
    dropped = np.array([r.extras["ramp"]["fitted_on_fewer"] > 0 for r in results])
    frame_saturated = np.array([FlagCode.SATURATED in codes(r.flags) for r in frame_results])
    # Brightest magnitude still usable on the ramp, and brightest unsaturated final frame.
    ramp_limit = grid[np.argmax(unusable) - 1]
    frame_limit = grid[np.argmax(frame_saturated) - 1]
    assert abs(ramp_limit - predicted) <= step and abs(frame_limit - final_frame) <= step
    assert ramp_limit - frame_limit == pytest.approx(-2.5 * math.log10(8 / needed), abs=2 * step)
    # Stars between the two limits get answers, flagged as fitted on the early resultants.
    between = (grid < drawn) & (grid > ramp_limit)  # a drawn centroid's final frame passes the full well
    assert between.sum() > 10
    for r, d in zip(np.array(results)[between], dropped[between], strict=True):
        assert d and r.dR_over_R.mean is not None and FlagCode.RAMP_FEWER_RESULTANTS in codes(r.flags)
        assert FlagCode.SATURATED not in codes(r.flags)


def test_optimal_ramp_runs_through_both_methods_and_names_itself(paper_config, paper_scene):
    ramp_cfg = ramps.Ramp(ramps.load_ma_table("romanisim-110"), fit="optimal")
    results = {}
    for method in ("monte_carlo", "linear"):
        config, scene = _with(paper_config, paper_scene, ramp=ramp_cfg, method=method)
        results[method] = slopes(config, [18.0], scene=scene)[0]
        assert results[method].conditions["ramp"]["fit"] == "optimal"
        assert results[method].conditions["ramp"]["ma_table"] == "romanisim-110"
        assert "ramp" in results[method].to_dict()
    # The paper's finite differences and the exact derivative agree (the NL is linear in beta here).
    assert results["linear"].bias["dR_over_R"].mean == pytest.approx(results["monte_carlo"].bias["dR_over_R"].mean, rel=2e-3)
