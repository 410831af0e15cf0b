"""What every request passes before the API sees it (app/security.py, the Host check): huge bodies
refused before parsing, errors that echo no more than a prefix, the security headers, docs from
vendored assets, no server path, jobs that belong to whoever submitted them, keys and hosts."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest
from nlpsf.web.settings import Limits

from ..servers import ROOT

SMALL = {"band": "Y106", "magnitudes": [19.5], "betas": [5e-7], "realizations": 8, "seed": 3}


SETTINGS = {"limits": Limits(max_realizations=500)}


@pytest.fixture(scope="module")
def client_settings():
    return SETTINGS


# --- bodies and echoes -------------------------------------------------------------------------


def test_a_body_over_the_limit_is_413_before_parsing(client):
    # The reproduction: a million keys (12 MB) used to block a worker for 50 s.
    huge = "{" + ",".join(f'"k{i}":1' for i in range(1_000_000)) + "}"
    start = time.perf_counter()
    response = client.post("/api/v1/solve", content=huge.encode(), headers={"Content-Type": "application/json"})
    assert response.status_code == 413
    assert response.headers["content-type"] == "application/problem+json"
    assert response.json()["limit"] == "max_body_bytes" and response.json()["status"] == 413
    assert len(response.content) < 1000
    assert time.perf_counter() - start < 2.0


def test_a_chunked_body_over_the_limit_is_413(client):
    def chunks():
        for _ in range(200):
            yield b" " * 1024

    response = client.post("/api/v1/solve", content=chunks(), headers={"Content-Type": "application/json"})
    assert response.status_code == 413


def test_errors_never_echo_more_than_a_short_prefix(client):
    body = {"band": "H" * 60_000, "magnitude": 18.3, "tolerance": 1e-4}
    response = client.post("/api/v1/solve", json=body)
    assert response.status_code == 422
    assert response.json()["field"] == "band"
    assert len(response.content) < 2_000
    # Many unknown keys under the size limit: a few errors, not one per key.
    keys = {f"k{i}": 1 for i in range(3000)}
    response = client.post("/api/v1/solve", json={"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, **keys})
    assert response.status_code == 422
    assert len(response.content) < 5_000


# --- exposure --------------------------------------------------------------------------------


def test_every_response_carries_the_security_headers(client):
    for path in ["/", "/api/v1/health", "/docs", "/api/v1/tables?sca=0", "/nope"]:
        response = client.get(path)
        headers = response.headers
        assert "frame-ancestors 'none'" in headers["content-security-policy"], path
        assert "script-src 'self'" in headers["content-security-policy"]
        assert headers["x-content-type-options"] == "nosniff"
        assert headers["referrer-policy"] == "no-referrer"
    too_big = client.post("/api/v1/solve", content=b"x" * 100_000)
    assert too_big.status_code == 413 and too_big.headers["x-content-type-options"] == "nosniff"


def test_docs_are_served_from_vendored_assets(client):
    page = client.get("/docs")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert "http" not in page.text, "the docs page must not load anything remote"
    sources = re.findall(r'(?:src|href)="([^"]+)"', page.text)
    assert "/vendor/swagger-ui/swagger-ui-bundle.js" in sources
    for source in sources:
        assert client.get(source).status_code == 200, source
    assert "<script>" not in page.text, "no inline script: the CSP forbids it"


def test_no_server_path_in_any_response(client):
    secrets = {str(ROOT), str(Path.home()), client.app.state.settings.db_path}
    for path in ("/api/v1/meta", "/api/v1/tables", "/api/v1/tables?band=H158", "/api/v1/health", "/api/v1/paper", "/api/v1/fits"):
        text = client.get(path).text
        for secret in secrets:
            assert secret not in text, (path, secret)
    assert client.get("/api/v1/meta").json()["tables"]["source"] == "slopes.npz"  # the file's name alone


# --- jobs belong to whoever submitted them ------------------------------------------------------


def test_a_job_id_is_a_capability_and_listing_hides_others_jobs(make_client):
    keys = ["alice-key-0123456789", "bob-key-0123456789ab"]
    with make_client(**SETTINGS | {"api_keys": ",".join(keys)}) as client:
        alice, bob = ({"Authorization": f"Bearer {k}"} for k in keys)
        assert client.get("/api/v1/health").status_code == 200  # probes need no key
        assert client.post("/api/v1/solve", json={"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}).status_code == 401
        assert client.get("/api/v1/meta", headers={"X-API-Key": "wrong-key-0123456789"}).status_code == 401
        mine = client.post("/api/v1/simulations", json=SMALL, params={"wait": 60}, headers=alice).json()
        theirs = client.post("/api/v1/simulations", json={**SMALL, "seed": 4}, headers={"X-API-Key": keys[1]}).json()
        assert client.get(f"/api/v1/simulations/{mine['id']}", headers=bob).json()["status"] == "done"  # the id is the capability
        listed = client.get("/api/v1/simulations", headers=alice).json()["jobs"]
        assert len(listed) == 1 and listed[0]["request"]["seed"] == 3
        assert all(job["id"] not in (mine["id"], theirs["id"]) for job in listed), "a listing must not hand out capabilities"
        # An id nobody was given is not found, and cannot be cancelled.
        assert client.delete("/api/v1/simulations/" + "ab" * 16, headers=bob).status_code == 404
        client.delete(f"/api/v1/simulations/{theirs['id']}", headers=bob)


def test_listing_every_job_is_an_operator_option(make_client):
    with make_client(**SETTINGS | {"list_all_jobs": True}) as client:
        client.post("/api/v1/simulations", json=SMALL, params={"wait": 60})
        assert len(client.get("/api/v1/simulations").json()["jobs"]) == 1


def test_host_header_check(make_client):
    with make_client(**SETTINGS | {"allowed_hosts": "nlpsf.example.org"}) as client:
        assert client.get("/api/v1/health").status_code == 400  # the TestClient's Host is "testserver"
        assert client.get("/api/v1/health", headers={"Host": "nlpsf.example.org"}).status_code == 200
