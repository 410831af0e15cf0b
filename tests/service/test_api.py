"""The REST API against the real library: the contract, solves, bad input, tables and curves
(simulations, jobs, the page, flags and the ranges shared with the library: ``test_api_jobs.py``)."""

from __future__ import annotations

import csv
import io
import json
import math

import numpy as np
import pytest
from fastapi.testclient import TestClient

from nlpsf import cli, roman
from nlpsf.request import presets as roman_default
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
