"""An API solve without a scene gets the Roman default; "scene": "paper" the paper's tables."""

import pytest

from nlpsf.sim import ramps


@pytest.fixture(scope="module")
def patient_client(tmp_path_factory):
    from fastapi.testclient import TestClient
    from nlpsf.web.main import create_app
    from nlpsf.web.settings import Settings

    settings = Settings(db_path=str(tmp_path_factory.mktemp("db") / "jobs.sqlite3"), job_workers=1, solve_wait_s=600)
    with TestClient(create_app(settings)) as client:
        yield client


@pytest.mark.slow
def test_an_api_solve_without_a_scene_is_the_roman_default(patient_client):
    response = patient_client.post("/api/v1/solve", json={"band": "H158", "magnitude": 19.0, "precision": 0.01})
    assert response.status_code == 200, response.text
    answer = response.json()
    conditions = answer["conditions"]
    assert conditions["scene_name"] == "roman" and conditions["linearise_at"] == "corrected"
    assert conditions["ramp"]["ma_table"] == "romanisim-4" and conditions["ramp"]["fit"] == "optimal"
    assert answer["exptime"] == pytest.approx(ramps.load_ma_table("C2A_IMG_HLWAS").duration_s)
    assert {v["name"] for v in conditions["roman_default"]} >= {"jitter", "charge_diffusion", "sed", "readout"}
    # No position: the most demanding of the SCA's nodes, the range beside it.
    span = conditions["sca_range"]
    assert answer["tolerance"] == span["most_demanding"]["tolerance"] >= span["least_demanding"]["tolerance"]
    assert "sca_range" in answer["flag_codes"]


def test_scene_paper_in_the_api_is_the_table_answer(patient_client):
    body = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}
    paper = patient_client.post("/api/v1/solve", json={**body, "scene": "paper"}).json()
    preset = patient_client.post("/api/v1/solve", json={**body, "scene": {"preset": "paper"}}).json()
    assert paper["fidelity"] == "table" and paper["exptime"] == 168.1 and paper["conditions"]["scene_name"] == "paper"
    assert paper["precision"] == preset["precision"]
    # The library's paper answer, the same number.
    from nlpsf.solve import solver

    assert paper["precision"] == solver.solve("H158", magnitude=18.3, tolerance=1e-4, scene="paper").precision
