"""The REST API against the real library: simulations and solve jobs, the page and the docs, the
typed request the API builds, flags as codes, and the ranges the library and the service share
(the contract, solves, tables and curves: ``test_api.py``)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from nlpsf import defaults, roman
from nlpsf.checks import InputError
from nlpsf.sim import experiment, ramps
from nlpsf.sim import scene as scenes
from nlpsf.solve import solver

from .test_api import post_raw

# --- simulations --------------------------------------------------------------------------------


def test_small_simulation_answered_synchronously_matches_the_library(client):
    body = {"band": "J129", "sca": 7, "magnitudes": [19.0, 21.0], "betas": [5e-7, 1e-6], "realizations": 12, "seed": 4}
    body["scene"] = "paper"  # the library's SimulationConfig defaults are the paper's scene
    response = client.post("/api/v1/simulations", params={"wait": 120}, json=body)
    assert response.status_code == 200, response.text
    job = response.json()
    assert job["status"] == "done" and job["progress"] == 1.0
    served = job["result"]["results"]
    config = experiment.SimulationConfig(band="J129", sca=7, realizations=12, seed=4)
    expected = [r.to_dict() for r in experiment.simulate(config, [19.0, 21.0], [5e-7, 1e-6])]
    assert len(served) == 4
    for got, want in zip(served, expected, strict=True):
        assert (got["magnitude"], got["beta"]) == (want["magnitude"], want["beta"])
        for metric in ("dR_over_R", "de1", "de2"):
            assert got[metric]["mean"] == pytest.approx(want[metric]["mean"], rel=1e-12)
            assert got[metric]["stderr"] == pytest.approx(want[metric]["stderr"], rel=1e-12)
    assert job["result"]["conditions"]["sca"] == 7


def test_solve_takes_a_throughput_and_names_it(client):
    body = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "scene": "paper"}
    default = client.post("/api/v1/solve", json=body).json()
    galsim = client.post("/api/v1/solve", json={**body, "throughput": "galsim-2021"}).json()
    assert default["conditions"]["throughput"] == "roman-2024" and galsim["conditions"]["throughput"] == "galsim-2021"
    # GalSim's 2021 H158 curve gives 5 % more electrons: the same star needs a tighter calibration.
    assert galsim["precision"] < default["precision"]
    assert client.post("/api/v1/solve", json={**body, "throughput": "cycle-5"}).status_code == 422


def test_simulation_throughput_is_a_request_field_named_in_the_conditions(client):
    body = {"band": "H158", "sca": 1, "magnitudes": [20.0], "realizations": 4, "fidelity": "linear"}
    runs = {}
    for throughput in roman.THROUGHPUTS:
        job = client.post("/api/v1/simulations", params={"wait": 120}, json={**body, "throughput": throughput}).json()
        assert job["status"] == "done", job
        assert job["result"]["conditions"]["throughput"] == throughput
        assert job["result"]["conditions"]["throughput_version"] == roman.THROUGHPUT_VERSIONS[throughput]
        runs[throughput] = job["result"]["results"][0]["flux_electrons"]
    # Official SCA 1 F158 zero point 26.323 (Roman_zeropoints_20240301) against GalSim 2021's 26.511.
    assert runs["roman-2024"] / runs["galsim-2021"] == pytest.approx(10 ** (-0.4 * 0.188), rel=0.01)
    refused = client.post("/api/v1/simulations", json={**body, "throughput": "cycle-5"})
    assert refused.status_code == 422


def test_simulation_pupil_scale_official_is_a_request_field(client):
    # The API's simulation is the library's: same rule, same numbers; an unknown rule is a 422.
    from nlpsf.sim import experiment

    body = {"band": "F184", "sca": 9, "magnitudes": [20.0], "realizations": 2, "fidelity": "linear", "pupil_scale": "official"}
    body["scene"] = "paper"  # compared with the library's paper-scene config below
    job = client.post("/api/v1/simulations", params={"wait": 120}, json=body).json()
    assert job["status"] == "done", job
    assert job["result"]["conditions"]["pupil_scale"] == "official"
    config = experiment.SimulationConfig(band="F184", sca=9, realizations=2, method="linear", pupil_scale="official")
    direct = experiment.simulate(config, [20.0], [5e-7])[0]
    assert job["result"]["results"][0]["dR_over_R"]["mean"] == pytest.approx(direct.dR_over_R.mean, rel=1e-12)
    assert client.post("/api/v1/simulations", json={**body, "pupil_scale": "cycle-5"}).status_code == 422


def test_sigma_beta_simulation_gives_the_scatter(client):
    body = {"magnitudes": [20.0], "betas": [5e-7], "sigma_betas": [5e-8, 1e-7], "realizations": 16, "fidelity": "linear"}
    job = client.post("/api/v1/simulations", params={"wait": 120}, json=body).json()
    assert job["status"] == "done", job
    small, large = job["result"]["results"]
    assert (small["sigma_beta"], large["sigma_beta"]) == (5e-8, 1e-7)
    # In the linear response the scatter is proportional to sigma_beta.
    assert large["dR_over_R"]["std"] == pytest.approx(2 * small["dR_over_R"]["std"], rel=0.05)


@pytest.mark.parametrize(
    ("body", "field", "limit"),
    [
        ({"realizations": 501}, "realizations", "max_realizations"),
        ({"stamp": 160}, "stamp", "max_stamp"),
        ({"magnitudes": [18.0 + 0.1 * k for k in range(51)]}, "magnitudes", "max_grid"),
        ({"magnitudes": [20.0] * 8, "betas": [5e-7] * 7}, "magnitudes", "max_grid"),
        ({"fidelity": "polychromatic", "n_wavelengths": 64}, "n_wavelengths", "max_wavelengths"),
    ],
)
def test_oversized_simulations_are_422_naming_the_limit(client, body, field, limit):
    response = client.post("/api/v1/simulations", json=body)
    assert response.status_code == 422, response.text
    problem = response.json()
    assert (problem["field"], problem["limit"]) == (field, limit)


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ('{"magnitudes": [NaN]}', "magnitudes"),
        ('{"magnitudes": [18, Infinity]}', "magnitudes"),
        ('{"magnitudes": []}', "magnitudes"),
        ('{"magnitudes": [1e300]}', "magnitudes"),
        ('{"betas": [1]}', "betas"),
        ('{"betas": []}', "betas"),
        ('{"sigma_betas": [-1e-7]}', "sigma_betas"),
        ('{"band": "X"}', "band"),
        ('{"sca": 0}', "sca"),
        ('{"realizations": 0}', "realizations"),
        ('{"realizations": 2.5}', "realizations"),
        ('{"stamp": 8}', "stamp"),
        ('{"oversampling": 99}', "oversampling"),
        ('{"exptime": 0}', "exptime"),
        ('{"seed": -1}', "seed"),
        ('{"fidelity": "exact"}', "fidelity"),
        ('{"n_wavelengths": 4}', "n_wavelengths"),
        ('{"weight_cut_rho2": 1}', "weight_cut_rho2"),
        ('{"beta_convention": "mine"}', "beta_convention"),
        ('{"realisations": 10}', "realisations"),
    ],
)
def test_bad_simulation_input_is_422(client, text, field):
    response = post_raw(client, "/api/v1/simulations", text)
    assert response.status_code == 422, response.text
    assert response.json()["field"] == field


def test_unknown_jobs(client):
    assert client.get("/api/v1/simulations/" + "0" * 32).status_code == 404
    assert client.delete("/api/v1/simulations/" + "0" * 32).status_code == 404
    assert client.get("/api/v1/simulations/not-a-job").status_code == 422


# --- the page and the docs ------------------------------------------------------------------


def test_page_and_docs_are_served(client):
    page = client.get("/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert 'src="vendor/uPlot.iife.min.js"' in page.text
    for asset in ("/app.js", "/app.css", "/vendor/uPlot.iife.min.js", "/vendor/uPlot.min.css"):
        assert client.get(asset).status_code == 200, asset
    assert "http" not in page.text.split("<body>")[0].replace("http-equiv", ""), "the page must not load anything remote"
    assert client.get("/docs").status_code == 200
    spec = client.get("/openapi.json").json()
    assert {"/api/v1/solve", "/api/v1/simulations", "/api/v1/simulations/{job_id}", "/api/v1/meta"} <= set(spec["paths"])


def test_responses_never_contain_non_finite_numbers(client):
    # A slope consistent with zero makes the precision infinite; JSON must carry null, not Infinity.
    def refuse(token):
        raise AssertionError(f"non-finite number {token} in a response")

    for metric in ("e1", "e2"):
        for magnitude in (16.0, 22.0, 27.5):
            body = {"band": "W146", "metric": metric, "magnitude": magnitude, "tolerance": 1e-3, "scene": "paper"}
            response = client.post("/api/v1/solve", json=body)
            assert response.status_code in (200, 422)
            json.loads(response.text, parse_constant=refuse)
            if response.status_code == 200:
                value = response.json()["precision"]
                assert value is None or math.isfinite(value)


# --- the API builds the library's typed request -------------------------------------------------


def _run_solve_job(client, body):
    """A solve that is a job, validated as the endpoint does and run in this process."""
    from nlpsf.web import job_kinds, models

    model = models.SolveRequest.model_validate(body)
    job = job_kinds.KINDS[job_kinds.SOLVE_KIND].validate(model.model_dump(), model.model_fields_set, client.app.state.settings)
    return job_kinds.run(json.loads(json.dumps(job)))  # the job request travels as JSON


def test_a_uniform_ols_ramp_solve_job_is_the_final_frame_at_beta_eff(client):
    # Independent of the ramp code path: an N-read OLS ramp's magnitude equals the final frame's at
    # beta_eff = (1 + 1/N) beta0 with the same precision (see tests/library/test_ramps.py).
    n = 8
    ramp = _run_solve_job(client, {"band": "H158", "precision": 0.01, "tolerance": 1e-4, "ramp": n, "scene": "paper"})
    frame = client.post(
        "/api/v1/solve",
        json={"band": "H158", "precision": 0.01, "tolerance": 1e-4, "beta0": defaults.BETA0 * (1 + 1 / n)} | {"scene": "paper"},
    ).json()
    assert ramp["conditions"]["ramp"]["ma_table"] == f"uniform-{n}"
    assert ramp["magnitude"] == pytest.approx(frame["magnitude"], abs=1e-5)


def test_an_ma_table_solve_job_takes_its_exposure_from_the_last_read(client):
    from nlpsf.sim import ramps

    table = {"resultants": [[1], [2, 3], [4, 5, 6]], "frame_time_s": 3.04}
    answer = _run_solve_job(client, {"band": "H158", "precision": 0.1, "magnitude": 19.0, "ma_table": table, "scene": "paper"})
    assert answer["exptime"] == pytest.approx(ramps.MATable.from_dict(table).duration_s)
    longer = _run_solve_job(
        client, {"band": "H158", "precision": 0.1, "magnitude": 19.0, "ma_table": table, "exptime": 30.0, "scene": "paper"}
    )
    assert longer["exptime"] == 30.0


@pytest.mark.parametrize("scene", [{"bfe": 1e-6}, {"ipc": "roman"}, {"background": 10.0}])
def test_a_scene_with_a_ramp_follows_the_librarys_rule(client, scene):
    # The service holds no rule of its own: it refuses exactly what the library's request refuses.
    from nlpsf.request.resolve import SolveRequest

    body = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "ramp": 6, "scene": {**scene, "preset": "paper"}}
    try:
        SolveRequest.from_json(body)
        library = None
    except InputError as error:
        library = error
    answer = client.post("/api/v1/solve", json=body)
    if library is None:
        assert answer.status_code in (200, 202), answer.text
    else:
        assert answer.status_code == 422
        assert answer.json()["field"] == library.argument and library.reason in answer.json()["detail"]


def test_service_json_has_no_nan_or_numpy_whatever_the_library_returns():
    # JSON (RFC 8259) has no NaN or infinity; numpy integers are not JSON numbers. The service's
    # responses and its job results go through the one json_safe (nlpsf.serialise).
    from nlpsf.web import job_kinds
    from nlpsf.web.errors import SafeJSONResponse

    payload = {"nan": float("nan"), "inf": np.float64("-inf"), "n": np.int64(3), "pair": (1.5, float("inf")), 2: "key"}
    expected = {"nan": None, "inf": None, "n": 3, "pair": [1.5, None], "2": "key"}
    assert json.loads(SafeJSONResponse(payload).body) == expected
    assert json.loads(json.dumps(job_kinds.json_safe(payload), allow_nan=False)) == expected


# --- flags as codes on the surface --------------------------------------------------------------


def test_meta_serves_the_flag_catalogue_and_the_scene_effect_registry(client):
    from nlpsf import flags

    meta = client.get("/api/v1/meta").json()
    served = {entry["code"]: entry for entry in meta["flag_codes"]}
    assert set(served) == {code.value for code in flags.FlagCode}
    assert all(entry["meaning"] and entry["template"] for entry in served.values())
    effects = meta["scene_effects"]
    assert [e["name"] for e in effects] == list(scenes.REGISTRY)  # the order they act in
    by_name = {e["name"]: e for e in effects}
    assert by_name["jitter"]["nominal"] == {"jitter_arcsec": scenes.ROMAN_JITTER_ARCSEC}
    assert by_name["jitter"]["kind"] == "optical" and by_name["brighter_fatter"]["kind"] == "detector"
    from nlpsf.sim import ramps

    for name, effect in by_name.items():  # what a ramp refuses says so
        assert (name in ramps.RAMP_REFUSES) == ("not a ramp" in effect["combines_with"]), name


def test_an_answers_flags_come_with_their_codes(client):
    # A star brighter than its saturation magnitude is flagged saturated, whatever the words say.
    body = {"band": "H158", "precision": 0.5, "magnitude": 17.0, "scene": "paper"}
    answer = client.post("/api/v1/solve", json=body).json()
    assert answer["saturation_magnitude"] > 17.0
    assert len(answer["flag_codes"]) == len(answer["flags"]) and "star_saturated" in answer["flag_codes"]
    catalogue = {entry["code"] for entry in client.get("/api/v1/meta").json()["flag_codes"]}
    assert set(answer["flag_codes"]) <= catalogue
    schema = client.get("/openapi.json").json()["components"]["schemas"]
    assert "flag_codes" in schema["SolveResponse"]["required"]
    curve = client.get("/api/v1/curves/beta?band=H158&magnitude=17").json()
    assert "star_saturated" in curve["flag_codes"] and len(curve["flag_codes"]) == len(curve["flags"])


# --- one owner for each range: the library's and the service's entries refuse the same ----------


@pytest.mark.parametrize(("beta0", "accepted"), [(5e-13, False), (defaults.BETA0_RANGE[0], True), (2e-3, False)])
def test_impact_beta0_is_refused_alike_by_the_library_and_the_service(client, beta0, accepted):
    from nlpsf.solve import impact

    if accepted:
        assert impact.check_request(beta0=beta0)["beta0"] == beta0
    else:
        with pytest.raises(InputError) as refused:
            impact.check_request(beta0=beta0)
        assert refused.value.argument == "beta0"
        answer = client.post("/api/v1/impact", json={"band": "H158", "magnitude": 18.3, "beta0": beta0})
        assert answer.status_code == 422 and answer.json()["field"] == "beta0"


def test_seeds_up_to_2_63_minus_1_at_every_library_entry():
    from nlpsf.solve import impact

    top = 2**63 - 1  # numpy's SeedSequence takes it; one past is refused alike by both entries
    assert impact.check_request(seed=top)["seed"] == top
    experiment.SimulationConfig(seed=top)
    for entry in (lambda: impact.check_request(seed=top + 1), lambda: experiment.SimulationConfig(seed=top + 1)):
        with pytest.raises(InputError, match="seed"):
            entry()


@pytest.mark.parametrize(
    ("scene", "field"), [({"bfe": 2e-5}, "scene.bfe"), ({"nl_coefficients": [1e-10]}, "scene.nl_coefficients")]
)
def test_a_scene_beyond_first_order_is_refused_by_the_library_and_the_service(client, scene, field):
    # At the full well Q = 1.1e5 e-: |bfe| Q = 2.2 and 3 b3 Q^2 = 3.6, both past 1; at Q/10, 0.22 and 0.036.

    model = scenes.from_request(scene)
    with pytest.raises(InputError) as refused:
        experiment.SimulationConfig(scene=model, full_well_e=defaults.FULL_WELL_E)
    assert refused.value.argument == field
    for path, body in (
        ("/api/v1/simulations", {"band": "H158", "scene": scene, "realizations": 2}),
        ("/api/v1/solve", {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "scene": {**scene, "preset": "paper"}}),
    ):
        answer = client.post(path, json=body)
        assert answer.status_code == 422 and answer.json()["field"] == field, answer.text
    # The same scene at a tenth of the full well is within the first-order regime.
    experiment.SimulationConfig(scene=model, full_well_e=defaults.FULL_WELL_E / 10, realizations=2)


def test_a_simulation_result_carries_the_standard_error_of_each_spread(client):
    from nlpsf.web import job_kinds, models

    request = models.SimulationRequest.model_validate(
        {"band": "H158", "magnitudes": [18.3], "betas": [5e-7], "sigma_betas": [5e-8], "realizations": 5, "stamp": 48,
         "fidelity": "linear", "seed": 3}
    )  # fmt: skip
    job = job_kinds.KINDS[job_kinds.SIMULATION_KIND].validate(
        request.model_dump(), request.model_fields_set, client.app.state.settings
    )
    (row,) = job_kinds.run(job)["results"]
    for metric in job_kinds.RESULT_METRICS:
        # Of n normal draws, the sample std's standard error is std / sqrt(2 (n - 1)).
        assert row[metric]["std_error"] == pytest.approx(row[metric]["std"] / math.sqrt(2 * (5 - 1)), rel=1e-12)


def test_std_error_is_the_spread_of_sample_standard_deviations():
    # Independent of the formula: the scatter of many samples' std around sigma.

    from nlpsf.sim.experiment.results import Statistic

    rng = np.random.default_rng(5)
    n = 20
    samples = rng.normal(0.0, 2.0, size=(4000, n))
    stds = samples.std(axis=1, ddof=1)
    predicted = np.mean([Statistic.of(s).std_error for s in samples[:200]])
    assert stds.std() == pytest.approx(predicted, rel=0.06)
    assert Statistic.of(np.array([1.0])).std_error is None


def test_every_service_setting_is_in_the_api_docs_configuration_list():
    from pathlib import Path

    from nlpsf.web.settings import Settings

    text = (Path(__file__).parents[2] / "docs" / "api.md").read_text()
    configuration = text.split("## Configuration", 1)[1]
    for name, info in Settings.model_fields.items():
        if name == "limits":
            names = [f"NLPSF_{limit.upper()}" for limit in Settings().limits.to_dict()]
        else:
            names = [info.validation_alias if isinstance(info.validation_alias, str) else f"NLPSF_{name.upper()}"]
        for variable in names:
            assert f"`{variable}`" in configuration, variable


def test_web_request_takes_the_new_fields_and_refuses_a_file(client):
    body = {"band": "H158", "magnitude": 19.0, "shear_m": 1e-3, "size_ratio": [[1.2, 1.0], [2.0, 1.0]], "scene": "paper"}
    answer = client.post("/api/v1/solve", json=body)
    assert answer.status_code == 200, answer.text
    assert answer.json()["shear"]["m"] == 1e-3
    scatter = client.post(
        "/api/v1/solve",
        json={"band": "H158", "mode": "scatter", "magnitude": 19.0, "tolerance": 1e-4, "stars": 4, "scene": "paper"},
    )
    assert scatter.status_code == 200 and scatter.json()["stars"] == 4
    refused = client.post("/api/v1/solve", json={**body, "size_ratio": "@/etc/passwd"})
    assert refused.status_code == 422


def test_service_takes_a_ramp_in_solve_and_simulations(make_client):
    from nlpsf.web.settings import Limits

    with make_client(limits=Limits(max_realizations=50)) as client:
        meta = client.get("/api/v1/meta").json()
        assert {t["name"] for t in meta["ma_tables"]} == set(ramps.shipped_table_names())
        assert meta["ramp_fits"] == list(ramps.RAMP_FITS)
        body = {"band": "H158", "precision": 0.01, "magnitude": 19.0, "ramp": 8, "scene": "paper"}
        answer = client.post("/api/v1/solve", json=body)
        assert answer.status_code == 200
        assert (
            answer.json()["slope"]
            == solver.solve(
                "H158", precision=0.01, magnitude=19.0, ramp=ramps.Ramp.uniform(8, defaults.EXPTIME_S), scene="paper"
            ).slope
        )
        question = {"band": "H158", "precision": 0.01, "magnitude": 19.0, "scene": "paper"}
        bad = client.post("/api/v1/solve", json={**question, "ma_table": {"resultants": [[1], []]}})
        assert bad.status_code == 422 and bad.json()["field"].startswith("ma_table")
        files = client.post("/api/v1/solve", json={**question, "ma_table": "/etc/x.json"})
        assert files.status_code == 422 and files.json()["field"] == "ma_table"  # the service reads no files
        body = {"band": "H158", "magnitudes": [19.0], "realizations": 4, "fidelity": "linear", "ma_table": "romanisim-110"}
        body["scene"] = "paper"  # the paper's scene on this table, as the library's config below
        job = client.post("/api/v1/simulations", params={"wait": 120}, json=body).json()
        assert job["status"] == "done", job
        table = ramps.load_ma_table("romanisim-110")
        config = experiment.SimulationConfig(realizations=4, method="linear", exptime_s=table.duration_s, ramp=ramps.Ramp(table))
        expected = experiment.simulate(config, [19.0], [defaults.BETA0])[0]
        assert job["result"]["results"][0]["dR_over_R"]["mean"] == pytest.approx(expected.dR_over_R.mean, rel=1e-12)
        assert job["result"]["conditions"]["ramp"]["ma_table"] == "romanisim-110"
