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
