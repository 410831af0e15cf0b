"""The service against a hostile client (issue 10): huge bodies, echoing errors, subnormal numbers,
absurd accuracy targets, other clients' jobs, missing security headers, CDN docs, server paths,
keys and hosts; and the retention rule that keeps the job database bounded."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from nlpsf.web.main import create_app
from nlpsf.web.settings import Limits, Settings
from nlpsf.web.store import Store

from nlpsf import defaults, solver
from nlpsf.checks import InputError

from .servers import ROOT, finished_job

SMALL = {"band": "Y106", "magnitudes": [19.5], "betas": [5e-7], "realizations": 8, "seed": 3}


def settings_for(tmp_path: Path, **overrides) -> Settings:
    values = {"db_path": str(tmp_path / "jobs.sqlite3"), "job_workers": 1, "max_queue": 8, "limits": Limits(max_realizations=500)}
    values.update(overrides)
    return Settings(**values)


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    with TestClient(create_app(settings_for(tmp_path_factory.mktemp("db")))) as test_client:
        yield test_client


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


# --- numbers at the edges ----------------------------------------------------------------------

SUBNORMALS = [5e-324, 1e-320, 2.2e-308]


@pytest.mark.parametrize("value", SUBNORMALS)
@pytest.mark.parametrize("field", ["exptime", "full_well"])
def test_subnormal_exposure_or_full_well_is_a_422_naming_it(client, field, value):
    response = client.post("/api/v1/solve", json={"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, field: value})
    assert response.status_code == 422, response.text
    assert response.json()["field"] == field
    for path in ("slope", "beta", "sigma_beta"):
        response = client.get(f"/api/v1/curves/{path}", params={field: value})
        assert response.status_code == 422, (path, response.text)
        assert response.json()["field"] == field


@pytest.mark.parametrize("field", ["exptime", "full_well"])
def test_the_library_refuses_subnormals_itself(field):
    # Validated at the library's entry point, so the CLI and Python callers are covered too.
    with pytest.raises(InputError, match=field):
        solver.solve("H158", magnitude=18.3, tolerance=1e-4, **{field: 5e-324})


@pytest.mark.parametrize("accuracy", [1e-320, 5e-324, 1e-9])
def test_an_absurd_accuracy_is_refused_clearly(client, accuracy):
    response = client.post("/api/v1/solve", json={"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "accuracy": accuracy})
    assert response.status_code == 422
    assert response.json()["field"] == "accuracy"
    assert f"{defaults.ACCURACY_RANGE[0]:g}" in response.json()["message"]


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
    assert client.get("/api/v1/meta").json()["tables"]["source"].endswith(".ecsv")


# --- jobs belong to whoever submitted them ------------------------------------------------------


def test_a_job_id_is_a_capability_and_listing_hides_others_jobs(tmp_path):
    keys = ["alice-key-0123456789", "bob-key-0123456789ab"]
    with TestClient(create_app(settings_for(tmp_path, api_keys=",".join(keys)))) as client:
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


def test_listing_every_job_is_an_operator_option(tmp_path):
    with TestClient(create_app(settings_for(tmp_path, list_all_jobs=True))) as client:
        client.post("/api/v1/simulations", json=SMALL, params={"wait": 60})
        assert len(client.get("/api/v1/simulations").json()["jobs"]) == 1


def test_host_header_check(tmp_path):
    with TestClient(create_app(settings_for(tmp_path, allowed_hosts="nlpsf.example.org"))) as client:
        assert client.get("/api/v1/health").status_code == 400  # the TestClient's Host is "testserver"
        assert client.get("/api/v1/health", headers={"Host": "nlpsf.example.org"}).status_code == 200


def test_settings_come_from_the_environment(monkeypatch):
    monkeypatch.setenv("NLPSF_MAX_GRID", "7")
    monkeypatch.setenv("NLPSF_ALLOWED_HOSTS", "a.example, b.example")
    monkeypatch.setenv("NLPSF_MAX_WAIT", "5")
    settings = Settings()
    assert settings.limits.max_grid == 7
    assert settings.allowed_hosts == ["a.example", "b.example"]
    assert settings.max_wait_s == 5.0
    monkeypatch.setenv("NLPSF_MAX_GRID", "0")
    with pytest.raises(ValueError, match="max_grid"):
        Settings()


# --- simulating solves are jobs -----------------------------------------------------------------


def test_a_simulating_solve_is_a_job_not_work_in_the_http_worker(tmp_path):
    body = {"band": "H158", "magnitude": 20.0, "precision": 0.01, "fidelity": "linear"}
    with TestClient(create_app(settings_for(tmp_path, solve_wait_s=0.0))) as client:
        queued = client.post("/api/v1/solve", json=body)
        assert queued.status_code == 202, queued.text
        job = queued.json()
        assert job["request"]["kind"] == "solve" and queued.headers["location"].endswith(job["id"])
        done = finished_job(client, job["id"])
        result = done.json()["result"]
        assert result["fidelity"] == "linear" and result["solved_for"] == "tolerance"
        # The same solve, waited for, is the same answer (from stored results).
        again = client.post("/api/v1/solve", json=body)
        assert again.status_code == 200 and again.json()["tolerance"] == result["tolerance"]


# --- memory ------------------------------------------------------------------------------------


def test_a_request_over_the_memory_budget_is_refused_naming_it(tmp_path):
    with TestClient(create_app(settings_for(tmp_path, job_memory_mb=64))) as client:
        response = client.post("/api/v1/simulations", json={**SMALL, "realizations": 400})
        assert response.status_code == 422
        assert response.json()["limit"] == "job_memory_mb"


def test_a_job_over_its_memory_budget_fails_cleanly(tmp_path):
    # The budget is checked on the request (above); a job that still outgrows it meets RLIMIT_AS.
    import multiprocessing

    from nlpsf.web import worker

    def child():
        worker.limit_memory(64)
        try:
            bytearray(512 * 1024**2)
        except MemoryError:
            raise SystemExit(7) from None

    process = multiprocessing.get_context("fork").Process(target=child)
    process.start()
    process.join(30)
    assert process.exitcode == 7


# --- retention --------------------------------------------------------------------------------


def test_retention_bounds_the_database_by_age_and_count(tmp_path):
    store = Store(tmp_path / "jobs.sqlite3")
    tickets = []
    for k in range(12):
        job, _ = store.submit({"k": k}, f"hash{k}", max_queue=100)
        internal = store.job_of(job["id"])
        store.claim("me", 100)
        store.finish(internal, "me", f"hash{k}", {"value": k})
        tickets.append(job["id"])
    # Age: make the first four old.
    with store.connect() as db:
        old = time.time() - 10 * 86_400
        for k in range(4):
            db.execute("UPDATE results SET created_at = ? WHERE hash = ?", (old, f"hash{k}"))
            db.execute("UPDATE jobs SET finished_at = ? WHERE request_hash = ?", (old, f"hash{k}"))
    removed = store.prune(max_age_s=5 * 86_400, max_results=5)
    assert removed["results"] == 4 + 3  # four too old, then three beyond the newest five
    assert [store.get(t) is not None for t in tickets] == [False] * 7 + [True] * 5
    for ticket in tickets[7:]:
        assert store.get(ticket)["result"] is not None, "a kept job never points at a deleted result"
    with store.connect() as db:
        assert db.execute("SELECT COUNT(*) FROM tickets").fetchone()[0] == 5
    # A cached answer renews its result: the oldest-but-used survives the next count cut.
    store.submit({"k": 7}, "hash7", max_queue=100)
    store.prune(max_age_s=5 * 86_400, max_results=1)
    with store.connect() as db:
        assert [r[0] for r in db.execute("SELECT hash FROM results")] == ["hash7"]


def test_meta_reports_the_service_limits(client):
    limits = client.get("/api/v1/meta").json()["limits"]
    assert limits["max_body_bytes"] == client.app.state.settings.max_body_bytes
    assert json.dumps(limits)


def test_waiters_share_one_poll(tmp_path):
    """?wait= costs one query per poll interval however many clients wait (it was a connection per
    waiter every 50 ms: 200 waiters cut the calculator's throughput by 85 %)."""
    from concurrent.futures import ThreadPoolExecutor

    # 200 cells (the grid limit) of 500 realizations: the job outlasts the 2 s wait several times over.
    betas = [4e-7 + 2e-8 * k for k in range(10)]
    long = {"band": "H158", "realizations": 500, "magnitudes": [18.0 + 0.1 * k for k in range(20)], "betas": betas, "seed": 5}
    with TestClient(create_app(settings_for(tmp_path, max_queue=64))) as client:
        store = client.app.state.store
        calls = []
        original = store.statuses

        def counted(tickets):
            calls.append(len(tickets))
            return original(tickets)

        store.statuses = counted
        first = client.post("/api/v1/simulations", json=long).json()
        waiters = 40
        with ThreadPoolExecutor(waiters) as pool:
            start = time.perf_counter()
            answers = list(pool.map(lambda _: client.post("/api/v1/simulations", json=long, params={"wait": 2}), range(waiters)))
            elapsed = time.perf_counter() - start
        assert all(a.status_code == 202 for a in answers), [(a.status_code, a.text[:300]) for a in answers[:2]]
        # One query per 0.1 s for all of them (not one per waiter per poll).
        assert len(calls) <= elapsed / 0.1 + 5, (len(calls), elapsed)
        assert max(calls) > 1, "the waiters should have been polled together"
        for answer in [first, *(a.json() for a in answers)]:
            client.delete(f"/api/v1/simulations/{answer['id']}")


def test_a_solve_with_an_accuracy_is_a_job_even_when_the_tables_meet_it(tmp_path):
    # The accuracy's effects are measured by simulation (nlpsf.impact), never inside the HTTP worker.
    body = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "accuracy": 0.5, "scene": "paper"}
    with TestClient(create_app(settings_for(tmp_path, solve_wait_s=0.0))) as client:
        queued = client.post("/api/v1/solve", json=body)
        assert queued.status_code == 202, queued.text
        result = finished_job(client, queued.json()["id"]).json()["result"]
        assert result["fidelity"] == "table" and result["model"]["accuracy"] == 0.5
