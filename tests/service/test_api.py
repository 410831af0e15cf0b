"""The REST API against the real library: contract, curves, tables, simulations, and bad input."""

from __future__ import annotations

import csv
import io
import json
import math

import numpy as np
import pytest
from fastapi.testclient import TestClient

from nlpsf import cli, defaults, roman
from nlpsf.checks import InputError
from nlpsf.request import presets as roman_default
from nlpsf.sim import experiment, ramps
from nlpsf.sim import scene as scenes
from nlpsf.slopes import tables
from nlpsf.solve import solver

from .. import shipped


def post_raw(client: TestClient, path: str, text: str):
    return client.post(path, content=text.encode(), headers={"Content-Type": "application/json"})


# --- contract ----------------------------------------------------------------------------------


def test_health(client):
    response = client.get("/api/v1/health")
    assert response.status_code == 200
    assert response.json()["status"] == "ok"


def test_meta_lists_what_the_library_offers(client):
    meta = client.get("/api/v1/meta").json()
    assert meta["bands"] == list(roman.BANDS)
    assert meta["scas"] == list(range(1, 19))
    assert meta["metrics"] == list(solver.METRICS)
    assert meta["modes"] == list(solver.MODES)
    assert meta["fidelities"] == list(solver.FIDELITIES)
    assert meta["data_version"] == roman.DATA_VERSION
    assert list(meta["throughputs"]) == list(roman.THROUGHPUTS) and meta["default_throughput"] == "roman-2024"
    assert meta["tables"]["fingerprint"] == tables.load_tables().meta["fingerprint"]
    assert meta["defaults"]["solve"]["beta0"] == 5e-7
    # Not given, the exposure is the scene's (published as null; the exposure each scene fills is beside it).
    assert meta["defaults"]["solve"]["exptime"] is None
    assert meta["defaults"]["scene_exptime"]["roman"] == roman_default.exptime_s()
    assert meta["limits"]["max_realizations"] == 500
    assert meta["limits"]["max_queue"] == 8


def cli_solve_json(capsys, arguments: list[str]) -> dict:
    assert cli.main(["solve", *arguments, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize(
    ("body", "arguments"),
    [
        (
            {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "scene": "paper"},
            ["--band", "H158", "--magnitude", "18.3", "--tolerance", "1e-4", "--scene", "paper"],
        ),
        (
            {"band": "J129", "sca": 3, "metric": "e2", "mode": "scatter", "precision": 0.05, "magnitude": 20.0, "scene": "paper"},
            [
                "--band",
                "J129",
                "--sca",
                "3",
                "--metric",
                "e2",
                "--mode",
                "scatter",
                "--precision",
                "0.05",
                "--magnitude",
                "20",
                "--scene",
                "paper",
            ],
        ),
        (
            {
                "band": "Y106",
                "metric": "size",
                "precision": 0.01,
                "tolerance": 1e-4,
                "beta0": 1e-6,
                "exptime": 300.0,
                "scene": "paper",
            },
            [
                "--band",
                "Y106",
                "--precision",
                "0.01",
                "--tolerance",
                "1e-4",
                "--beta0",
                "1e-6",
                "--exptime",
                "300",
                "--scene",
                "paper",
            ],
        ),
    ],
)
def test_solve_returns_what_the_cli_prints(client, capsys, body, arguments):
    response = client.post("/api/v1/solve", json=body)
    assert response.status_code == 200, response.text
    served = response.json()
    printed = cli_solve_json(capsys, arguments)
    for volatile in ("elapsed_s",):
        served.pop(volatile, None)
        printed.pop(volatile, None)
    assert served == printed


@pytest.mark.parametrize("metric", solver.METRICS)
@pytest.mark.parametrize("mode", solver.MODES)
def test_solve_each_unknown_round_trips(client, metric, mode):
    """Solve for each member from the other two; feeding the answer back returns the third member."""
    given = {"band": "H158", "metric": metric, "mode": mode, "scene": "paper"}
    start = client.post("/api/v1/solve", json={**given, "magnitude": 20.0, "precision": 0.02})
    assert start.status_code == 200, start.text
    first = start.json()
    assert first["solved_for"] == "tolerance"
    assert all(first[k] is not None for k in ("precision", "tolerance", "magnitude", "slope", "saturation_magnitude"))
    assert first["conditions"]["band"] == "H158" and first["fidelity"] == "table"
    back = client.post("/api/v1/solve", json={**given, "magnitude": 20.0, "tolerance": first["tolerance"]}).json()
    assert back["solved_for"] == "precision"
    assert back["precision"] == pytest.approx(0.02, rel=1e-9)
    magnitude = client.post("/api/v1/solve", json={**given, "precision": 0.02, "tolerance": first["tolerance"]}).json()
    assert magnitude["solved_for"] == "magnitude"
    assert isinstance(magnitude["flags"], list)
    if magnitude["magnitude"] is not None and not magnitude["flags"]:
        assert magnitude["magnitude"] == pytest.approx(20.0, abs=max(3 * (magnitude["uncertainty"] or 0), 0.02))


# --- bad input never yields a 5xx --------------------------------------------------------------

GOOD = '"band": "H158", "magnitude": 18.3'


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("{" + GOOD + ', "tolerance": NaN}', "tolerance"),
        ("{" + GOOD + ', "tolerance": Infinity}', "tolerance"),
        ("{" + GOOD + ', "tolerance": -Infinity}', "tolerance"),
        ("{" + GOOD + ', "tolerance": 1e400}', "tolerance"),
        ("{" + GOOD + ', "tolerance": -1e-4}', "tolerance"),
        ("{" + GOOD + ', "tolerance": 0}', "tolerance"),
        ("{" + GOOD + ', "tolerance": 1e300}', "tolerance"),
        ('{"band": "H158", "magnitude": 1e300, "tolerance": 1e-4}', "magnitude"),
        ('{"band": "H158", "magnitude": -1e300, "tolerance": 1e-4}', "magnitude"),
        ("{" + GOOD + ', "tolerance": "1e-4"}', "tolerance"),
        ("{" + GOOD + ', "tolerance": "abc"}', "tolerance"),
        ("{" + GOOD + ', "tolerance": true}', "tolerance"),
        ("{" + GOOD + ', "tolerance": [1e-4]}', "tolerance"),
        ("{" + GOOD + ', "tolerance": {"v": 1}}', "tolerance"),
        ('{"band": "H999", "magnitude": 18.3, "tolerance": 1e-4}', "band"),
        ('{"band": 158, "magnitude": 18.3, "tolerance": 1e-4}', "band"),
        ("{" + GOOD + ', "tolerance": 1e-4, "sca": 0}', "sca"),
        ("{" + GOOD + ', "tolerance": 1e-4, "sca": 19}', "sca"),
        ("{" + GOOD + ', "tolerance": 1e-4, "sca": 100000000000000000000000000000}', "sca"),
        ("{" + GOOD + ', "tolerance": 1e-4, "sca": 18.5}', "sca"),
        ("{" + GOOD + ', "tolerance": 1e-4, "sca": "18"}', "sca"),
        ("{" + GOOD + ', "tolerance": 1e-4, "metric": "size2"}', "metric"),
        ("{" + GOOD + ', "tolerance": 1e-4, "mode": "both"}', "mode"),
        ("{" + GOOD + ', "tolerance": 1e-4, "beta0": -5e-7}', "beta0"),
        ("{" + GOOD + ', "tolerance": 1e-4, "beta0": 0}', "beta0"),
        ("{" + GOOD + ', "tolerance": 1e-4, "exptime": -1}', "exptime"),
        ("{" + GOOD + ', "tolerance": 1e-4, "exptime": NaN}', "exptime"),
        ("{" + GOOD + ', "tolerance": 1e-4, "full_well": 0}', "full_well"),
        ("{" + GOOD + ', "tolerance": 1e-4, "fidelity": "exact"}', "fidelity"),
        ("{" + GOOD + ', "tolerance": 1e-4, "accuracy": -0.1}', "accuracy"),
        ("{" + GOOD + ', "tolerance": 1e-4, "magnitdue": 18}', "magnitdue"),
        ('{"magnitude": 18.3, "tolerance": 1e-4}', "band"),
    ],
)
def test_bad_solve_input_is_a_422_naming_the_field(client, text, field):
    response = post_raw(client, "/api/v1/solve", text)
    assert response.status_code == 422, response.text
    problem = response.json()
    assert problem["field"] == field
    assert field in problem["message"]


@pytest.mark.parametrize(
    "members",
    [
        {"magnitude": 18.3},
        {"precision": 0.01},
        {"tolerance": 1e-4},
        {},
        {"magnitude": 18.3, "precision": 0.01, "tolerance": 1e-4},
    ],
)
def test_solve_needs_exactly_two_members(client, members):
    response = client.post("/api/v1/solve", json={"band": "H158", **members})
    assert response.status_code == 422
    problem = response.json()
    assert problem["field"] in ("precision", "tolerance", "magnitude")
    assert problem["type"] == "/problems/invalid-combination"  # the problem's code, not its English


@pytest.mark.parametrize("text", ["", "not json", "[1, 2]", "null", "18.3", '{"band": "H158",'])
def test_malformed_bodies_are_422(client, text):
    response = post_raw(client, "/api/v1/solve", text)
    assert response.status_code == 422
    assert response.json()["message"]


@pytest.mark.parametrize(
    "query",
    [
        "curves/beta?band=H999",
        "curves/beta?magnitude=nan",
        "curves/beta?magnitude=inf",
        "curves/beta?beta_max=-1",
        "curves/sigma_beta?sca=99",
        "curves/slope?exptime=-5",
        "curves/slope?metric=x",
        "tables?band=Q",
        "tables.csv?sca=0",
        "tables?sca=abc",
    ],
)
def test_bad_queries_are_422(client, query):
    response = client.get(f"/api/v1/{query}")
    assert response.status_code == 422, response.text
    assert response.json()["field"]


# --- tables, curves, paper ----------------------------------------------------------------------


def test_tables_json_and_csv_agree(client):
    rows = client.get("/api/v1/tables", params={"band": "H158", "sca": 18}).json()["rows"]
    download = client.get("/api/v1/tables.csv", params={"band": "H158", "sca": 18})
    assert download.status_code == 200
    assert download.headers["content-type"].startswith("text/csv")
    assert "attachment" in download.headers["content-disposition"]
    parsed = list(csv.DictReader(io.StringIO(download.text)))
    assert len(parsed) == len(rows) == len(tables.table_rows("H158", 18))
    assert {r["band"] for r in parsed} == {"H158"}
    assert float(parsed[3]["magnitude"]) == rows[3]["magnitude"]


def test_slope_curves_cover_every_band_at_the_requested_conditions(client):
    data = client.get("/api/v1/curves/slope", params={"metric": "size", "mode": "bias", "exptime": 300.0}).json()
    assert "table" in data["source"]
    assert [c["band"] for c in data["curves"]] == tables.load_tables().bands
    for curve in data["curves"]:
        assert curve["conditions"]["exptime_s"] == 300.0
        assert len(curve["magnitude"]) == len(curve["slope"]) == len(curve["uncertainty"]) > 10
    direct = tables.curve("J129", 18, "size", "bias", exptime=300.0)
    served = next(c for c in data["curves"] if c["band"] == "J129")
    assert served["slope"] == pytest.approx(direct["slope"])
    # Independently: a longer exposure is the same star brighter, an exact shift of the magnitude axis
    # by 2.5 log10(T / T_table) on the slopes of the shipped ECSV (astropy, scipy's spline).
    sca = served["conditions"]["sca"]
    shifted = np.asarray(served["magnitude"]) - 2.5 * math.log10(300.0 / shipped.exptime_s())
    np.testing.assert_allclose(served["slope"], shipped.slope("J129", sca, "size", "bias", shifted), rtol=1e-9)


@pytest.mark.parametrize(
    ("path", "mode", "axis", "metric"),
    [("beta", "bias", "beta", "size"), ("beta", "bias", "beta", "e1"), ("sigma_beta", "scatter", "sigma_beta", "size")],
)
def test_beta_curves_are_the_table_slope_times_the_axis(client, path, mode, axis, metric):
    data = client.get(f"/api/v1/curves/{path}", params={"band": "F184", "metric": metric, "magnitude": 20.0}).json()
    assert "first order" in data["source"]
    # The slope from the shipped ECSV (astropy, scipy's spline), not from the solver the endpoint calls.
    slope = float(shipped.slope("F184", data["conditions"]["sca"], metric, mode, 20.0))
    for x, y, error in zip(data[axis], data["values"], data["uncertainty"], strict=True):
        # Signed: NL makes Delta e1 negative here, and the curve must say so.
        assert y == pytest.approx(slope * x, rel=1e-9, abs=1e-300)
        assert error >= 0
    assert data["conditions"]["band"] == "F184"


def test_paper_data_is_served_unchanged(client):
    assert client.get("/api/v1/paper").json() == tables.paper_data()


def test_fits_endpoint(client):
    fits = client.get("/api/v1/fits", params={"band": "H158", "sca": 18}).json()["fits"]
    assert {f["mode"] for f in fits} == {"bias", "scatter"}
    assert all(f["A"] > 0 for f in fits)


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
