"""The scene, the impact report and the field through the REST API: the same library numbers, bad input named."""

from __future__ import annotations

import pytest

from nlpsf.sim import experiment
from nlpsf.sim import scene as scenes
from nlpsf.solve import solver

from ..servers import finished_job


def test_api_simulation_with_scene_matches_the_library(client):
    body = {"magnitudes": [19.0], "betas": [5e-7], "realizations": 4, "scene": {"preset": "galsim-roman", "position": [300, 400]}}
    job = client.post("/api/v1/simulations", params={"wait": 120}, json=body).json()
    assert job["status"] == "done", job
    model = scenes.from_request({"preset": "galsim-roman", "position": [300, 400]})
    want = experiment.simulate(experiment.SimulationConfig(realizations=4, scene=model), [19.0], [5e-7])[0]
    assert job["result"]["results"][0]["dR_over_R"]["mean"] == pytest.approx(want.dR_over_R.mean, rel=1e-12)


@pytest.mark.parametrize(
    ("scene", "field"),
    [
        ({"jitter": -0.01}, "scene.jitter"),
        ({"sed": "vega"}, "scene.sed"),
        ({"ipc": [[0.0, 0.1], [0.1, 1.0]]}, "scene.ipc"),
        ({"position": [0, 100]}, "scene.position"),
        ({"position": [5000, 100]}, "scene.position"),
        ({"ipc_order": "during"}, "scene.ipc_order"),
        ({"preset": "hubble"}, "scene.preset"),
        ({"colour": "red"}, "scene.colour"),
    ],
)
def test_api_bad_scene_is_422_naming_the_field(client, scene, field):
    for path, body in (("/api/v1/simulations", {"realizations": 2}), ("/api/v1/impact", {"realizations": 2})):
        response = client.post(path, json={**body, "scene": scene})
        assert response.status_code == 422, response.text
        assert response.json()["field"] == field


@pytest.mark.parametrize(
    ("scene", "field"),
    [
        ({"position": [0, 100]}, "scene.position"),
        ({"position": "a b"}, "scene.position"),
        ({"jitter": "x"}, "scene.jitter"),
        ({"preset": "hubble"}, "scene.preset"),
        ({"colour": "red"}, "scene.colour"),
        ("hubble", "scene"),
    ],
)
def test_a_solves_bad_scene_names_what_is_wrong_in_it(client, scene, field):
    # A solve's scene is a preset's name or an object: an object with a bad field is named by that
    # field, not answered with the names' error ("Input should be 'roman', 'paper' or ...").
    body = {"band": "H158", "magnitude": 20.0, "precision": 0.01, "scene": scene}
    response = client.post("/api/v1/solve", json=body)
    assert response.status_code == 422 and response.json()["field"] == field, response.text
    assert response.json()["detail"].startswith(f"{field}: ")
    row = client.post("/api/v1/solve/batch", json={"requests": [body]}).json()["results"][0]
    assert row["ok"] is False and row["error"]["field"] == field


def test_api_nan_in_scene_is_422(client):
    response = client.post("/api/v1/impact", content='{"scene": {"jitter": NaN}}', headers={"content-type": "application/json"})
    assert response.status_code == 422 and response.json()["field"] == "scene.jitter"


def test_api_impact(client):
    response = client.post(
        "/api/v1/impact", json={"band": "H158", "magnitude": 19.0, "realizations": 4, "scene": {"jitter": 0.02}}
    )
    assert response.status_code == 200, response.text
    report = response.json()
    jitter = next(e for e in report["effects"] if e["name"] == "jitter")
    assert jitter["on"] and jitter["impact"]["size"] < 0
    assert client.post("/api/v1/impact", json={"realizations": 501}).json()["limit"] == "max_realizations"


def test_api_impact_is_a_job_not_work_in_the_http_worker(make_client):

    from nlpsf.solve import impact

    body = {"band": "J129", "sca": 3, "magnitude": 19.5, "realizations": 4, "scene": {"ipc": "roman"}}
    with make_client(solve_wait_s=0.0) as test_client:
        queued = test_client.post("/api/v1/impact", json=body)
        assert queued.status_code == 202, queued.text
        job = queued.json()
        assert job["request"]["kind"] == "impact" and queued.headers["location"].endswith(job["id"])
        done = finished_job(test_client, job["id"])
        report = done.json()["result"]
        # The job's report is the library's, computed in the worker.
        direct = impact.impact("J129", 3, 19.5, scene=scenes.from_request(body["scene"]), realizations=4)
        assert [e["impact"] for e in report["effects"]] == [e["impact"] for e in direct["effects"]]
        assert next(e for e in report["effects"] if e["name"] == "ipc")["on"]
        # The same request again is answered from the stored result.
        again = test_client.post("/api/v1/impact", json=body)
        assert again.status_code == 200 and again.json()["effects"] == report["effects"]
        # Bad input is refused before anything is queued.
        refused = test_client.post("/api/v1/impact", json={**body, "magnitude": 99.0})
        assert refused.status_code == 422 and refused.json()["field"] == "magnitude"


def test_api_solve_over_field_and_with_scene(client):
    body = {"band": "J129", "sca": 3, "magnitude": 19.0, "tolerance": 1e-4, "over_field": "sca", "scene": "paper"}
    response = client.post("/api/v1/solve", json=body)
    assert response.status_code == 200, response.text
    assert len(response.json()["conditions"]["over_field"]) == 5
    # From the shipped field-point tables, answered at once (not a job): the library's answer.
    assert response.json()["conditions"]["fidelity"] == "table"
    assert (
        response.json()["precision"]
        == solver.solve_over_field("J129", [3], magnitude=19.0, tolerance=1e-4, scene="paper").precision
    )
    focal_plane = client.post("/api/v1/solve", json={**body, "over_field": "focal_plane"})
    assert focal_plane.status_code == 200 and len(focal_plane.json()["conditions"]["over_field"]) == 90
    with_scene = client.post(
        "/api/v1/solve", json={**body, "over_field": None, "scene": {"jitter": 0.014, "preset": "paper"}}
    ).json()
    assert with_scene["fidelity"] == "linear" and with_scene["conditions"]["scene"]["jitter_arcsec"] == 0.014
    assert client.post("/api/v1/solve", json={**body, "over_field": "everywhere"}).status_code == 422


@pytest.mark.slow
def test_api_solve_with_another_pupil_scale_is_a_job_and_a_batch_refuses_it(make_client):
    body = {"band": "H158", "magnitude": 20.0, "precision": 0.01, "pupil_scale": "official", "scene": "paper"}
    with make_client(solve_wait_s=0.0) as test_client:
        queued = test_client.post("/api/v1/solve", json=body)
        assert queued.status_code == 202, queued.text
        result = finished_job(test_client, queued.json()["id"]).json()["result"]
        direct = solver.solve("H158", magnitude=20.0, precision=0.01, pupil_scale="official", scene="paper")
        assert result["conditions"]["pupil_scale"] == "official" and result["tolerance"] == pytest.approx(direct.tolerance)
        # The tables' own rule stays an instant table answer.
        plain = test_client.post("/api/v1/solve", json={**body, "pupil_scale": "galsim"})
        assert plain.status_code == 200 and plain.json()["conditions"]["fidelity"] == "table"
        batch = test_client.post("/api/v1/solve/batch", json={"requests": [body]})
        assert batch.status_code == 200 and batch.json()["results"][0]["ok"] is False


def test_a_solves_background_given_is_not_replaced_by_the_sky(client):
    # No sky (background 0) on the Roman default is another scene than the field grid's: a job, as the
    # CLI's --background 0 is simulated, never the grid's answer over the default's sky.
    body = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}
    with_sky = client.post("/api/v1/solve", json={**body, "scene": {"position": [100, 200]}})
    assert with_sky.status_code == 200 and with_sky.json()["conditions"]["scene"]["background_e"] > 10
    for scene in ({"position": [100, 200], "background": 0}, {"background": 0}):
        response = client.post("/api/v1/solve", params={"wait": 0}, json={**body, "scene": scene})
        assert response.status_code == 202, response.text
        job = client.get(f"/api/v1/simulations/{response.json()['id']}").json()
        assert job["request"]["solve"]["request"]["scene"]["background"] == 0.0  # the job's own request: no sky
        client.delete(f"/api/v1/simulations/{job['id']}")
