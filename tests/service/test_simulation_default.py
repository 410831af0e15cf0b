"""POST /api/v1/simulations simulates what the CLI's ``simulate`` simulates: the Roman default
(nlpsf.request.presets) unless the request names the paper's scene, which stays as before."""

from __future__ import annotations

import json

import pytest

from nlpsf.cli import main
from nlpsf.request import presets as roman_default

BODY = {"band": "J129", "sca": 7, "magnitudes": [20.0], "betas": [5e-7], "realizations": 2, "stamp": 48, "fidelity": "linear"}
CLI = ["simulate", "--band", "J129", "--sca", "7", "--magnitude", "20", "--beta", "5e-7", "--realizations", "2",
       "--stamp", "48", "--method", "linear", "--json", "--quiet"]  # fmt: skip


def cli_result(capsys, *extra: str) -> dict:
    capsys.readouterr()
    assert main([*CLI, *extra]) == 0
    out = json.loads(capsys.readouterr().out)
    return out[0] if isinstance(out, list) else out


def served(client, body: dict) -> dict:
    job = client.post("/api/v1/simulations", params={"wait": 120}, json=body).json()
    assert job["status"] == "done", job
    return job["result"]


@pytest.mark.parametrize(
    ("extra_body", "extra_cli"),
    [({}, ()), ({"scene": "paper"}, ("--scene", "paper")), ({"scene": {"position": [500, 3000]}}, ("--position", "500,3000"))],
)
def test_a_simulation_is_the_clis_for_the_same_request(client, capsys, extra_body, extra_cli):
    result = served(client, {**BODY, **extra_body})
    want = cli_result(capsys, *extra_cli)
    got = result["results"][0]
    assert result["conditions"]["exptime_s"] == pytest.approx(want["exptime_s"], rel=1e-12)
    assert result["conditions"]["pupil_scale"] == want["conditions"]["pupil_scale"]
    for metric in ("dR_over_R", "de1", "de2"):
        assert got[metric]["mean"] == pytest.approx(want[metric]["mean"], rel=1e-12)


def test_the_default_is_the_roman_defaults_readout_and_the_paper_keeps_its_final_frame(client):
    default = served(client, BODY)["conditions"]
    assert default["exptime_s"] == pytest.approx(roman_default.exptime_s(), rel=1e-12)
    assert default["pupil_scale"] == roman_default.PUPIL_SCALE
    paper = served(client, {**BODY, "scene": "paper"})["conditions"]
    assert paper["exptime_s"] == 168.1 and paper["pupil_scale"] == "galsim"


def test_a_default_simulation_names_its_scene_as_a_default_solve_does(client):
    # The sky fill_simulation fills in is the default's own: the scene stays the preset "roman", as a
    # solve's does (it was unnamed, so the result read as a custom scene); a sky the client gives is a
    # change from it, and the scene is then unnamed (described by its values).
    solve = client.post("/api/v1/solve", json={"band": "J129", "sca": 7, "magnitude": 20.0, "precision": 0.01}).json()
    assert solve["conditions"]["scene_name"] == "roman"
    for extra in ({}, {"scene": {"position": [500, 3000]}}):
        conditions = served(client, {**BODY, **extra})["conditions"]
        assert conditions["scene"]["name"] == "roman" and conditions["scene_description"].startswith("roman:")
        assert conditions["scene"]["background_e"] == pytest.approx(roman_default.readout("J129", 7).background_e, rel=1e-12)
    own_sky = served(client, {**BODY, "scene": {"background": 500.0}})["conditions"]
    assert own_sky["scene"]["name"] is None and own_sky["scene"]["background_e"] == 500.0
