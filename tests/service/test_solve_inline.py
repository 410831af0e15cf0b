"""POST /solve answers inline whatever the tables or the Roman default's field grid answer (the cost
of the answer decides, not the scene), with the answer the job gives; what needs a simulation is
still a job. And extreme tolerances: an answer or a 422 naming the field, never a 500."""

from __future__ import annotations

import json

import pytest
from nlpsf.web import job_kinds

#: Requests the field grid answers: at a position (both ways of giving it), and the SCA range.
GRID_BODIES = [
    {"band": "H158", "magnitude": 19.0, "precision": 0.01, "scene": {"position": [1000, 3000]}},
    {"band": "J129", "sca": 7, "precision": 0.01, "tolerance": 1e-4, "metric": "e1", "scene": {"position": [300, 2500]}},
    {"band": "H158", "magnitude": 19.0, "precision": 0.01},
    {"band": "F184", "sca": 3, "tolerance": 1e-4, "magnitude": 18.5, "scene": "roman"},
]


@pytest.fixture(scope="module")
def client(make_client_module):
    # No wait for a job's answer: a job comes back 202, an inline answer 200.
    with make_client_module(solve_wait_s=0.0) as test_client:
        yield test_client


@pytest.fixture(scope="module")
def make_client_module(tmp_path_factory):
    from tests.conftest import _service_client

    return lambda **overrides: _service_client(tmp_path_factory.mktemp("inline") / "jobs.sqlite3", overrides)


def _without_elapsed(answer: dict) -> dict:
    return {k: v for k, v in answer.items() if k != "elapsed_s"}


@pytest.mark.parametrize("body", GRID_BODIES, ids=["position", "e1-position", "sca-range", "preset-roman"])
def test_a_field_grid_answer_is_inline_and_is_the_jobs_answer(client, body):
    response = client.post("/api/v1/solve", json=body)
    assert response.status_code == 200, response.text
    assert "location" not in response.headers  # not a job
    inline = response.json()
    assert "default_from_grid" in inline["flag_codes"] or "sca_range" in inline["flag_codes"]
    # The job process's own run of the same request (what a 202 used to lead to).
    job = job_kinds.run(job_kinds.solve_job({"request": body, "over_field": None}))
    assert _without_elapsed(inline) == _without_elapsed(job)


@pytest.mark.parametrize(
    "body",
    [*GRID_BODIES, {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "scene": "paper"}],
    ids=["position", "e1-position", "sca-range", "preset-roman", "paper"],
)
def test_an_answer_is_sent_as_the_standard_librarys_compact_json_of_the_jobs_answer(client, body):
    # The bytes on the wire, first answer and kept one alike, are json.dumps of the job process's
    # answer with the service's documented spelling (compact, UTF-8 text as is, no NaN): the key
    # order, every number's spelling and every string as the standard library writes them.
    job = job_kinds.run(job_kinds.solve_job({"request": body, "over_field": None}))
    for _ in range(2):  # the second: a field-grid answer kept by request
        response = client.post("/api/v1/solve", json=body, headers={"accept-encoding": "identity"})
        assert response.status_code == 200, response.text
        served = {**job, "elapsed_s": response.json()["elapsed_s"]}  # a timing: the one value of its own
        expected = json.dumps(served, ensure_ascii=False, allow_nan=False, separators=(",", ":")).encode()
        assert response.content == expected


def test_a_request_the_grid_does_not_hold_is_still_a_job(client):
    # Another beta0 than the grid was built at: simulated.
    body = {"band": "H158", "magnitude": 19.0, "precision": 0.01, "beta0": 1e-6, "scene": {"position": [1000, 3000]}}
    queued = client.post("/api/v1/solve", json=body)
    assert queued.status_code == 202, queued.text
    assert queued.json()["request"]["kind"] == "solve"
    client.delete(f"/api/v1/simulations/{queued.json()['id']}")


@pytest.mark.parametrize("state", [{"linearise_at": "corrected"}, {"linearise_at": "corrected", "residual_nl": "per_read_beta"}])
def test_the_paper_scene_in_another_linearisation_state_is_a_job_not_seconds_inline(client, state):
    # The paper's tables hold the state at beta0 only: another is simulated (the batch refuses it),
    # so the single solve queues it too instead of simulating inside the HTTP worker.
    body = {"band": "Z087", "sca": 3, "tolerance": 1e-3, "precision": 0.01, "scene": "paper", **state}
    queued = client.post("/api/v1/solve", json=body)
    assert queued.status_code == 202, queued.text
    assert queued.json()["request"]["kind"] == "solve"
    client.delete(f"/api/v1/simulations/{queued.json()['id']}")
    refused = client.post("/api/v1/solve/batch", json={"requests": [body]}).json()
    assert refused["results"][0]["ok"] is False


def test_an_accuracy_is_still_a_job(client):
    body = {"band": "H158", "magnitude": 19.0, "precision": 0.01, "accuracy": 0.05, "scene": {"position": [1000, 3000]}}
    queued = client.post("/api/v1/solve", json=body)
    assert queued.status_code == 202, queued.text
    client.delete(f"/api/v1/simulations/{queued.json()['id']}")


@pytest.mark.parametrize(
    "extra",
    [{"scene": {"position": [1000, 3000]}}, {}, {"scene": {"preset": "roman", "position": [1000, 3000]}}],
    ids=["scene-position", "sca-range", "preset-position"],
)
@pytest.mark.parametrize("tolerance", [1e-9, 1e-13])
def test_a_tolerance_beyond_the_defaults_grid_is_answered_inline_and_flagged(client, extra, tolerance):
    # Fainter than the field grid the default's error falls as the flux (docs/ramps.md): extrapolated, inline.
    body = {"band": "H158", "precision": 0.01, "tolerance": tolerance, **extra}
    response = client.post("/api/v1/solve", json=body)
    assert response.status_code == 200, response.text
    answer = response.json()
    assert answer["binding_limit"] == "nonlinearity" and "extrapolated_answer" in answer["flag_codes"]
    assert ("fainter_than_40" in answer["flag_codes"]) == (answer["magnitude"] > 40)


def test_the_paper_scene_answers_extreme_tolerances(client):
    for tolerance, code in [(1e-7, None), (1e-13, "extrapolated_answer")]:
        body = {"band": "H158", "precision": 0.01, "tolerance": tolerance, "scene": "paper"}
        response = client.post("/api/v1/solve", json=body)
        assert response.status_code == 200, response.text
        answer = response.json()
        assert answer["binding_limit"] == "nonlinearity"
        if code:
            assert code in answer["flag_codes"]


def test_the_position_describes_the_default_alike_in_solve_batch_and_page_csv(client):
    from nlpsf.request import presets as roman_default

    row = {"band": "H158", "magnitude": 19.0, "precision": 0.01, "scene": {"position": [1000, 3000]}}
    single = client.post("/api/v1/solve", json=row).json()
    batch = client.post("/api/v1/solve/batch", json={"requests": [row]}).json()["results"][0]["solution"]
    text = "band,position,precision,magnitude\nH158,1000 3000,0.01,19\n"
    page = client.post("/api/v1/page/batch", content=text, headers={"Content-Type": "text/csv"}).json()
    page_row = page["results"][0]["solution"]
    sky = roman_default.fill(roman_default.NAME, "H158", 18, None, None, None, None).background_e
    own = roman_default.scene((1000.0, 3000.0), sky)  # the library's own default scene at the position
    for answer in (single, batch, page_row):
        assert answer["conditions"]["scene_description"] == own.describe()
        assert answer["conditions"]["scene"]["name"] == roman_default.NAME
