"""Up-the-ramp exposures: MA tables, per-read NL, resultants, slope fits, saturation per resultant.

The checks are analytic (one pixel's ramp done by hand), against an independent fit (numpy's
polyfit, an explicit generalised least-squares solve), or against the final-frame simulator
through the exact beta_eff mapping. The last tests are the slope a calibration error acts through:
linearised at the uncorrected beta0 (the paper) or at the corrected detector (a residual NL), with a
ramp's saturation flags set by the raw beta0 either way.
"""

import functools
import json
import math

import numpy as np
import pytest

from nlpsf.checks import InputError
from nlpsf.flags import FlagCode, codes
from nlpsf.sim import experiment, ramps
from nlpsf.sim import scene as scenes
from nlpsf.sim.experiment import SimulationConfig, simulate, slopes
from nlpsf.slopes import tablebuild
from nlpsf.solve import solver

from .. import shipped

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


# --- the solver -------------------------------------------------------------------------------


def test_solver_reads_a_uniform_ols_ramp_from_the_tables_at_beta_eff():
    n = 8
    ramp = paper_solve("H158", precision=0.01, magnitude=19.0, ramp=uniform(n))
    # Same tables at beta_eff = (1 + 1/n) beta0: d/d beta = (1 + 1/n) d/d beta_eff.
    frame = paper_solve("H158", precision=0.01, magnitude=19.0, beta0=BETA * (1 + 1 / n))
    assert ramp.slope == pytest.approx((1 + 1 / n) * frame.slope, rel=1e-12)
    assert ramp.conditions["ramp_slopes_from"].startswith("tables at beta_eff")
    assert ramp.conditions["ramp"]["ma_table"] == f"uniform-{n}"
    # Checked against a fresh linear-response simulation of the ramp itself.
    fresh = paper_solve("H158", precision=0.01, magnitude=19.0, ramp=uniform(n), fidelity="linear")
    assert "simulations" in fresh.conditions["ramp_slopes_from"]
    assert fresh.slope == pytest.approx(ramp.slope, abs=3 * ramp.slope_uncertainty)


def test_solver_magnitude_for_an_ols_ramp_is_the_final_frames_at_beta_eff():
    # |c_ramp(m)| p beta0 = T with c_ramp(m) = c c(m; c beta0) is the final frame's equation at
    # beta0' = c beta0 with the same precision p: the same magnitude.
    n = 8
    ramp = paper_solve("H158", precision=0.01, tolerance=1e-4, ramp=uniform(n))
    frame = paper_solve("H158", precision=0.01, tolerance=1e-4, beta0=BETA * (1 + 1 / n))
    assert ramp.binding_limit == frame.binding_limit == "nonlinearity"
    assert ramp.magnitude == pytest.approx(frame.magnitude, abs=1e-5)
    optimal = paper_solve("H158", precision=0.01, tolerance=1e-4, ramp=uniform(n, "optimal"))
    assert "simulations" in optimal.conditions["ramp_slopes_from"]
    assert optimal.magnitude == pytest.approx(ramp.magnitude, abs=3 * ramp.uncertainty)


def test_solver_saturation_rules_and_stars_between_them():
    n = 8
    plain = paper_solve("H158", precision=0.01, magnitude=17.0)
    ramp = paper_solve("H158", precision=0.01, magnitude=17.0, ramp=uniform(n))
    payload = json.loads(json.dumps(ramp.to_dict()))
    assert payload["final_frame_saturation_magnitude"] == pytest.approx(plain.saturation_magnitude)
    # A slope needs two resultants (romancal); the second ends at tau = 2/n of the exposure. romancal's
    # rule judges the signal S = x - beta0 x^2 of the charge x there: it reaches the full well W at
    # x = (1 - sqrt(1 - 4 beta0 W)) / (2 beta0), a peak charge x / tau over the exposure, so the limit is
    # 2.5 log10(x / (tau W)) brighter than the final frame's (2.5 log10(n / 2) for a linear detector).
    x = (1 - math.sqrt(1 - 4 * BETA * FULL_WELL)) / (2 * BETA)
    shift = 2.5 * math.log10(x / (2 / n * FULL_WELL))
    assert shift > 2.5 * math.log10(n / 2) + 0.05  # the linear estimate is this much too faint
    assert payload["saturation_magnitude"] == pytest.approx(plain.saturation_magnitude - shift, abs=1e-9)
    charge = paper_solve("H158", precision=0.01, magnitude=19.0, ramp=uniform(n, saturation="charge"))
    assert charge.saturation_magnitude == pytest.approx(plain.saturation_magnitude - 2.5 * math.log10(n / 2), abs=1e-9)
    assert "ramp" in ramp.conditions["saturation_rule"] and "final frame" in plain.conditions["saturation_rule"]
    # m = 17 lies between the two limits: an answer from a fresh simulation, flagged as such.
    assert FlagCode.STAR_SATURATED in codes(plain.flags)
    assert not {FlagCode.SATURATED, FlagCode.STAR_SATURATED, FlagCode.RAMP_SATURATED} & set(codes(ramp.flags))
    assert FlagCode.BETWEEN_SATURATION_LIMITS in codes(ramp.flags)
    assert "simulations" in ramp.conditions["ramp_slopes_from"] and ramp.tolerance > 0
    # When saturation binds, the brightest usable star is the ramp's limit, not the final frame's.
    loose = paper_solve("H158", precision=1e-4, tolerance=1e-3, ramp=uniform(n))
    assert loose.binding_limit == "saturation"
    assert loose.brightest_usable_magnitude == pytest.approx(loose.saturation_magnitude)
    assert loose.brightest_usable_magnitude == pytest.approx(loose.final_frame_saturation_magnitude - shift)
    with pytest.raises(InputError) as error:
        paper_solve("H158", precision=0.01, magnitude=10.0, ramp=uniform(n))
    assert error.value.argument == "magnitude"


def test_solver_takes_a_scene_with_a_ramp_where_the_ramp_can_read_it_out():
    # The charge rule with a background b: the pixel holds (q + b) tau at the last read of the
    # resultant a slope needs, so the star's limit is a peak charge W / tau - b over the exposure
    # (the final frame's: W - b), read off the same photometry at those charges.
    n, background = 8, 2000.0
    ramp = uniform(n, saturation="charge")
    answer = paper_solve("H158", precision=0.01, magnitude=20.0, ramp=ramp, scene=scenes.SceneModel(background_e=background))
    # The peak charge of the shipped table's stars (astropy), scaled as 10^(-0.4 m): the limits.
    limit = shipped.saturation_magnitude("H158", 18, FULL_WELL / (2 / n) - background, T)
    assert answer.saturation_magnitude == pytest.approx(limit, abs=1e-9)
    assert answer.final_frame_saturation_magnitude == pytest.approx(
        shipped.saturation_magnitude("H158", 18, FULL_WELL - background, T), abs=1e-12
    )
    assert answer.fidelity == "linear" and "the scene has no table" in answer.conditions["ramp_slopes_from"]
    assert answer.conditions["scene"]["background_e"] == background and answer.tolerance > 0
    # IPC goes through the ramp too; brighter-fatter is the one effect a ramp refuses (ramps.check_scene).
    ipc = scenes.SceneModel(ipc=((0.0, 0.02, 0.0), (0.02, 0.92, 0.02), (0.0, 0.02, 0.0)))
    assert paper_solve("H158", precision=0.01, magnitude=20.0, ramp=ramp, scene=ipc).tolerance > 0
    with pytest.raises(InputError) as error:
        paper_solve("H158", precision=0.01, magnitude=20.0, ramp=ramp, scene=scenes.SceneModel(bfe_coefficient=1e-7))
    assert error.value.argument == "scene" and "brighter_fatter" in error.value.reason


def test_solver_without_a_ramp_reports_one_saturation_rule():
    s = paper_solve("H158", precision=0.01, magnitude=19.0)
    assert s.final_frame_saturation_magnitude == s.saturation_magnitude and "ramp" not in s.conditions


# --- the command line and the service -----------------------------------------------------------


def _cli_json(capsys, *argv):
    from nlpsf import cli

    # The ramp's own rules on the paper's scene (the default is the Roman star's).
    code = cli.main([*argv, "--scene", "paper"] if argv[0] in ("solve", "simulate", "slopes") else list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_cli_solve_with_a_ramp_reports_both_saturation_rules(capsys):
    code, out, _ = _cli_json(capsys, "solve", "--precision", "0.01", "--magnitude", "19", "--ramp", "8", "--json")
    assert code == 0
    payload = json.loads(out)
    library = paper_solve("H158", precision=0.01, magnitude=19.0, ramp=uniform(8))
    assert payload["tolerance"] == library.tolerance
    x = (1 - math.sqrt(1 - 4 * BETA * FULL_WELL)) / (2 * BETA)  # romancal's signal rule at the second read
    shift = 2.5 * math.log10(x / (2 / 8 * FULL_WELL))
    assert payload["saturation_magnitude"] == pytest.approx(payload["final_frame_saturation_magnitude"] - shift, abs=1e-9)
    code, out, _ = _cli_json(capsys, "solve", "--precision", "0.01", "--magnitude", "19", "--ramp", "8")
    assert code == 0 and "(ramp rule: resultant 2, the one a slope needs)" in out
    # An MA table's exposure defaults to its last read.
    code, out, _ = _cli_json(capsys, "solve", "--precision", "0.01", "--magnitude", "19", "--ma-table", "romanisim-109", "--json")
    assert code == 0 and json.loads(out)["exptime"] == pytest.approx(ramps.load_ma_table("romanisim-109").duration_s)


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["--ramp", "0"], "--ramp"),
        (["--ma-table", "nope"], "--ma-table"),
        (["--ramp", "4", "--ramp-fit", "optimal", "--read-noise", "-1"], "--read-noise"),
    ],
)
def test_cli_bad_ramps_exit_2_naming_the_option(capsys, argv, option):
    code, out, err = _cli_json(capsys, "simulate", "--realizations", "2", *argv, "--json")
    assert code == 2 and out == "" and f"error: {option}:" in err


def test_cli_simulate_and_slopes_with_a_ramp_match_the_library(capsys):
    code, out, _ = _cli_json(capsys, "simulate", "--realizations", "4", "--magnitude", "19", "--ramp", "5", "--json")
    assert code == 0
    payload = json.loads(out)
    config = SimulationConfig(realizations=4, ramp=uniform(5))
    assert payload["dR_over_R"]["mean"] == pytest.approx(simulate(config, [19.0], [BETA])[0].dR_over_R.mean, rel=1e-12)
    assert payload["conditions"]["ramp"]["ma_table"] == "uniform-5" and payload["ramp"]["fitted_on_all"] > 0
    code, out, _ = _cli_json(
        capsys, "slopes", "--realizations", "4", "--magnitude", "19", "--ma-table", "romanisim-110", "--ramp-fit", "optimal",
        "--method", "linear", "--json",
    )  # fmt: skip
    assert code == 0 and json.loads(out)[0]["conditions"]["ramp"]["fit"] == "optimal"


# --- read noise: the SCA's official value unless given ------------------------------------------


def test_read_noise_defaults_to_the_scas_official_value_and_says_where_it_came_from(capsys, tmp_path, make_client):
    from nlpsf.roman import backgrounds

    # Library: the SCA's median CDS noise / sqrt(2) (backgrounds, checked against the CDS table there).
    official = {sca: backgrounds.read_noise(sca) for sca in (1, 3, 18)}
    assert official[1] != official[18]  # so the look-up is per SCA, not one number
    for sca, value in official.items():
        ramp, _ = ramps.build(6, fit="optimal", sca=sca)
        assert ramp.read_noise_e == value
        source = ramp.conditions(T)["read_noise_source"]
        assert f"SCA {sca}" in source and "CDS" in source
        # The optimal fit is the one an explicit, equal read noise gives (same weights).
        explicit = ramps.Ramp.uniform(6, T, "optimal", value)
        assert ramp == explicit and explicit.conditions(T)["read_noise_source"] == "given"
        charge = np.array([1e3, 5e4])
        kept = np.array([6, 6])
        np.testing.assert_array_equal(ramps.slope_weights(charge, kept, ramp, T), ramps.slope_weights(charge, kept, explicit, T))
    given, _ = ramps.build(ma_table="romanisim-109", read_noise_e=7.0, sca=1)
    assert given.read_noise_e == 7.0 and given.conditions(given.table.duration_s)["read_noise_source"] == "given"
    with pytest.raises(InputError, match="sca"):
        ramps.build(6, sca=19)
    # CLI: --read-noise omitted on SCA 3.
    code, out, _ = _cli_json(capsys, "solve", "--sca", "3", "--precision", "0.01", "--magnitude", "19", "--ramp", "8", "--json")
    assert code == 0
    conditions = json.loads(out)["conditions"]["ramp"]
    assert conditions["read_noise_e"] == official[3] and "SCA 3" in conditions["read_noise_source"]
    code, out, _ = _cli_json(
        capsys, "solve", "--sca", "3", "--precision", "0.01", "--magnitude", "19", "--ramp", "8", "--read-noise", "5", "--json"
    )
    assert json.loads(out)["conditions"]["ramp"]["read_noise_source"] == "given"
    # A batch reads each row's SCA.
    batch = tmp_path / "rows.csv"
    batch.write_text("band,sca,magnitude,precision\nH158,1,19,0.01\nH158,3,19,0.01\n")
    code, out, _ = _cli_json(capsys, "solve", "--batch", str(batch), "--ramp", "8", "--json")
    assert code == 0
    assert [row["solution"]["conditions"]["ramp"]["read_noise_e"] for row in json.loads(out)] == [official[1], official[3]]
    # Web: the same rule in /solve (and the simulation models).
    with make_client() as client:
        body = {"band": "H158", "sca": 3, "precision": 0.01, "magnitude": 19.0, "ramp": 8, "scene": "paper"}
        answer = client.post("/api/v1/solve", json=body)
        assert answer.status_code == 200, answer.text
        assert answer.json()["conditions"]["ramp"]["read_noise_e"] == official[3]
        assert client.post("/api/v1/solve", json={**body, "read_noise": 5.0}).json()["conditions"]["ramp"]["read_noise_e"] == 5.0
        assert client.get("/api/v1/meta").json()["defaults"]["simulation"]["read_noise"] is None


@pytest.mark.parametrize("beta", [0.0, BETA, 2e-6])
def test_the_exact_saturation_limit_of_the_signal_rule_is_the_quadratics_root(beta):
    # Uniform reads (one per resultant: no dilution): the second resultant's signal q t2 - beta (q t2)^2
    # reaches the threshold W at q t2 = (1 - sqrt(1 - 4 beta W)) / (2 beta) (W for beta = 0).
    n = 8
    ramp = uniform(n)
    tau2 = 2 / n
    x = FULL_WELL if beta == 0 else (1 - math.sqrt(1 - 4 * beta * FULL_WELL)) / (2 * beta)
    assert ramp.limit_charge(T, FULL_WELL, beta) == pytest.approx(x / tau2, rel=1e-12)
    shift = ramp.saturation_shift_mag(T, FULL_WELL, beta)
    assert shift == pytest.approx(2.5 * math.log10(x / tau2 / FULL_WELL), rel=1e-12)
    # A background fills part of the well: the star's own limit drops by it.
    assert ramp.limit_charge(T, FULL_WELL, beta, 500.0) == pytest.approx(x / tau2 - 500.0, rel=1e-12)
    # The linear estimate (no full well given) is the charge rule's, exact at beta = 0.
    assert ramp.saturation_shift_mag(T) == pytest.approx(2.5 * math.log10(n / 2), rel=1e-12)
    charge_rule = uniform(n, saturation="charge")
    assert charge_rule.saturation_shift_mag(T, FULL_WELL, beta) == pytest.approx(2.5 * math.log10(n / 2), rel=1e-12)


@pytest.mark.parametrize("over", [1.0001, 1.3, 100.0])
def test_a_quadratic_whose_signal_never_reaches_the_well_is_refused_not_searched(over, make_client):
    # S = Q - beta Q^2 peaks at 1 / (4 beta): past 4 beta W = 1 the root above has no real value, no
    # charge is ever flagged by the signal rule, and the limit (the search for it) does not exist.
    n = 8
    ramp, tau2 = uniform(n), 2 / n
    edge = 1 / (4 * FULL_WELL)
    x = (1 - math.sqrt(1 - 4 * (0.999 * edge) * FULL_WELL)) / (2 * 0.999 * edge)
    assert ramp.limit_charge(T, FULL_WELL, 0.999 * edge) == pytest.approx(x / tau2, rel=1e-9)
    with pytest.raises(InputError) as refused:
        ramp.limit_charge(T, FULL_WELL, over * edge)
    assert refused.value.argument == "beta0" and "1/(4 beta)" in refused.value.reason
    # The charge rule judges the charge, not the signal: its limit stands whatever beta is.
    assert uniform(n, saturation="charge").limit_charge(T, FULL_WELL, over * edge) == pytest.approx(FULL_WELL / tau2, rel=1e-9)
    # Every entry point refuses it before any work (the service had searched forever).
    body = {"band": "H158", "magnitude": 25.0, "tolerance": 1e-4, "scene": "paper", "ramp": 2, "beta0": over * edge}
    with make_client() as client:
        for path in ("/api/v1/solve", "/api/v1/page/limits", "/api/v1/page/requirement"):
            answer = client.post(path, json=body)
            assert answer.status_code == 422 and "beta0" in answer.text, (path, answer.text)


# --- the ramp's rules and the linearisation state from every entry point -------------------------


def test_the_ramp_rules_reach_the_solver_from_the_cli_and_a_json_body(capsys):
    # The charge rule at the resultant a slope needs, for a linear detector judged by its charge:
    # k = 2 (romancal: one resultant gives no slope) or k = 1 (through zero), ending at k T / n.
    from nlpsf.request.resolve import SolveRequest

    n = 8
    frame = paper_solve("H158", precision=0.01, magnitude=19.0).saturation_magnitude
    for single, needed in (("unusable", 2), ("through_zero", 1)):
        argv = ["solve", "--precision", "0.01", "--magnitude", "19", "--ramp", str(n), "--ramp-saturation", "charge"]
        code, out, _ = _cli_json(capsys, *argv, "--single-resultant", single, "--json")
        assert code == 0
        payload = json.loads(out)
        assert payload["saturation_magnitude"] == pytest.approx(frame - 2.5 * math.log10(n / needed), abs=1e-9)
        assert payload["conditions"]["ramp"]["saturation"] == "charge"
        assert payload["conditions"]["ramp"]["single_resultant"] == single
        body = {"band": "H158", "precision": 0.01, "magnitude": 19.0, "ramp": n, "scene": "paper"}
        request = SolveRequest.from_json({**body, "ramp_saturation": "charge", "ramp_single_resultant": single})
        assert solver.answer(request).saturation_magnitude == payload["saturation_magnitude"]
    # Neither given: romancal's rules (ramps.build's defaults).
    assert SolveRequest.from_json(body).ramp.saturation == "signal"
    assert SolveRequest.from_json(body).ramp.single_resultant == "unusable"
    with pytest.raises(InputError) as error:
        SolveRequest.from_json({**body, "ramp_single_resultant": "twice"})
    assert error.value.argument == "ramp_single_resultant"


def test_cli_slopes_takes_the_linearisation_state(capsys):
    # "corrected" with the earlier residual model (per_read_beta): the slope at the residual NL
    # CORRECTED_RESIDUAL x beta0. A final frame's saturation does not depend on beta, so that is the
    # paper's slope taken at beta0' = CORRECTED_RESIDUAL x beta0.
    argv = ["slopes", "--realizations", "4", "--magnitude", "18", "--method", "linear", "--json"]
    code, out, _ = _cli_json(capsys, *argv, "--linearise-at", "corrected", "--residual-nl", "per_read_beta")
    assert code == 0
    earlier = json.loads(out)[0]
    assert earlier["conditions"]["linearised_at"]["state"] == "corrected"
    assert earlier["conditions"]["residual_nl"] == "per_read_beta"
    config = SimulationConfig(realizations=4, method="linear")
    at_residual = slopes(config, [18.0], beta0=experiment.CORRECTED_RESIDUAL * BETA)[0]
    assert earlier["bias_slope"]["dR_over_R"]["mean"] == pytest.approx(at_residual.bias["dR_over_R"].mean, rel=1e-12)
    # The default model corrects the raw beta0 on the final frame (one resultant, no IPC): exactly, so the
    # calibration error acts on the linear image, the paper's slope as beta0 -> 0 (here 1e-6 beta0).
    code, out, _ = _cli_json(capsys, *argv, "--linearise-at", "corrected")
    corrected = json.loads(out)[0]
    assert corrected["conditions"]["residual_nl"] == "per_resultant_correction"
    vanishing = slopes(config, [18.0], beta0=1e-6 * BETA)[0]
    assert corrected["bias_slope"]["dR_over_R"]["mean"] == pytest.approx(vanishing.bias["dR_over_R"].mean, rel=1e-5)
    code, out, _ = _cli_json(capsys, *argv)
    raw = json.loads(out)[0]
    assert "linearised_at" not in raw["conditions"]
    # At m = 18 the NL is not linear in beta: the slope at beta0 is measurably not the corrected one.
    assert raw["bias_slope"]["dR_over_R"]["mean"] != pytest.approx(corrected["bias_slope"]["dR_over_R"]["mean"], rel=1e-3)


@pytest.fixture(scope="module")
def h158():
    config = SimulationConfig(band="H158", realizations=12)
    return config, experiment.prepare(config)


def test_the_corrected_state_is_the_first_order_slope_at_vanishing_nl(h158):
    # Independent of the finite difference: metric(b) / b at b = 1e-4 beta0 is the slope at beta -> 0 to
    # 1e-4 of its curvature; the corrected state (residual 1e-2 beta0) must sit within 1e-2 of the 3.4 %
    # that separates the two states, and the paper state must not.
    config, scene = h158
    tiny = 1e-4 * BETA
    first_order = simulate(config, [18.3], [tiny], scene=scene)[0].dR_over_R.mean / tiny
    corrected = slopes(config, [18.3], scene=scene, linearise_at="corrected")[0]
    paper = slopes(config, [18.3], scene=scene)[0]
    assert corrected.bias["dR_over_R"].mean == pytest.approx(first_order, rel=1e-3)
    assert paper.bias["dR_over_R"].mean / first_order - 1 > 0.02
    assert corrected.conditions["linearised_at"]["state"] == "corrected"


def test_a_ramp_keeps_the_raw_saturation_flags_in_the_corrected_state(h158):
    _config, scene = h158
    table = ramps.load_ma_table("romanisim-110")
    ramp = ramps.Ramp(table, "ols", 10.0, saturation="signal", single_resultant="unusable")
    cfg = SimulationConfig(band="H158", realizations=12, exptime_s=table.duration_s, ramp=ramp)
    prepared = experiment.Scene(cfg, scene.psf, scene.offsets, scene.stamps, scene.reference, 0.0)
    magnitude = 16.0  # between the limits: the core drops resultants
    paper = slopes(cfg, [magnitude], scene=prepared)[0]
    corrected = slopes(cfg, [magnitude], scene=prepared, linearise_at="corrected")[0]
    assert paper.extras["ramp"]["fitted_on_fewer"] > 0
    assert corrected.extras["ramp"] == paper.extras["ramp"]
    # Flagging at the residual instead (what the raw detector does not do) keeps more resultants.
    residual = simulate(cfg, [magnitude], [1e-2 * BETA], scene=prepared)[0]
    assert residual.extras["ramp"]["pixels_by_resultants"] != paper.extras["ramp"]["pixels_by_resultants"]


def test_a_ramps_conditions_are_its_own_and_its_own_copy():
    # Two ramps equal but for where their read noise came from (ramps compare without it) each
    # state their own source; changing one answer's conditions changes no other's.
    table = ramps.MATable(((1,), (2, 3), (4, 5, 6)), 3.04, name="test-table")
    one = ramps.Ramp(table, read_noise_e=8.0, read_noise_source="SCA 14")
    other = ramps.Ramp(table, read_noise_e=8.0, read_noise_source="SCA 15")
    assert one == other
    first, second = one.conditions(30.0), other.conditions(30.0)
    assert (first["read_noise_source"], second["read_noise_source"]) == ("SCA 14", "SCA 15")
    first["read_pattern"][0].append(99)
    first["fit"] = "changed"
    again = one.conditions(30.0)
    assert again["read_pattern"] == [[1], [2, 3], [4, 5, 6]] and again["fit"] == "ols"
