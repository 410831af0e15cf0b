"""POST /solve/batch answers the Roman default from its shipped field grid, exactly as POST /solve
answers the same request (the job that runs ``solver.answer``), and refuses on their own the rows
that need a fresh simulation, naming the field and where to send them."""

import pytest

from nlpsf.slopes import fieldgrid

pytestmark = pytest.mark.skipif(fieldgrid.shipped_grid() is None, reason="the Roman default's field grid is not installed")

BASE = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}

#: Rows a single /solve answers from the tables or the grid: no position (the SCA range), a
#: position (as a preset's fields and as the scene's only field), a magnitude solve, the paper's scene.
ROWS = [
    BASE,
    {**BASE, "scene": {"position": [1000.0, 3000.0]}},
    {
        "band": "W146",
        "sca": 6,
        "metric": "e2",
        "precision": 0.01,
        "magnitude": 20.5,
        "scene": {"preset": "roman", "position": [3000.0, 1200.0]},
    },
    {"band": "J129", "sca": 3, "precision": 0.01, "tolerance": 1e-4},
    {**BASE, "scene": "paper"},
]


@pytest.fixture(scope="module")
def patient_client(tmp_path_factory):
    from fastapi.testclient import TestClient
    from nlpsf.web.main import create_app
    from nlpsf.web.settings import Settings

    settings = Settings(db_path=str(tmp_path_factory.mktemp("db") / "jobs.sqlite3"), job_workers=1, solve_wait_s=600)
    with TestClient(create_app(settings)) as client:
        yield client


def _without_timing(solution: dict) -> dict:
    return {k: v for k, v in solution.items() if k != "elapsed_s"}


@pytest.mark.slow
def test_a_batch_row_is_the_single_solve_of_that_row(patient_client):
    batch = patient_client.post("/api/v1/solve/batch", json={"requests": ROWS})
    assert batch.status_code == 200, batch.text
    results = batch.json()["results"]
    assert [r["ok"] for r in results] == [True] * len(ROWS), [r.get("error") for r in results]
    for row, result in zip(ROWS, results, strict=True):
        single = patient_client.post("/api/v1/solve", json=row)
        assert single.status_code == 200, single.text
        # The whole answer: the solved value, every uncertainty part, the conditions (the SCA range's
        # nodes, the default's values and sources), the flags.
        assert _without_timing(result["solution"]) == _without_timing(single.json()), row
    default, at_position = results[0]["solution"], results[1]["solution"]
    assert default["fidelity"] == at_position["fidelity"] == "table"
    span = default["conditions"]["sca_range"]
    assert default["precision"] == span["most_demanding"]["precision"] <= span["least_demanding"]["precision"]
    assert "sca_range" not in at_position["conditions"] and "default_from_grid" in at_position["flag_codes"]
    assert results[4]["solution"]["conditions"]["scene_name"] == "paper"


#: Rows whose answer needs a fresh simulation, and the field each refusal names.
NEEDS_SIMULATION = [
    ({**BASE, "beta0": 6e-7}, "beta0"),
    ({**BASE, "scene": {"jitter": 0.01}}, "scene"),
    ({**BASE, "accuracy": 0.01}, "accuracy"),
    ({**BASE, "pupil_scale": "header"}, "pupil_scale"),
    ({**BASE, "linearise_at": "beta0"}, "linearise_at"),
    ({**BASE, "fidelity": "linear"}, "fidelity"),
    ({**BASE, "scene": "galsim-roman"}, "scene"),
    ({**BASE, "exptime": 200.0}, "exptime"),
]
#: Fainter than every node's magnitudes: answered from the grid's faint end by the flux law, flagged.
FAINTER_THAN_THE_GRID = {**BASE, "magnitude": 30.0, "scene": {"position": [1000.0, 3000.0]}}


def test_rows_that_need_a_simulation_are_refused_alone_with_where_to_send_them(client):
    rows = [
        BASE,
        *(row for row, _ in NEEDS_SIMULATION),
        {**BASE, "magnitude": "x"},
        FAINTER_THAN_THE_GRID,
        {**BASE, "scene": "paper"},
    ]
    response = client.post("/api/v1/solve/batch", json={"requests": rows})
    assert response.status_code == 200
    body = response.json()
    results = body["results"]
    assert [r["index"] for r in results] == list(range(len(rows)))
    assert (body["answered"], body["failed"]) == (3, len(NEEDS_SIMULATION) + 1)
    assert results[0]["ok"] and results[-1]["ok"] and results[-2]["ok"]
    assert "extrapolated_faint" in results[-2]["solution"]["flag_codes"]
    for (row, field), result in zip(NEEDS_SIMULATION, results[1:-3], strict=True):
        assert not result["ok"], row
        error = result["error"]
        assert error["type"] == "/problems/needs-simulation" and error["status"] == 422, (row, error)
        assert error["field"] == field and error["send_to"] == "/api/v1/solve", (row, error)
        assert "/api/v1/solve" in error["detail"]
    invalid = results[-3]["error"]
    assert invalid["type"] == "/problems/invalid-input" and invalid["field"] == "magnitude"


def test_a_position_row_of_the_page_csv_is_the_api_row(client):
    text = "band,scene,position,precision,magnitude\nH158,,1000 3000,1%,19\nH158,roman,1000;3000,0.01,19\nH158,paper,,1%,19\n"
    answer = client.post("/api/v1/page/batch", content=text, headers={"Content-Type": "text/csv"}).json()
    assert [r["ok"] for r in answer["results"]] == [True, True, True], answer["results"]
    row = {"band": "H158", "precision": 0.01, "magnitude": 19.0, "scene": {"position": [1000.0, 3000.0]}}
    api = client.post("/api/v1/solve/batch", json={"requests": [row]}).json()["results"][0]["solution"]
    first, second, paper = (r["solution"] for r in answer["results"])
    assert first["tolerance"] == second["tolerance"] == api["tolerance"]
    assert first["conditions"] == api["conditions"] and paper["conditions"]["scene_name"] == "paper"
    assert first["tolerance"] != paper["tolerance"]


def test_the_pages_example_batch_is_answered_in_full(client):
    import html
    import re
    from pathlib import Path

    page = (Path(__file__).resolve().parents[2] / "static" / "index.html").read_text(encoding="utf-8")
    example = html.unescape(re.search(r'<textarea id="batch-text"[^>]*>(.*?)</textarea>', page, re.S).group(1))
    answer = client.post("/api/v1/page/batch", content=example, headers={"Content-Type": "text/csv"}).json()
    assert answer["failed"] == 0 and answer["answered"] == len(example.strip().splitlines()) - 1, answer["results"]
    scenes = [r["solution"]["conditions"]["scene_name"] for r in answer["results"]]
    assert "roman" in scenes and "paper" in scenes
