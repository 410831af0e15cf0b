"""Serving policy under abuse, in process: complete validation before anything is queued (numbers at
the edges too: subnormals, absurd accuracy targets), fair sharing of the queue, stuck jobs ended,
database damage noticed, HTTP semantics, and the settings and limits the service runs under."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sqlite3
import time

import pytest
from nlpsf.web.settings import Limits, Settings

from nlpsf import defaults
from nlpsf.checks import InputError
from nlpsf.solve import solver

from ..servers import wait_for

SOLVE = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}
#: About a minute of work on one core: always cancelled or ended, never waited for.
LONG = {"band": "H158", "realizations": 3000, "magnitudes": [18.0 + 0.1 * k for k in range(60)], "seed": 11}
KEYS = ["client-a-key-0123456789", "client-b-key-0123456789"]


#: Limits wide enough for LONG: these tests are about policy, not size.
SETTINGS = {"limits": Limits(max_realizations=5000, max_stamp_pixels=10**9, max_work=10**12)}


@pytest.fixture(scope="module")
def client_settings():
    return SETTINGS


# --- 2. nothing accepted that fails later --------------------------------------------------------

REFUSED_AT_ENTRY = [
    ("/api/v1/simulations", {"realizations": 2, "stamp": 32, "scene": {"nl_coefficients": [1, 2]}}, "scene.nl_coefficients"),
    ("/api/v1/simulations", {"realizations": 2, "stamp": 32, "scene": {"bfe": 1e-4}}, "scene.bfe"),
    ("/api/v1/simulations", {"realizations": 2, "stamp": 32, "weight_cut_rho2": 1e308}, "weight_cut_rho2"),
    ("/api/v1/solve", {**SOLVE, "scene": {"nl_coefficients": [1, 2]}}, "scene.nl_coefficients"),
    ("/api/v1/solve", {**SOLVE, "scene": {"bfe": 1e-4, "preset": "paper"}}, "scene.bfe"),  # the default: a ramp refuses BFE
    ("/api/v1/solve", {**SOLVE, "ma_table": "x" * 300}, "ma_table"),
    ("/api/v1/impact", {"beta0": 5e-324, "realizations": 5}, "beta0"),
]


@pytest.mark.parametrize(("path", "body", "field"), REFUSED_AT_ENTRY)
def test_refused_at_the_entry_with_the_field_named_and_nothing_queued(client, path, body, field):
    before = client.app.state.store.counts()
    response = client.post(path, json=body)
    assert response.status_code == 422, response.text[:300]
    assert response.json()["field"] == field
    assert client.app.state.store.counts() == before  # no job was queued


def test_a_range_refusal_is_the_schemas_range(client):
    """The 422 and the published schema come from one bound (the library's)."""
    from nlpsf import defaults

    schema = client.get("/openapi.json").json()["components"]["schemas"]["SimulationRequest"]["properties"]
    assert schema["weight_cut_rho2"]["maximum"] == defaults.WEIGHT_CUT_RHO2_RANGE[1]
    top = defaults.WEIGHT_CUT_RHO2_RANGE[1]
    assert (
        client.post(
            "/api/v1/simulations?wait=0", json={"realizations": 2, "stamp": 32, "weight_cut_rho2": top * 1.01}
        ).status_code
        == 422
    )


# --- 5. fair sharing -----------------------------------------------------------------------------


def test_one_client_cannot_hold_the_queue(make_client):
    with make_client(**SETTINGS | {"api_keys": KEYS, "max_queue": 8, "max_queue_per_client": 2}) as client:
        a, b = ({"X-API-Key": key} for key in KEYS)
        tickets = [client.post("/api/v1/simulations", json=LONG, headers=a).json()["id"]]  # runs
        wait_for(lambda: client.get(f"/api/v1/simulations/{tickets[0]}", headers=a).json()["status"] == "running")
        for seed in (1, 2):
            response = client.post("/api/v1/simulations", json={**LONG, "seed": seed}, headers=a)
            assert response.status_code == 202
            tickets.append(response.json()["id"])
        refused = client.post("/api/v1/simulations", json={**LONG, "seed": 3}, headers=a)
        assert refused.status_code == 429
        assert refused.json()["limit"] == "max_queue_per_client" and int(refused.headers["Retry-After"]) > 0
        # Others still get in while A waits.
        other = client.post("/api/v1/simulations", json={**LONG, "seed": 4}, headers=b)
        assert other.status_code == 202
        # Counts are the caller's own: B sees its one queued job, not A's running one.
        counts = client.get("/api/v1/simulations", headers=b).json()["counts"]
        assert counts == {"queued": 1}
        for ticket, headers in [*((t, a) for t in tickets), (other.json()["id"], b)]:
            client.delete(f"/api/v1/simulations/{ticket}", headers=headers)


# --- 3. a stuck job is ended and its place freed ----------------------------------------------------


def test_a_stopped_job_is_ended_and_the_queue_moves_on(make_client):
    with make_client(**SETTINGS | {"job_stall_s": 2.0}) as client:
        settings = client.app.state.settings
        stuck = client.post("/api/v1/simulations", json=LONG).json()
        pid = wait_for(lambda: client.app.state.store.get(stuck["id"])["pid"])
        wait_for(lambda: client.get(f"/api/v1/simulations/{stuck['id']}").json()["status"] == "running")
        os.kill(pid, signal.SIGSTOP)
        stopped = time.monotonic()
        try:
            small = client.post("/api/v1/simulations", json={"band": "Y106", "realizations": 4, "stamp": 48}).json()
            ended = wait_for(
                lambda: (j := client.get(f"/api/v1/simulations/{stuck['id']}").json())["status"] != "running" and j, 20
            )
            took = time.monotonic() - stopped
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGCONT)
        assert ended["status"] == "failed" and ended["error"]["limit"] == "job_stall_s", ended
        print(f"stopped job ended after {took:.1f} s (job_stall_s {settings.job_stall_s:g})")
        assert took < settings.job_stall_s + 3.0
        done = wait_for(lambda: (j := client.get(f"/api/v1/simulations/{small['id']}").json())["status"] == "done" and j, 120)
        assert done["result"]["results"]


def test_the_wall_time_limit_grows_with_the_job():
    settings = Settings(db_path="/nonexistent/unused.sqlite3", job_stall_s=10.0, job_time_factor=20.0)
    assert settings.job_time_limit_s(None) == 100.0  # solves and impact reports: 10 x job_stall_s
    assert settings.job_time_limit_s(1.0) == 100.0
    assert settings.job_time_limit_s(60.0) == 1200.0


# --- 6. damage to the database shows in /health within a heartbeat or two ---------------------------


def test_a_damaged_table_shows_in_health_within_two_seconds(tmp_path, make_client):
    db = tmp_path / "jobs.sqlite3"
    with make_client(db_path=db, **SETTINGS) as client:
        assert client.get("/api/v1/health").json()["status"] == "ok"
        with contextlib.closing(sqlite3.connect(db)) as handle:
            handle.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            page_size = handle.execute("PRAGMA page_size").fetchone()[0]
            root = handle.execute("SELECT rootpage FROM sqlite_master WHERE name = 'jobs'").fetchone()[0]
        # Overwrite the jobs table's page only: the heartbeat's own table (instances) still writes.
        with open(db, "r+b") as handle:
            handle.seek((root - 1) * page_size)
            handle.write(b"\xa5" * page_size)
        damaged = time.monotonic()
        state = wait_for(lambda: (h := client.get("/api/v1/health").json())["status"] == "degraded" and h, timeout=5)
        assert time.monotonic() - damaged < 2.5
        assert "corrupt" in state["job_store"]["reason"]
        # ...and stays so: the heartbeat's own write still succeeds, but it no longer clears the fault.
        for _ in range(10):
            time.sleep(0.25)
            assert client.get("/api/v1/health").json()["status"] == "degraded"
        assert client.post("/api/v1/simulations", json={"realizations": 2, "stamp": 32}).status_code == 503


# --- 7. HTTP semantics -----------------------------------------------------------------------------


def test_options_and_head_on_api_routes(client):
    options = client.options("/api/v1/solve")
    assert options.status_code == 204 and options.headers["allow"] == "OPTIONS, POST"
    head = client.head("/api/v1/solve")
    assert head.status_code == 405 and "POST" in head.headers["allow"]
    meta = client.head("/api/v1/meta")
    assert meta.status_code == 200 and meta.content == b"" and meta.headers["content-type"].startswith("application/json")
    assert client.get("/api/v1/no-such-thing").status_code == 404


def test_capabilities_are_not_cached_and_tables_are(client):
    job = client.post("/api/v1/simulations", json={"band": "Y106", "realizations": 2, "stamp": 32})
    assert job.headers["cache-control"] == "no-store"
    assert client.get(f"/api/v1/simulations/{job.json()['id']}").headers["cache-control"] == "no-store"
    assert client.post("/api/v1/solve", json=SOLVE).headers["cache-control"] == "no-store"
    for path in ("/api/v1/tables", "/api/v1/tables.ecsv", "/api/v1/tables.csv"):
        first = client.get(path, params={"band": "H158", "sca": 1})
        assert first.headers["etag"] and "max-age" in first.headers["cache-control"]
        again = client.get(path, params={"band": "H158", "sca": 1}, headers={"If-None-Match": first.headers["etag"]})
        assert again.status_code == 304


def test_bodies_on_get_and_duplicate_keys_are_refused(client):
    assert client.request("GET", "/api/v1/meta", content=b"{}" * 1000).status_code == 400
    body = b'{"band": "H158", "band": "J129", "magnitude": 18.3, "tolerance": 1e-4}'
    response = client.post("/api/v1/solve", content=body, headers={"content-type": "application/json"})
    assert response.status_code == 422 and "'band' twice" in response.json()["detail"]


# --- numbers at the edges, and the settings themselves ---------------------------------------------

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


def test_meta_reports_the_service_limits(client):
    limits = client.get("/api/v1/meta").json()["limits"]
    assert limits["max_body_bytes"] == client.app.state.settings.max_body_bytes
    assert json.dumps(limits)
