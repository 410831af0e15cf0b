"""The API as other tools see it: a typed OpenAPI schema, problem details, cacheable tables, batch solves."""

from __future__ import annotations

import gzip
import json

import pytest
from astropy.table import Table

from nlpsf import roman
from nlpsf.solve import solver


@pytest.fixture(scope="module")
def client_settings():
    return {}  # the service's own limits


@pytest.fixture(scope="module")
def schema(client):
    return client.get("/openapi.json").json()


def _operations(schema):
    for path, operations in schema["paths"].items():
        for method, operation in operations.items():
            yield path, method, operation


def test_every_response_is_typed(schema):
    for path, method, operation in _operations(schema):
        for code, response in operation["responses"].items():
            if code == "304":
                continue  # no body
            content = response.get("content")
            assert content, f"{method} {path} {code} documents no content"
            for media, entry in content.items():
                assert entry.get("schema"), f"{method} {path} {code} {media} has no schema"
                assert entry["schema"] != {}, f"{method} {path} {code} {media} is untyped"


def test_every_get_has_a_response_model(schema):
    for path, method, operation in _operations(schema):
        if method == "get":
            ok = operation["responses"]["200"]["content"]
            assert any("$ref" in e["schema"] or e["schema"].get("type") == "string" for e in ok.values()), path


def test_errors_are_problem_details_in_the_schema(schema):
    for path, method, operation in _operations(schema):
        for code, response in operation["responses"].items():
            if int(code) >= 400:
                assert list(response["content"]) == ["application/problem+json"], (path, method, code)


def _query(schema, path, name):
    return next(p for p in schema["paths"][path]["get"]["parameters"] if p["name"] == name)


def _resolve(schema, entry):
    if "anyOf" in entry:
        entry = next(e for e in entry["anyOf"] if e.get("type") != "null")
    if "$ref" in entry:
        entry = schema["components"]["schemas"][entry["$ref"].rsplit("/", 1)[1]]
    return entry


def test_choices_are_enums_and_sca_is_bounded(schema):
    solve = schema["components"]["schemas"]["SolveRequest"]["properties"]
    assert set(_resolve(schema, solve["band"])["enum"]) == set(roman.BANDS)
    assert set(_resolve(schema, solve["metric"])["enum"]) == set(solver.METRICS)
    assert set(_resolve(schema, solve["mode"])["enum"]) == set(solver.MODES)
    assert set(_resolve(schema, solve["fidelity"])["enum"]) == set(solver.FIDELITIES)
    assert (solve["sca"]["minimum"], solve["sca"]["maximum"]) == (1, roman.N_SCA)
    sca = _resolve(schema, _query(schema, "/api/v1/curves/beta", "sca")["schema"])
    assert (sca["minimum"], sca["maximum"]) == (1, roman.N_SCA)
    assert set(_resolve(schema, _query(schema, "/api/v1/curves/beta", "band")["schema"])["enum"]) == set(roman.BANDS)


UNIT_WORDS = (
    "unit",
    "pixel",
    "arcsec",
    " K)",
    " nm",
    " s",
    "1/e-",
    "e-",
    "AB mag",
    "dimensionless",
    "count",
    "text",
    "hex",
    "fraction",
    "1/mag",
)


def _numeric(entry) -> bool:
    kinds = [entry, *entry.get("anyOf", [])]
    kinds += [k["items"] for k in kinds if isinstance(k.get("items"), dict)]
    return any(k.get("type") in ("number", "integer") for k in kinds)


def test_every_number_field_names_its_unit(schema):
    # Numbers carry units; objects and flags are described by their own fields.
    missing = []
    for name, model in schema["components"]["schemas"].items():
        for field, entry in model.get("properties", {}).items():
            text = entry.get("description", "")
            if (_numeric(entry) or entry.get("type") == "string") and not any(word in text for word in UNIT_WORDS):
                missing.append(f"{name}.{field}: {text!r}")
    for path, method, operation in _operations(schema):
        for parameter in operation.get("parameters", []):
            if parameter["name"] == "job_id":
                continue
            if not any(word in parameter.get("description", "") for word in UNIT_WORDS):
                missing.append(f"{method} {path} ?{parameter['name']}")
    assert not missing, missing


def test_bad_input_is_one_problem_naming_every_field(client):
    response = client.post("/api/v1/solve", json={"band": "X999", "sca": 99, "tolerance": "a", "magnitude": 18})
    assert response.status_code == 422
    assert response.headers["content-type"] == "application/problem+json"
    body = response.json()
    assert body["status"] == 422 and body["type"] and body["title"] and body["detail"] == body["message"]
    assert body["field"] == "band"
    assert {e["field"] for e in body["errors"]} == {"band", "sca", "tolerance"}


def test_tables_are_compressed_and_revalidated(client):
    plain = client.get("/api/v1/tables", headers={"Accept-Encoding": "identity"})
    with client.stream("GET", "/api/v1/tables", headers={"Accept-Encoding": "gzip"}) as zipped:
        assert zipped.headers["content-encoding"] == "gzip"
        wire = b"".join(zipped.iter_raw())
    assert len(wire) < len(plain.content) / 3  # 6.6 MB of float text -> 1.9 MB
    assert json.loads(gzip.decompress(wire)) == plain.json()
    etag = plain.headers["etag"]
    assert client.get("/api/v1/tables").headers["etag"] == etag  # strong and stable
    assert etag != client.get("/api/v1/tables", params={"band": "H158"}).headers["etag"]
    again = client.get("/api/v1/tables", headers={"If-None-Match": etag})
    assert again.status_code == 304 and again.content == b""
    assert plain.json()["meta"]["fingerprint"] in etag


def test_tables_as_ecsv_carry_units(client):
    response = client.get("/api/v1/tables.ecsv", params={"band": "H158", "sca": 18})
    assert response.status_code == 200
    table = Table.read(response.text, format="ascii.ecsv")
    assert str(table["magnitude"].unit) == "mag(AB)"
    assert str(table["bias_size"].unit) == "electron" and str(table["flux_electrons"].unit) == "electron"
    rows = client.get("/api/v1/tables", params={"band": "H158", "sca": 18}).json()["rows"]
    assert len(table) == len(rows)
    assert list(table["bias_size"]) == pytest.approx([r["bias_size"] for r in rows], rel=1e-15)


def test_batch_answers_each_request_on_its_own(client):
    good = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "scene": "paper"}
    batch = [good, {"band": "H158", "magnitude": "x", "tolerance": 1e-4}, {**good, "beta0": -1.0}, {**good, "metric": "e1"}]
    response = client.post("/api/v1/solve/batch", json={"requests": batch})
    assert response.status_code == 200
    body = response.json()
    assert (body["answered"], body["failed"]) == (2, 2)
    results = body["results"]
    assert [r["ok"] for r in results] == [True, False, False, True]
    single = client.post("/api/v1/solve", json=good).json()
    assert results[0]["solution"]["precision"] == single["precision"]
    assert results[1]["error"]["field"] == "magnitude" and results[2]["error"]["field"] == "beta0"
    assert results[3]["solution"]["metric"] == "e1"


def test_curves_carry_the_fidelity_part_the_calculator_quotes(client):
    # The page's hover and bands show both parts: they must be the solver's own.
    solution = solver.solve("H158", magnitude=18.3, precision=1.0, scene="paper")  # the curves are the tables'
    fidelity = solution.uncertainty_fidelity / solution.tolerance
    statistical = solution.uncertainty_statistical / solution.tolerance
    beta = client.get("/api/v1/curves/beta", params={"band": "H158", "magnitude": 18.3}).json()
    assert beta["fidelity_relative_uncertainty"] == pytest.approx(fidelity, rel=1e-12)
    assert beta["uncertainty"][-1] / beta["values"][-1] == pytest.approx(statistical, rel=1e-9)
    slope = client.get("/api/v1/curves/slope", params={"bands": "H158"}).json()["curves"][0]
    assert slope["fidelity_relative_uncertainty"] == pytest.approx(fidelity, rel=1e-12)


def test_band_names_are_case_insensitive_but_listed_as_an_enum(client):
    lower = client.post("/api/v1/solve", json={"band": "h158", "magnitude": 18.3, "tolerance": 1e-4, "scene": "paper"})
    upper = client.post("/api/v1/solve", json={"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "scene": "paper"})
    assert lower.status_code == 200 and lower.json()["precision"] == upper.json()["precision"]
    assert client.get("/api/v1/curves/beta", params={"band": "j129"}).json()["band"] == "J129"
