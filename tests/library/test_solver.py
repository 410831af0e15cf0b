"""The two-of-three calculator: the paper's example, round trips, extremes, refusals, fidelity, a shear
budget in place of the tolerance, and scatter averaged over stars."""

import functools
import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nlpsf import cli, roman
from nlpsf.checks import InputError
from nlpsf.flags import FlagCode, codes
from nlpsf.request import shear
from nlpsf.sim import scene as scenes
from nlpsf.slopes import tables
from nlpsf.solve import solver, validity

from .. import shipped

# These tests check the paper's tables and relations: the paper's scene (the default is the Roman star's).
paper_solve = functools.partial(solver.solve, scene="paper")

TABLES = tables.load_tables()


def test_the_papers_worked_example():
    # H158, m = 18.3, Delta R / R = 1e-4, beta0 = 5e-7: "beta must be calibrated to ~1 %".
    s = paper_solve("H158", magnitude=18.3, tolerance=1e-4)
    assert s.solved_for == "precision"
    assert 0.005 < s.precision < 0.015
    # T = |c| p beta0, with c read from the shipped ECSV by astropy and interpolated by scipy (not
    # the table object the solver read).
    slope = float(shipped.slope("H158", 18, "size", "bias", 18.3))
    assert s.precision == pytest.approx(1e-4 / (abs(slope) * 5e-7), rel=1e-12)
    assert s.slope == pytest.approx(slope, rel=1e-9)
    # And its ellipticity example: |De| = 4.7e-5 -> a few per cent (paper: ~2.4 % with Cycle-5 optics).
    e = paper_solve("H158", metric="e", magnitude=18.3, tolerance=4.7e-5)
    assert 0.01 < e.precision < 0.2


bands = st.sampled_from(roman.BANDS)
scas = st.integers(1, 18)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    band=bands,
    sca=scas,
    metric=st.sampled_from(tables.METRICS),
    mode=st.sampled_from(tables.MODES),
    offset=st.floats(0.05, 7.0),
    log_precision=st.floats(-4, -0.5),
)
def test_solving_each_member_returns_the_others(band, sca, metric, mode, offset, log_precision):
    table = TABLES.get(band, sca)
    magnitude = table.saturation() + offset
    precision = 10**log_precision
    forward = paper_solve(band, sca, metric, mode, precision=precision, magnitude=magnitude)
    tolerance = forward.tolerance
    assert forward.uncertainty is not None and forward.uncertainty >= 0
    back = paper_solve(band, sca, metric, mode, tolerance=tolerance, magnitude=magnitude)
    assert abs(back.precision - precision) <= max(back.uncertainty, 1e-12 * precision)
    slopes = table.lookup(metric, mode, np.arange(magnitude, 28.0, 0.02))[0]
    if metric in ("size", "e") or np.all(np.abs(slopes) <= abs(forward.slope) * (1 + 1e-9)):
        # The magnitude comes back where every fainter star also meets the tolerance, which for a
        # monotonic |c| is the magnitude we started from.
        m = paper_solve(band, sca, metric, mode, precision=precision, tolerance=tolerance)
        if m.binding_limit == "nonlinearity":
            assert abs(m.magnitude - magnitude) <= max(m.uncertainty, 1e-6)


def test_solving_magnitude_says_which_limit_binds():
    nl = paper_solve("H158", precision=0.01, tolerance=1e-4)
    assert nl.binding_limit == "nonlinearity" and nl.magnitude > nl.saturation_magnitude
    assert nl.brightest_usable_magnitude == nl.magnitude
    loose = paper_solve("H158", precision=0.01, tolerance=0.05)
    assert loose.binding_limit == "saturation"
    assert loose.magnitude == pytest.approx(loose.saturation_magnitude)
    assert FlagCode.SATURATION_BINDS in codes(loose.flags)


@pytest.mark.parametrize("tolerance", [1e-9, 1e-6, 1e-3, 1.0])
def test_extreme_tolerances(tolerance):
    s = paper_solve("J129", 4, precision=0.01, tolerance=tolerance)
    assert s.magnitude is not None and math.isfinite(s.magnitude)
    if tolerance == 1e-9:
        assert s.magnitude > 28 and FlagCode.EXTRAPOLATED_ANSWER in codes(s.flags)
    if tolerance == 1.0:
        assert s.binding_limit == "saturation"


@pytest.mark.parametrize("precision", [1e-6, 1e-3, 1.0, 10.0])
def test_extreme_precisions(precision):
    s = paper_solve("F184", 2, precision=precision, magnitude=19.0)
    assert s.tolerance > 0 and math.isfinite(s.tolerance)
    assert s.tolerance == pytest.approx(abs(float(shipped.slope("F184", 2, "size", "bias", 19.0))) * precision * 5e-7, rel=1e-9)
    peak = float(shipped.peak_electrons("F184", 2, 19.0))
    # Past delta_beta * Q_peak = 5 % the error is no longer linear in delta_beta: flagged.
    assert (FlagCode.OUTSIDE_LINEAR_REGIME in codes(s.flags)) == (precision * 5e-7 * peak > validity.LINEAR_REGIME_LIMIT)


def test_magnitudes_brighter_than_saturation_and_fainter_than_30():
    table = TABLES.get("Y106", 9)
    saturated = paper_solve("Y106", 9, precision=0.01, magnitude=table.saturation() - 0.5)
    assert FlagCode.STAR_SATURATED in codes(saturated.flags)
    faint = paper_solve("Y106", 9, precision=0.01, magnitude=31.0)
    assert FlagCode.EXTRAPOLATED_FAINT in codes(faint.flags)
    inside = paper_solve("Y106", 9, precision=0.01, magnitude=27.0)
    assert faint.tolerance == pytest.approx(inside.tolerance * 10 ** (-0.4 * 4), rel=2e-3)
    with pytest.raises(InputError, match="magnitude") as error:
        paper_solve("Y106", 9, precision=0.01, magnitude=table.magnitudes[0] - 1)
    assert "too bright" in str(error.value) or "past the tables" in str(error.value)


@pytest.mark.parametrize(("band", "sca"), [("H158", 18), ("Z087", 1)])
def test_a_brightest_star_past_the_tables_is_refused(band, sca):
    # The tables hold the NL strength beta0 x Q_peak up to their own beta0 times their brightest row's
    # peak charge (read from the ECSV here). Where the error stays below the tolerance everywhere, the
    # answer is the saturation magnitude, whose strength is beta0 x the full well: past that reach its
    # slope is not known (it was answered with a null slope and flags that said both things), so it
    # is refused, as a given magnitude past the tables is; inside it, it is answered with its slope.
    settings = shipped._table().meta["settings"]
    reach = settings["beta0"] * shipped._rows(band, sca)["peak_electrons"].max()
    limit = reach / settings["full_well_e"]
    inside = paper_solve(band, sca, precision=0.5, tolerance=0.5, beta0=0.98 * limit)
    assert inside.binding_limit == "saturation" and math.isfinite(inside.slope)
    for beta0 in (1.02 * limit, 1e-4):
        with pytest.raises(InputError) as error:
            paper_solve(band, sca, precision=0.5, tolerance=0.5, beta0=beta0)
        assert error.value.argument == "beta0" and f"{limit:.3g}" in str(error.value)


def test_every_brightest_star_answer_has_a_finite_uncertainty_and_conservative_bound():
    # A crossing within d ln|c|/dm's step of the tables' bright end (R062 SCA 10, e2, tolerance 1e-6,
    # precision 1e-3: at m = 17.259, 0.009 mag from its end at 17.25) had a NaN log derivative and so a NaN
    # conservative bound (null in JSON). Over bands, SCAs, metrics and demands, every answer's
    # numbers are finite.
    for band in roman.BANDS:
        for sca in (1, 10, 18):
            for metric in ("size", "e1", "e2", "e"):
                for tolerance, precision in ((1e-6, 1e-3), (1e-4, 1e-2), (1e-3, 0.5)):
                    s = paper_solve(band, sca, metric=metric, tolerance=tolerance, precision=precision)
                    where = (band, sca, metric, tolerance, precision)
                    assert math.isfinite(s.magnitude) and math.isfinite(s.uncertainty), where
                    assert math.isfinite(s.conservative["relative_slope_bound"]), where
                    assert s.conservative["magnitude"] is not None and math.isfinite(s.conservative["magnitude"]), where


@pytest.mark.parametrize("beta0", [1e-9, 1e-8, 5e-7, 2e-6, 1e-5])
def test_beta0_range(beta0):
    s = paper_solve("H158", precision=0.01, magnitude=21.0, beta0=beta0)
    assert math.isfinite(s.tolerance) and s.conditions["beta0"] == beta0
    m = paper_solve("H158", precision=0.01, tolerance=1e-5, beta0=beta0)
    assert math.isfinite(m.magnitude)
    # More nonlinearity: the same tolerance needs fainter stars.
    if beta0 > 5e-7:
        assert m.magnitude > paper_solve("H158", precision=0.01, tolerance=1e-5).magnitude


def test_a_non_monotonic_detector_is_refused_with_the_reason():
    with pytest.raises(InputError, match="magnitude") as error:
        paper_solve("H158", precision=0.01, magnitude=18.3, beta0=1e-5)
    assert "not monotonic" in str(error.value) and "beta0=1e-05" in str(error.value)


def test_exposure_and_full_well_change_the_answer_as_flux_does():
    base = paper_solve("H158", precision=0.01, tolerance=1e-4)
    longer = paper_solve("H158", precision=0.01, tolerance=1e-4, exptime=2 * 168.1)
    assert longer.magnitude == pytest.approx(base.magnitude + 2.5 * math.log10(2), abs=1e-6)
    deeper = paper_solve("H158", precision=0.01, tolerance=1e-4, full_well=2.2e5)
    assert deeper.magnitude == pytest.approx(base.magnitude)
    assert deeper.saturation_magnitude == pytest.approx(base.saturation_magnitude - 2.5 * math.log10(2))


def test_a_slope_through_zero_is_handled_not_divided_by():
    # K213 SCA 1: the e2 bias slope changes sign near m = 17.8.
    table = TABLES.get("K213", 1)
    magnitudes = np.linspace(table.magnitudes[0], 19.0, 2000)
    values = shipped.slope("K213", 1, "e2", "bias", magnitudes)
    zero = magnitudes[np.argmin(np.abs(values))]
    s = paper_solve("K213", 1, metric="e2", tolerance=1e-6, magnitude=float(zero), full_well=1e7)
    assert s.precision is None or s.precision > 1e3
    if s.precision is None:
        assert FlagCode.SLOPE_CONSISTENT_WITH_ZERO in codes(s.flags)
    # A tolerance met only fainter than the crossing: the answer must not stop at the zero, where
    # |c| is small, but at the faint-side magnitude where every fainter star meets the tolerance.
    c19 = abs(float(shipped.slope("K213", 1, "e2", "bias", 19.0)))
    m = paper_solve("K213", 1, metric="e2", precision=0.01, tolerance=0.9 * c19 * 0.01 * 5e-7, full_well=1e7)
    assert m.magnitude > 19.0 > zero
    fainter = np.abs(shipped.slope("K213", 1, "e2", "bias", np.arange(m.magnitude + 0.001, 28, 0.01)))
    assert np.all(fainter * 0.01 * 5e-7 <= 0.9 * c19 * 0.01 * 5e-7 * (1 + 1e-9))
    assert FlagCode.SLOPE_CHANGES_SIGN in codes(m.flags)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"precision": 0.01}, "tolerance"),
        ({"precision": 0.01, "tolerance": 1e-4, "magnitude": 20.0}, "magnitude"),
        ({"precision": -0.01, "magnitude": 20.0}, "precision"),
        ({"precision": float("nan"), "magnitude": 20.0}, "precision"),
        ({"tolerance": float("inf"), "magnitude": 20.0}, "tolerance"),
        ({"tolerance": 0.0, "magnitude": 20.0}, "tolerance"),
        ({"precision": 0.01, "magnitude": 99.0}, "magnitude"),
        ({"precision": 0.01, "magnitude": 20.0, "beta0": 0.0}, "beta0"),
        ({"precision": 0.01, "magnitude": 20.0, "exptime": -5.0}, "exptime"),
        ({"precision": 0.01, "magnitude": 20.0, "metric": "size2"}, "metric"),
        ({"precision": 0.01, "magnitude": 20.0, "mode": "mean"}, "mode"),
        ({"precision": 0.01, "magnitude": 20.0, "sca": 19}, "sca"),
        ({"precision": 0.01, "magnitude": 20.0, "fidelity": "best"}, "fidelity"),
        ({"precision": 0.01, "magnitude": 20.0, "accuracy": -1.0}, "accuracy"),
    ],
)
def test_bad_requests_are_refused_naming_the_argument(kwargs, name):
    with pytest.raises(InputError) as error:
        paper_solve(kwargs.pop("band", "H158"), **kwargs)
    assert error.value.argument == name


def test_unknown_band_is_refused():
    with pytest.raises(InputError, match="band"):
        paper_solve("X123", precision=0.01, magnitude=20)


def test_answers_carry_conditions_and_uncertainty():
    d = paper_solve("J129", 11, "e1", "scatter", beta0=4e-7, exptime=100.0, precision=0.1, magnitude=20.0).to_dict()
    for key in ("precision", "tolerance", "magnitude", "solved_for", "uncertainty", "slope", "saturation_magnitude", "flags"):
        assert key in d
    c = d["conditions"]
    assert (c["band"], c["sca"], c["exptime_s"], c["beta0"], c["fidelity"]) == ("J129", 11, 100.0, 4e-7, "table")
    assert d["uncertainty"] >= d["uncertainty_statistical"] > 0
    assert d["uncertainty_fidelity"] > 0  # the table level's measured error against the polychromatic reference
    json.dumps(d, allow_nan=False)


def test_fresh_simulation_fidelity_agrees_with_the_table():
    table = paper_solve("H158", precision=0.01, magnitude=19.3)
    linear = paper_solve("H158", precision=0.01, magnitude=19.3, fidelity="linear")
    assert linear.fidelity == "linear"
    assert abs(linear.tolerance - table.tolerance) <= table.uncertainty_statistical + linear.uncertainty_statistical
    mc = paper_solve("H158", precision=0.01, tolerance=1e-4, fidelity="monte_carlo")
    assert mc.magnitude == pytest.approx(paper_solve("H158", precision=0.01, tolerance=1e-4).magnitude, abs=0.01)


def test_accuracy_picks_the_cheapest_level_that_meets_it():
    from nlpsf.slopes import fidelity

    errors = fidelity.measured()["errors"]["H158"]["bias"]["size"]
    paper = scenes.preset("paper")  # the tables' own scene: without a scene, accuracy holds to the Roman default
    loose = solver.solve("H158", precision=0.01, magnitude=20.0, accuracy=2 * errors["table"], scene=paper)
    assert loose.fidelity == "table"
    tight = solver.solve("H158", precision=0.01, magnitude=20.0, accuracy=0.5 * errors["table"], scene=paper)
    assert tight.fidelity == "polychromatic"
    assert tight.uncertainty_fidelity / tight.tolerance <= 0.5 * errors["table"]


def test_cli_solve_json_contract(capsys):
    code = cli.main(
        [
            "solve",
            "--band",
            "H158",
            "--sca",
            "18",
            "--metric",
            "size",
            "--mode",
            "bias",
            "--beta0",
            "5e-7",
            "--exptime",
            "168.1",
            "--tolerance",
            "1e-4",
            "--magnitude",
            "18.3",
            "--json",
        ]
    )
    payload = json.loads(capsys.readouterr().out)
    assert code == 0
    assert {"precision", "tolerance", "magnitude", "solved_for", "uncertainty", "slope", "saturation_magnitude", "flags"} <= set(
        payload
    )
    assert payload["solved_for"] == "precision"


def test_cli_solve_refuses_one_member(capsys):
    assert cli.main(["solve", "--band", "H158", "--magnitude", "18.3", "--json"]) == 2
    assert "exactly two" in capsys.readouterr().err


def test_answers_carry_the_optical_model_uncertainty_in_quadrature():
    # scripts/psf_statistics.py measured how far the slopes move when nlpsf's PSF is made as wide as
    # the official one; the answer's uncertainty holds that share beside the statistical and
    # fidelity ones, scaled like them (T = c p beta0: relative on p and T).
    d = paper_solve("Y106", 18, magnitude=20.0, tolerance=1e-4).to_dict()
    model = roman.optical_model_uncertainty("Y106", "size")
    assert d["uncertainty_optical_model"] == pytest.approx(d["precision"] * model, rel=1e-12)
    # Beside the scene's model part (effects left out, pupil-scale rule): the pupil rule and the
    # official-PSF comparison both measure the optics, so the larger of the two counts.
    effects, pupil = (d["precision"] * d["model"][k] for k in ("effects_relative", "pupil_scale_relative"))
    assert d["uncertainty_model"] == pytest.approx(math.hypot(effects, pupil), rel=1e-12)
    parts = (d["uncertainty_statistical"], d["uncertainty_fidelity"], effects, max(d["uncertainty_optical_model"], pupil))
    assert d["uncertainty"] == pytest.approx(math.hypot(*parts), rel=1e-12)
    assert d["conditions"]["throughput"] == TABLES.meta["settings"]["throughput"]
    # One ellipticity component's share is stated against |c_e|: relative to e1 alone it is larger.
    e = paper_solve("Y106", 18, "e", magnitude=20.0, tolerance=1e-4)
    e1 = paper_solve("Y106", 18, "e1", magnitude=20.0, tolerance=1e-4)
    assert e.uncertainty_optical_model / e.precision == pytest.approx(roman.optical_model_uncertainty("Y106", "e"))
    assert e1.uncertainty_optical_model / e1.precision >= e.uncertainty_optical_model / e.precision


def test_another_throughput_relabels_the_tables_and_agrees_with_a_fresh_simulation_under_it():
    default = paper_solve("J129", 11, magnitude=19.0, tolerance=1e-4)
    galsim = paper_solve("J129", 11, magnitude=19.0, tolerance=1e-4, throughput="galsim-2021")
    assert galsim.conditions["throughput"] == "galsim-2021" and default.conditions["throughput"] == "roman-2024"
    assert FlagCode.THROUGHPUT_RELABELLED in codes(galsim.flags)
    # More electrons per magnitude in GalSim's 2021 curve: stars saturate fainter, by the zero-point gap.
    from nlpsf.roman import photometry

    gap = photometry.zero_point("J129", sca=11, throughput="galsim-2021") - photometry.zero_point(
        "J129", sca=11, throughput="roman-2024"
    )
    assert galsim.saturation_magnitude - default.saturation_magnitude == pytest.approx(gap, abs=1e-9)
    # A fresh linear simulation on GalSim's throughput (its own PSF wavelength) agrees within the
    # relabelling error the flag quotes.
    fresh = paper_solve("J129", 11, magnitude=19.0, tolerance=1e-4, throughput="galsim-2021", fidelity="linear")
    assert fresh.precision == pytest.approx(galsim.precision, rel=tables.RELABEL_ERROR["J129"][0] + 1e-3)
    assert galsim.uncertainty_optical_model > default.uncertainty_optical_model * galsim.precision / default.precision


@pytest.mark.slow
def test_another_pupil_scale_rule_is_simulated_with_that_rule_and_says_so(capsys):
    from nlpsf.sim import experiment

    request = {"band": "H158", "sca": 18, "magnitude": 18.3, "precision": 0.01}
    official = paper_solve(**request, pupil_scale="official")
    assert official.conditions["pupil_scale"] == "official" and official.conditions["fidelity"] == "linear"
    assert FlagCode.PUPIL_SCALE_SIMULATED in codes(official.flags)
    # The slope is the simulator's with that rule at the tables' settings, not the tables' galsim one.
    settings = TABLES.get("H158", 18).settings
    config = experiment.SimulationConfig(
        band="H158",
        sca=18,
        realizations=int(settings["realizations"]),
        seed=int(settings["seed"]),
        method="linear",
        weight_cut_rho2=float(settings["weight_cut_rho2"]),
        pupil_scale="official",
    )
    direct = experiment.slopes(config, [18.3])[0].slope("bias", ("dR_over_R",))[0]
    assert official.slope == pytest.approx(direct, rel=1e-12)
    galsim = paper_solve(**request, fidelity="linear")
    assert abs(official.slope / galsim.slope - 1) > 0.01
    # The tables' own rule asks for no simulation.
    assert paper_solve(**request, pupil_scale="galsim").conditions["fidelity"] == "table"
    with pytest.raises(InputError, match="pupil_scale"):
        paper_solve(**request, pupil_scale="hubble")
    code = cli.main(
        ["solve", "--band", "H158", "--magnitude", "18.3", "--precision", "0.01", "--pupil-scale", "official", "--json",
         "--scene", "paper"]
    )  # fmt: skip
    assert code == 0
    assert json.loads(capsys.readouterr().out)["slope"] == pytest.approx(official.slope, rel=1e-12)


@pytest.mark.parametrize(("metric", "kind"), [("size", "m"), ("e1", "c"), ("e2", "c"), ("e", "c")])
def test_a_shear_budget_gives_the_same_answer_as_the_tolerance_it_implies(metric, kind):
    ratio = [(1.2, 0.3), (1.5, 0.5), (2.0, 0.2)]
    budget = {f"shear_{kind}": 1e-3 if kind == "m" else 2e-4}
    by_budget = paper_solve("H158", metric=metric, magnitude=19.0, size_ratio=ratio, **budget)
    effective = shear.check_size_ratio(ratio).effective
    tolerance = 1e-3 * effective**2 / 2 if kind == "m" else 2 * 2e-4 * effective**2
    by_tolerance = paper_solve("H158", metric=metric, magnitude=19.0, tolerance=tolerance)
    assert by_budget.tolerance == pytest.approx(tolerance, rel=1e-14)
    assert by_budget.precision == pytest.approx(by_tolerance.precision, rel=1e-12)
    answer = by_budget.to_dict()
    assert answer["tolerance"] == pytest.approx(tolerance, rel=1e-14)
    assert answer["shear"][kind] == budget[f"shear_{kind}"]
    assert answer["shear"]["tolerance"] == answer["tolerance"]
    assert answer["shear"]["size_ratio"]["ratios"] == [1.2, 1.5, 2.0]
    assert answer["shear"]["given"] == kind


def test_a_size_ratio_alone_reports_the_implied_bias_and_it_round_trips():
    first = paper_solve("J129", metric="size", precision=0.02, magnitude=19.5, size_ratio=1.4)
    implied = first.shear
    assert implied["given"] == "tolerance"
    assert implied["m"] == pytest.approx(shear.multiplicative_bias(first.tolerance, shear.check_size_ratio(1.4)))
    assert implied["uncertainty"] == pytest.approx(first.uncertainty_statistical * 2 / 1.4**2)
    back = paper_solve("J129", metric="size", magnitude=19.5, shear_m=implied["m"], size_ratio=1.4)
    assert back.precision == pytest.approx(0.02, rel=1e-12)
    # And the magnitude from (precision, budget) is the one we started from.
    mag = paper_solve("J129", metric="size", precision=0.02, shear_m=implied["m"], size_ratio=1.4)
    assert mag.magnitude == pytest.approx(19.5, abs=1e-3)


@pytest.mark.parametrize("metric", ["size", "e1", "e"])
def test_scatter_averaged_over_n_stars_falls_as_one_over_sqrt_n(metric):
    one = paper_solve("H158", metric=metric, mode="scatter", precision=0.1, magnitude=19.0)
    many = paper_solve("H158", metric=metric, mode="scatter", precision=0.1, magnitude=19.0, stars=25)
    assert many.tolerance == pytest.approx(one.tolerance / 5, rel=1e-12)
    assert many.slope == one.slope  # the slope is still one star's
    assert "25 stars" in many.applies_to and many.conditions["stars"] == 25
    assert "sqrt(stars)" in many.conditions["relation"]
    assert one.applies_to.startswith("one star")
    # Solving for the magnitude: n stars at tolerance T are one star at tolerance T sqrt(n).
    m_many = paper_solve("H158", metric=metric, mode="scatter", precision=0.1, tolerance=1e-5, stars=25)
    m_one = paper_solve("H158", metric=metric, mode="scatter", precision=0.1, tolerance=5e-5)
    assert m_many.nonlinearity_magnitude == pytest.approx(m_one.nonlinearity_magnitude, abs=1e-6)
    precision = paper_solve("H158", metric=metric, mode="scatter", tolerance=1e-5, magnitude=19.0, stars=25)
    assert precision.precision == pytest.approx(
        5 * paper_solve("H158", metric=metric, mode="scatter", tolerance=1e-5, magnitude=19.0).precision
    )


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"mode": "bias", "stars": 4, "tolerance": 1e-4}, "stars"),
        ({"mode": "scatter", "stars": 0, "tolerance": 1e-4}, "stars"),
        ({"mode": "scatter", "stars": 1.5, "tolerance": 1e-4}, "stars"),
        ({"shear_m": 1e-3, "size_ratio": 1.5, "tolerance": 1e-4}, "tolerance"),
        ({"shear_m": 1e-3}, "size_ratio"),
        ({"shear_c": 1e-3, "size_ratio": 1.5}, "shear_c"),
        ({"metric": "e1", "shear_m": 1e-3, "size_ratio": 1.5}, "shear_m"),
        ({"shear_m": 1e-3, "size_ratio": 1.5, "precision": 0.01}, "shear_m"),
        ({"shear_m": 1e-3, "size_ratio": -1}, "size_ratio"),
        ({"shear_m": 1e-13, "size_ratio": 1e-3}, "shear_m"),
        ({"size_ratio": "1:x", "tolerance": 1e-4}, "size_ratio"),
    ],
)
def test_bad_budget_requests_name_the_field(kwargs, field):
    kwargs = {"magnitude": 19.0, **kwargs}
    with pytest.raises(InputError) as info:
        paper_solve("H158", **kwargs)
    assert info.value.argument == field


def test_cli_shear_json_contract(capsys):
    code = cli.main(
        ["solve", "--metric", "e2", "--shear-c", "1e-4", "--size-ratio", "1.5", "--magnitude", "19", "--json", "--scene", "paper"]
    )
    assert code == 0
    payload = json.loads(capsys.readouterr().out)
    assert payload["shear"]["c"] == 1e-4 and payload["shear"]["size_ratio"] == 1.5
    assert payload["tolerance"] == pytest.approx(2 * 1e-4 * 1.5**2) == payload["shear"]["tolerance"]
    assert payload["solved_for"] == "precision" and math.isfinite(payload["precision"])
    assert cli.main(["solve", "--shear-m", "1e-3", "--magnitude", "19"]) == 2
    assert "--size-ratio" in capsys.readouterr().err
    assert (
        cli.main(["solve", "--mode", "scatter", "--stars", "9", "--precision", "0.1", "--magnitude", "19", "--scene", "paper"])
        == 0
    )
    assert "9 stars" in capsys.readouterr().out
