"""The impact endpoint takes the pupil-mask scale rule, as the CLI's ``nlpsf impact --pupil-scale``."""

import pytest

from nlpsf.solve import impact

from ..servers import finished_job


def test_api_impact_runs_with_the_pupil_rule_asked_for(make_client):
    body = {"band": "H158", "magnitude": 19.0, "realizations": 4, "pupil_scale": "official"}
    with make_client(solve_wait_s=0.0) as client:
        answer = client.post("/api/v1/impact", json=body)
        if answer.status_code == 202:
            answer = finished_job(client, answer.json()["id"])
            report = answer.json()["result"]
        else:
            assert answer.status_code == 200, answer.text
            report = answer.json()
        direct = impact.impact("H158", 18, 19.0, realizations=4, pupil_scale="official")
        assert report["conditions"]["pupil_scale"] == "official"
        expected = direct["conditions"]["plain_slope"]["size"]
        assert report["conditions"]["plain_slope"]["size"] == pytest.approx(expected, rel=1e-12)
        refused = client.post("/api/v1/impact", json={**body, "pupil_scale": "wide"})
        assert refused.status_code == 422 and refused.json()["field"].startswith("pupil_scale")
