"""The page's own endpoints (app/page_api.py), without a browser: the curves are POST /solve's answers
for the same question (its scene, position and readout) at any magnitude, scale as the shipped table
reads, tell one saturation story; the limits bracket what /solve answers; the CSV batch reads
percents and names bad input; the downloads say their units; the guide is served as shipped."""

from __future__ import annotations

import csv
import io
import json
import random
from pathlib import Path

import pytest

from nlpsf.solve import solver

from .. import shipped
from ..servers import wait_for

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def client_settings():
    return {}  # the service's own limits


def curves(client, body: dict, at=(), overlay: bool = False) -> dict:
    params = {"at": list(at), **({"overlay": "true"} if overlay else {})}
    response = client.post("/api/v1/page/requirement", params=params, json=body)
    assert response.status_code == 200, response.text
    return response.json()


def posted_solve(client, body: dict):
    """POST /solve, a fresh simulation (the default between the limits at a position) followed to its
    end however busy the machine is: past the deployment's wait it is a job to poll (202)."""
    response = client.post("/api/v1/solve", json=body)
    if response.status_code == 202:
        location = response.headers["Location"]
        wait_for(lambda: client.get(location).json()["status"] not in ("queued", "running"), timeout=600, interval=0.5)
        response = client.post("/api/v1/solve", json=body)  # now from the stored result
    return response


def solved(client, body: dict) -> dict:
    response = posted_solve(client, body)
    assert response.status_code == 200, response.text
    return response.json()


QUESTIONS = [
    pytest.param({"band": "H158"}, id="default-whole-SCA"),
    pytest.param({"band": "W146", "scene": {"position": [700, 3900]}}, id="default-at-a-position"),
    pytest.param({"band": "J129", "metric": "e2", "scene": {"preset": "roman", "position": [4000, 100]}}, id="default-e2"),
    pytest.param({"band": "H158", "scene": "paper"}, id="paper"),
    pytest.param({"band": "Y106", "scene": "paper", "mode": "scatter", "stars": 9, "exptime": 120.0}, id="paper-scatter"),
]


@pytest.mark.parametrize("question", QUESTIONS)
def test_the_drawn_curve_is_the_solve_answer_at_random_magnitudes(client, question):
    # The page posts /solve's own body: what it draws is that request's scene, position and readout.
    # At random magnitudes (added to the grid, as the page adds its answer's), the curve is the answer
    # POST /solve gives for the same question there.
    rng = random.Random(str(question))
    at = [round(rng.uniform(15.0, 26.0), 5) for _ in range(5)]
    data = curves(client, {**question, "tolerance": 1e-4, "magnitude": 19.0}, at=at)["curves"]
    chosen = next(r for r in data["requirement"] if r["factor"] == 1.0)
    compared = 0
    for m in at:
        i = data["magnitude"].index(m)
        response = posted_solve(client, {**question, "tolerance": 1e-4, "magnitude": m})
        if response.status_code == 422:
            assert chosen["precision"][i] is None, f"/solve refuses m={m}; the curve has a value"
            continue
        assert response.status_code == 200, response.text
        answer = response.json()
        if "default_between_limits" in answer["flag_codes"]:
            # Between the saturation limits at a position /solve simulates afresh (issue 28): no curve value there.
            assert chosen["precision"][i] is None
            continue
        assert chosen["precision"][i] == pytest.approx(answer["precision"], rel=1e-9, abs=0)
        assert data["slope"][i] == pytest.approx(answer["slope"], rel=1e-9, abs=0)
        compared += 1
    assert compared >= 3
    # A tolerance answer: its T is the curves' T, and its point (m, p) is on the chosen curve.
    answer = solved(client, {**question, "precision": 0.02, "magnitude": 21.3})
    data = curves(client, {**question, "precision": 0.02, "magnitude": 21.3}, at=[21.3])["curves"]
    assert data["tolerance"] == pytest.approx(answer["tolerance"], rel=1e-9, abs=0)
    chosen = next(r for r in data["requirement"] if r["factor"] == 1.0)
    assert chosen["precision"][data["magnitude"].index(21.3)] == pytest.approx(0.02, rel=1e-9)


def test_the_curves_scale_with_the_tolerance_as_the_shipped_table_reads(client):
    data = curves(client, {"band": "H158", "scene": "paper", "tolerance": 1e-4, "magnitude": 18.3})["curves"]
    by_factor = {round(c["factor"], 3): c for c in data["requirement"]}
    chosen = by_factor[1.0]
    assert 18.3 in data["magnitude"], "the request's magnitude is on the grid"
    # T = |c| p beta0: p is proportional to T at every magnitude ...
    for low, high in zip(by_factor[0.1]["precision"], by_factor[10.0]["precision"], strict=True):
        if low is not None and high is not None:
            assert high == pytest.approx(100 * low, rel=1e-9)
    # ... and inversely proportional to the slope, read from the shipped ECSV (astropy, scipy's spline)
    # at the conditions the answer names (the paper's scene: its 168.1 s), not from the same endpoint.
    conditions = data["conditions"]
    assert (conditions["exptime"], conditions["beta0"]) == (shipped.exptime_s(), 5e-7)
    keep = [i for i, p in enumerate(chosen["precision"]) if p is not None]
    slopes = shipped.slope("H158", 18, "size", "bias", [data["magnitude"][i] for i in keep])
    for i, c in zip(keep, slopes, strict=True):
        assert chosen["precision"][i] * abs(c) * 5e-7 == pytest.approx(1e-4, rel=1e-9)
    # The limits are the solver's own: its saturation magnitude for this question.
    answer = solved(client, {"band": "H158", "scene": "paper", "tolerance": 1e-4, "magnitude": 18.3})
    assert data["limits"]["saturation_magnitude"] == pytest.approx(answer["saturation_magnitude"], rel=1e-12)


def test_one_saturation_story_for_the_default_ramp(client):
    # The Roman default up its ramp: the limit that binds is the resultant a slope needs; the final
    # frame's is named as such. With a position both are that answer's own.
    body = {"band": "W146", "tolerance": 1e-4, "magnitude": 18.3, "scene": {"position": [1000, 3000]}}
    answer = solved(client, body)
    limits = curves(client, body)["curves"]["limits"]
    assert limits["readout"] == "ramp"
    # Between the limits the answer is simulated afresh (issue 28): its limits are its own star's prepared
    # peak, the curve's the grid's nodes interpolated (equal to 4e-9 mag); elsewhere the same numbers.
    rel = 1e-8 if "default_between_limits" in answer["flag_codes"] else 1e-12
    assert limits["saturation_magnitude"] == pytest.approx(answer["saturation_magnitude"], rel=rel)
    assert limits["final_frame_saturation_magnitude"] == pytest.approx(answer["final_frame_saturation_magnitude"], rel=rel)
    assert limits["saturation_magnitude"] < 18.3 < limits["final_frame_saturation_magnitude"]
    # Without a position: the faintest limit over the SCA's nodes, which the answer's node's lies within.
    whole_body = {**body, "scene": None}
    whole = curves(client, whole_body)["curves"]["limits"]
    low, high = whole["saturation_range"]
    assert whole["saturation_magnitude"] == high
    assert low <= solved(client, whole_body)["saturation_magnitude"] <= high


def test_the_paper_overlay_and_published_points(client):
    default = curves(client, {"band": "H158", "tolerance": 1e-4, "magnitude": 18.3}, overlay=True)
    assert default["paper"] is not None and default["published"] is None
    exptime = default["curves"]["conditions"]["exptime"]
    paper_answer = solved(client, {"band": "H158", "scene": "paper", "exptime": exptime, "tolerance": 1e-4, "magnitude": 21.0})
    i = default["paper"]["magnitude"].index(21.0)
    chosen = next(r for r in default["paper"]["requirement"] if r["factor"] == 1.0)
    assert chosen["precision"][i] == pytest.approx(paper_answer["precision"], rel=1e-9)
    paper = curves(client, {"band": "H158", "scene": "paper", "tolerance": 1e-4, "magnitude": 18.3}, overlay=True)
    assert paper["paper"] is None  # the answer is the paper's scene already
    published = json.loads((ROOT / "nlpsf" / "data" / "paper" / "published_data.json").read_text())
    assert paper["published"]["slope"] == published["fig3_bias_slopes_per_beta"]["H158"]["size"]
    assert paper["published"]["magnitude"] == published["magnitudes"]


def test_a_question_without_a_curve_at_table_cost_says_why(client):
    body = {"band": "H158", "tolerance": 1e-4, "magnitude": 18.3, "scene": {"preset": "roman", "jitter": 0.02}}
    data = curves(client, body)["curves"]
    assert data["needs_simulation"] and "simulated" in data["needs_simulation"]
    over_field = curves(client, {"band": "H158", "tolerance": 1e-4, "magnitude": 18.3, "over_field": "sca"})["curves"]
    assert "worst" in over_field["needs_simulation"]


def test_slopes_of_every_band_are_the_questions(client):
    body = {"band": "H158", "tolerance": 1e-4, "magnitude": 18.3, "scene": {"position": [1000, 3000]}}
    response = client.post("/api/v1/page/slopes", params={"at": [18.3]}, json=body)
    assert response.status_code == 200, response.text
    by_band = {c["band"]: c for c in response.json()["curves"]}
    assert set(by_band) >= {"H158", "W146", "F184"}
    for band in ("W146", "F184"):
        answer = solved(client, {**body, "band": band})
        curve = by_band[band]
        value = curve["slope"][curve["magnitude"].index(18.3)]
        if "default_between_limits" in answer["flag_codes"]:  # simulated afresh there (issue 28): no curve value
            assert value is None
            continue
        assert value == pytest.approx(abs(answer["slope"]), rel=1e-9)
        assert curve["where"]["kind"] == "position"


def test_limits_bracket_what_the_solver_answers(client):
    for body in ({"band": "J129", "sca": 3, "scene": "paper"}, {"band": "J129", "sca": 3}):
        limits = client.post("/api/v1/page/limits", json={**body, "tolerance": 1e-4, "magnitude": 20}).json()
        brightest = limits["brightest_answered_magnitude"]
        assert solved(client, {**body, "tolerance": 1e-4, "magnitude": brightest + 0.01})["precision"] > 0
        refused = client.post("/api/v1/solve", json={**body, "tolerance": 1e-4, "magnitude": brightest - 0.01})
        assert refused.status_code == 422 and refused.json()["field"] == "magnitude"
    assert limits["readout"] == "ramp" and limits["saturation_magnitude"] > brightest


def test_the_full_tables_download_says_its_units_provenance_and_columns(client):
    text = client.get("/api/v1/page/tables.csv").text
    header = [line for line in text.splitlines() if line.startswith("#")]
    body = [line for line in text.splitlines() if not line.startswith("#")]
    rows = list(csv.DictReader(body))
    plain = list(csv.DictReader(io.StringIO(client.get("/api/v1/tables.csv").text)))
    assert rows == plain, "the same rows as the tables' own CSV"
    described = {line.split(":", 1)[0].strip("# ").strip() for line in header if line.startswith("#   ")}
    assert set(rows[0]) <= described, "every column is explained"
    assert any("bias_size_interp" in line and "interpolated back" in line for line in header)
    assert any("fingerprint" in line for line in header) and any("exptime_s in s" in line for line in header)


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


def test_batch_csv_that_would_lose_or_swap_a_value_is_refused_naming_the_line(client):
    # A column named twice (which band?) and a cell beyond the header (dropped, once) are refused, not answered.
    for text, named in (("band,band,precision,magnitude\nH158,J129,0.01,19\n", "band more than once"),
                        ("band,precision,magnitude\nH158,0.01,19\nH158,0.01,19,20\n", "line 3 has 4 cells")):  # fmt: skip
        refused = client.post("/api/v1/page/batch", content=text, headers={"Content-Type": "text/csv"})
        assert refused.status_code == 422 and refused.json()["field"] == "csv" and named in refused.json()["detail"]
    padded = client.post(
        "/api/v1/page/batch", content="band,precision,magnitude,\nH158,0.01,19,\n", headers={"Content-Type": "text/csv"}
    )
    assert padded.status_code == 200 and padded.json()["results"][0]["ok"]


def test_batch_csv_echoes_a_cell_that_is_no_finite_number_as_sent(client):
    # "nan", "inf" cells (and a position holding one) are refused by their own field, and the
    # answer's echo of the rows shows what was sent: JSON has no NaN, and a null would read as a
    # cell left empty (which asks for that quantity to be solved).
    text = "band,tolerance,magnitude,precision,position\nH158,nan,19,,\nH158,1e-4,inf,,\nH158,1e-4,,-inf%,\nH158,1e-4,19,,nan 3\n"
    answer = client.post("/api/v1/page/batch", content=text, headers={"Content-Type": "text/csv"}).json()
    assert [r["ok"] for r in answer["results"]] == [False] * 4
    assert [r["error"]["field"].split(".")[0] for r in answer["results"]] == ["tolerance", "magnitude", "precision", "scene"]
    sent = [answer["requests"][0]["tolerance"], answer["requests"][1]["magnitude"], answer["requests"][2]["precision"]]
    assert sent == ["nan", "inf", "-inf%"] and answer["requests"][3]["scene"]["position"] == "nan 3"


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
    # Which presets fill a blank background with a sky: as a solve on each fills it.
    for name in presets["scenes"]:
        scene = {"preset": name, "position": [2000, 2000]} if presets["scenes"][name]["sky"] else name
        body = {"band": "H158", "magnitude": 20.0, "tolerance": 1e-3, "scene": scene}
        answer = client.post("/api/v1/solve", params={"wait": 0}, json=body)
        if answer.status_code == 202:  # simulated (galsim-roman): the job's scene holds what was filled
            client.delete(f"/api/v1/simulations/{answer.json()['id']}")
            continue
        sky = answer.json()["conditions"]["scene"]["background_e"] if answer.json()["conditions"].get("scene") else 0.0
        assert presets["scenes"][name]["sky"] is (sky > 0), (name, sky)


def test_the_page_reads_its_impacts_from_the_library(client):
    impacts = client.get("/api/v1/page/impact-terms", params={"precision": 0.01, "impact": [0.25, -1.0, -1.5]}).json()
    # T = |c| p beta0 at fixed T: p / |1 + impact|; a vanishing slope asks no precision (null).
    assert impacts["precision"] == [pytest.approx(0.008), None, pytest.approx(0.02)]


def test_the_page_can_ask_for_a_simulated_answers_job_at_once(client):
    # The page shows the progress of an answer that needs a simulation: with wait=0 /solve returns
    # its job (202, Location) instead of waiting solve_wait_s; the job ends with the same answer.
    from ..servers import finished_job

    body = {"band": "H158", "tolerance": 1e-4, "magnitude": 19.0, "scene": "paper", "fidelity": "linear"}
    response = client.post("/api/v1/solve", params={"wait": 0}, json=body)
    if response.status_code == 200:  # an identical earlier request: answered from stored results
        assert response.json()["fidelity"] == "linear"
        return
    assert response.status_code == 202 and response.headers["location"].startswith("/api/v1/simulations/")
    job = finished_job(client, response.json()["id"]).json()
    assert job["status"] == "done"
    waited = client.post("/api/v1/solve", json=body).json()  # now from stored results
    assert job["result"]["precision"] == pytest.approx(waited["precision"], rel=1e-12)
