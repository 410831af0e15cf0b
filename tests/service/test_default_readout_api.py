"""A Roman-default solve that names only its fit, read noise or ramp rules gets them on the default's
own readout (its HLWAS table), as a simulation does; a ramp given without a fit gets the default's
likelihood fit, as the CLI does. (They were once dropped: the schema's "ols" reached the library as if
given, and a fit or read noise without a ramp was ignored, the answer silently the default's.)"""

import pytest
from nlpsf.web import job_parts, models

from nlpsf.request import presets as roman_default
from nlpsf.request.resolve import SolveRequest
from nlpsf.slopes import fieldgrid

BODY = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}


def _api_request(body: dict) -> SolveRequest:
    """The library request the API builds for a /solve or batch body (the same call both make)."""
    model = models.SolveRequest.model_validate(body)
    return job_parts.solve_request(job_parts.solve_body(model.model_dump(), model.model_fields_set))


def test_a_fit_or_read_noise_alone_changes_the_defaults_own_readout():
    default = _api_request(BODY)
    assert default.ramp.fit == roman_default.RAMP_FIT and default.ramp.table.name in ("romanisim-4", "C2A_IMG_HLWAS")
    ols = _api_request({**BODY, "ramp_fit": "ols"})
    assert ols.ramp.fit == "ols" and ols.ramp.table == default.ramp.table and ols.exptime == default.exptime
    noisy = _api_request({**BODY, "read_noise": 7.5})
    assert noisy.ramp.read_noise_e == 7.5 and noisy.ramp.fit == roman_default.RAMP_FIT
    assert noisy.ramp.table == default.ramp.table and default.ramp.read_noise_e != 7.5
    # Naming the default's own fit is the default.
    assert _api_request({**BODY, "ramp_fit": roman_default.RAMP_FIT}) == default


def test_a_ramp_without_a_fit_gets_the_scenes_fit():
    assert _api_request({**BODY, "ramp": 8}).ramp.fit == roman_default.RAMP_FIT
    assert _api_request({**BODY, "ramp": 8, "scene": "paper"}).ramp.fit == "ols"
    assert _api_request({**BODY, "ramp": 8, "ramp_fit": "ols"}).ramp.fit == "ols"


@pytest.mark.skipif(fieldgrid.shipped_grid() is None, reason="the Roman default's field grid is not installed")
def test_a_batch_row_with_another_fit_is_not_answered_from_the_defaults_grid(client):
    rows = [BODY, {**BODY, "ramp_fit": roman_default.RAMP_FIT}, {**BODY, "ramp_fit": "ols"}, {**BODY, "read_noise": 7.5}]
    results = client.post("/api/v1/solve/batch", json={"requests": rows}).json()["results"]
    assert [r["ok"] for r in results] == [True, True, False, False]
    assert results[0]["solution"] == {**results[1]["solution"], "elapsed_s": results[0]["solution"]["elapsed_s"]}
    assert {r["error"]["type"] for r in results[2:]} == {"/problems/needs-simulation"}
