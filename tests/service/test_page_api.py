"""The page's own endpoints (app/page_api.py), without a browser: the curves follow the library's
scaling, the limits bracket what the solver answers, the CSV batch reads percents and names bad
input, and the user guide is served from the package as shipped."""

from __future__ import annotations

import csv
import io
from pathlib import Path

import pytest

from nlpsf.checks import InputError
from nlpsf.solve import solver

from .. import shipped

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def client_settings():
    return {}  # the service's own limits


def test_requirement_curves_scale_with_the_tolerance_and_stop_at_saturation(client):
    data = client.get("/api/v1/page/requirement", params={"tolerance": 1e-4, "at": 18.3}).json()
    curves = {round(c["factor"], 3): c for c in data["requirement"]}
    chosen = curves[1.0]
    assert 18.3 in chosen["magnitude"], "the answer's magnitude is on the grid"
    assert min(chosen["magnitude"]) >= data["limits"]["saturation_magnitude"]
    # T = |c| p beta0: p is proportional to T at every magnitude.
    for low, high in zip(curves[0.1]["precision"], curves[10.0]["precision"], strict=True):
        assert high == pytest.approx(100 * low, rel=1e-9)
    # ... and inversely proportional to the slope, read from the shipped ECSV (astropy, scipy's spline)
    # at the conditions the answer names, not from the same endpoint.
    conditions = data["conditions"]
    assert (conditions["exptime_s"], conditions["beta0"]) == (shipped.exptime_s(), 5e-7)
    slopes = shipped.slope(conditions["band"], conditions["sca"], "size", "bias", chosen["magnitude"])
    for p, c in zip(chosen["precision"], slopes, strict=True):
        assert p * abs(c) * 5e-7 == pytest.approx(1e-4, rel=1e-9)


def test_limits_bracket_what_the_solver_answers(client):
    limits = client.get("/api/v1/page/limits", params={"band": "J129", "sca": 3}).json()
    brightest = limits["brightest_answered_magnitude"]
    solver.solve("J129", sca=3, tolerance=1e-4, magnitude=brightest + 0.01, scene="paper")
    with pytest.raises(InputError):
        solver.solve("J129", sca=3, tolerance=1e-4, magnitude=brightest - 0.01, scene="paper")
    assert limits["nonmonotonic_magnitude"] < limits["saturation_magnitude"]


def test_batch_csv_reads_percents_and_reports_each_row(client):
    text = "band,precision,magnitude,scene\nH158,1%,19,paper\nH158,0.01,19,paper\nH158,abc,19,paper\n"
    answer = client.post("/api/v1/page/batch", content=text, headers={"Content-Type": "text/csv"}).json()
    assert [r["ok"] for r in answer["results"]] == [True, True, False]
    expected = solver.solve("H158", precision=0.01, magnitude=19, scene="paper").tolerance
    assert answer["results"][0]["solution"]["tolerance"] == pytest.approx(expected, rel=1e-12)
    assert answer["results"][1]["solution"]["tolerance"] == pytest.approx(expected, rel=1e-12)
    assert answer["results"][2]["error"]["field"] == "precision"
    response = client.post("/api/v1/page/batch?format=csv", content=text, headers={"Content-Type": "text/csv"})
    assert 'filename="nlpsf-batch-answers.csv"' in response.headers["content-disposition"]
    rows = list(csv.DictReader(line for line in io.StringIO(response.text) if not line.startswith("#")))
    assert float(rows[0]["tolerance"]) == pytest.approx(expected, rel=1e-12) and rows[2]["ok"] == "False"
    assert client.post("/api/v1/page/batch", content="", headers={"Content-Type": "text/csv"}).status_code == 422
    for bad in ("# only a comment\n", "band,precision\n", ",x\n1,2\n"):
        refused = client.post("/api/v1/page/batch", content=bad, headers={"Content-Type": "text/csv"})
        assert refused.status_code == 422 and refused.json()["field"] == "csv", bad


def test_the_guide_is_served_as_shipped_and_nothing_else(client):
    assert "guide" in client.get("/api/v1/page/docs").json()["pages"]
    guide = client.get("/api/v1/page/docs/guide")
    assert guide.status_code == 200 and guide.text == (ROOT / "docs" / "guide.md").read_text()
    for name in ("..%2Fpyproject", "Guide", "nope"):
        assert client.get(f"/api/v1/page/docs/{name}").status_code in (404, 422), name


def test_presets_carry_sources(client):
    presets = client.get("/api/v1/page/presets").json()
    assert all(p["source"] and p["share"] for p in presets["presets"])
    assert any("arXiv:2505.00093" in p["source"] for p in presets["presets"])
    assert presets["scenes"]["roman"]["fields"]["ipc"] == "roman"


def test_the_page_reads_its_limits_and_impacts_from_the_library(client):
    from nlpsf.solve import relation

    params = {"band": "J129", "sca": 3, "beta0": 1e-6, "exptime": 100.0}
    limits = client.get("/api/v1/page/limits", params=params).json()
    assert limits["nonmonotonic_magnitude"] == relation.nl_invalid_magnitude("J129", 3, 1e-6, 100.0)
    impacts = client.get("/api/v1/page/impact-terms", params={"precision": 0.01, "impact": [0.25, -1.0, -1.5]}).json()
    # T = |c| p beta0 at fixed T: p / |1 + impact|; a vanishing slope asks no precision (null).
    assert impacts["precision"] == [pytest.approx(0.008), None, pytest.approx(0.02)]
