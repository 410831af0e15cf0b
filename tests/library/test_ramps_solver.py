"""Up-the-ramp exposures through the solver, the CLI and the service: a ramp read from the tables
at its beta_eff, the saturation rules and the stars between them, the read noise's default, and the
linearisation state (the uncorrected beta0 of the paper, or the corrected detector's residual NL)
with a ramp's saturation flags set by the raw beta0 either way. The ramps themselves (MA tables,
fits, resultants): ``test_ramps.py``.
"""

import json
import math

import numpy as np
import pytest

from nlpsf.checks import InputError
from nlpsf.flags import FlagCode, codes
from nlpsf.sim import experiment, ramps
from nlpsf.sim import scene as scenes
from nlpsf.sim.experiment import SimulationConfig, simulate, slopes
from nlpsf.solve import solver

from .. import shipped
from .test_ramps import BETA, FULL_WELL, T, paper_solve, uniform

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
