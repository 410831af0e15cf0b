"""The job database breaks under a running service (issue 10): deleted, corrupted, read-only, full,
and corrupt at start. In every case the calculator keeps answering, /health says "degraded" with the
reason, /simulations answers 503 with it, the log says it once, and the service recovers without a
restart when the file is back; results stored before the fault are still there after it.

Read-only and full need a file system of their own (a small tmpfs, mounted as root); without root
those two are skipped, and read-only falls back to file permissions where they bind."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import sqlite3
import subprocess
import time
from pathlib import Path

import pytest

from ..servers import wait_for

SMALL = {"band": "Y106", "magnitudes": [19.5], "betas": [5e-7], "realizations": 8, "seed": 3}
# A table solve, answered in the HTTP worker without the job store: the paper's scene (the Roman
# default without a position simulates its SCA range, which is a job and needs the store).
SOLVE = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "scene": "paper"}


@contextlib.contextmanager
def small_filesystem(directory: Path, size: str = "2m"):
    if os.geteuid() != 0:
        pytest.skip("needs root to mount a small tmpfs")
    directory.mkdir(parents=True, exist_ok=True)
    if subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(directory)], capture_output=True).returncode:
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield directory
    finally:
        subprocess.run(["umount", "-l", str(directory)], check=False)


def checkpoint(path: Path) -> None:
    with contextlib.closing(sqlite3.connect(path)) as db:
        db.execute("PRAGMA wal_checkpoint(TRUNCATE)")


def health(client) -> dict:
    response = client.get("/api/v1/health")
    assert response.status_code == 200
    return response.json()


def store_errors(caplog) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.name == "nlpsf.store" and r.levelno >= logging.ERROR]


def exercise_fault(client, caplog, db: Path, inject, restore, reason: str, reads_work: bool = False) -> None:
    """Before: a finished job. During: degraded, 503, calculator fine, one log line. After: recovered."""
    done = client.post("/api/v1/simulations", json=SMALL, params={"wait": 60}).json()
    assert done["status"] == "done"
    checkpoint(db)
    caplog.clear()
    inject()
    degraded = wait_for(lambda: (h := health(client))["status"] == "degraded" and h, timeout=15)
    assert reason in degraded["job_store"]["reason"]
    assert str(db) not in str(degraded)
    for _ in range(3):
        assert client.post("/api/v1/solve", json=SOLVE).status_code == 200
        refused = client.post("/api/v1/simulations", json={**SMALL, "seed": 77})
        assert refused.status_code == 503, refused.text
        assert reason in refused.json()["message"] and str(db) not in refused.text
        looked = client.get(f"/api/v1/simulations/{done['id']}")
        assert looked.status_code == (200 if reads_work else 503)
    time.sleep(3)  # several heartbeats and dispatcher rounds in the fault
    assert len(store_errors(caplog)) == 1, [r.getMessage() for r in store_errors(caplog)]
    restore()
    wait_for(lambda: health(client)["status"] == "ok", timeout=15)
    kept = client.get(f"/api/v1/simulations/{done['id']}").json()
    assert kept["status"] == "done" and kept["result"] == done["result"], "a stored result was lost"
    fresh = client.post("/api/v1/simulations", json={**SMALL, "seed": 78}, params={"wait": 60})
    assert fresh.status_code == 200 and fresh.json()["status"] == "done"
    assert any("usable again" in r.getMessage() for r in caplog.records if r.name == "nlpsf.store")


@pytest.mark.slow
def test_deleted_database(tmp_path, caplog, make_client):
    db = tmp_path / "jobs.sqlite3"
    aside = tmp_path / "aside"
    aside.mkdir()

    def files():
        return [p for p in tmp_path.iterdir() if p.name.startswith("jobs.sqlite3")]

    with make_client(db_path=db) as client:
        exercise_fault(
            client,
            caplog,
            db,
            inject=lambda: [shutil.move(p, aside / p.name) for p in files()],
            restore=lambda: [shutil.move(p, tmp_path / p.name) for p in aside.iterdir()],
            reason="missing",
        )


@pytest.mark.slow
def test_corrupted_database(tmp_path, caplog, make_client):
    db = tmp_path / "jobs.sqlite3"
    backup = tmp_path / "backup.sqlite3"

    def corrupt():
        shutil.copy(db, backup)
        with open(db, "r+b") as handle:
            handle.write(b"this is not a database at all" * 200)

    with make_client(db_path=db) as client:
        exercise_fault(client, caplog, db, inject=corrupt, restore=lambda: shutil.copy(backup, db), reason="corrupt")


@pytest.mark.slow
def test_read_only_database(tmp_path, caplog, make_client):
    with small_filesystem(tmp_path / "fs") as directory:
        db = directory / "jobs.sqlite3"

        def remount(mode: str):
            # A remount to read-only fails (busy) while a write is open: the service writes every
            # few seconds, so try again until it falls between two writes.
            def done() -> bool:
                return subprocess.run(["mount", "-o", f"remount,{mode}", str(directory)], capture_output=True).returncode == 0

            wait_for(done, timeout=20, interval=0.05)

        with make_client(db_path=db) as client:
            exercise_fault(client, caplog, db, inject=lambda: remount("ro"), restore=lambda: remount("rw"), reason="read-only")


@pytest.mark.slow
def test_full_disk(tmp_path, caplog, make_client):
    with small_filesystem(tmp_path / "fs", size="1m") as directory:
        db = directory / "jobs.sqlite3"
        filler = directory / "filler"

        def fill():
            # Every free block taken, then new rows are what cannot be written.
            with contextlib.suppress(OSError), open(filler, "wb") as handle:
                while True:
                    handle.write(b"\0" * 4096)
                    handle.flush()

        with make_client(db_path=db) as client:
            # A burst of submissions grows the database until the disk is full.
            def inject():
                fill()
                for seed in range(100, 140):
                    client.post("/api/v1/simulations", json={**SMALL, "seed": seed, "realizations": 1})

            exercise_fault(client, caplog, db, inject=inject, restore=lambda: filler.unlink(), reason="full")


def test_corrupt_database_at_start_leaves_the_calculator_running(tmp_path, caplog, make_client):
    db = tmp_path / "jobs.sqlite3"
    db.write_bytes(b"garbage, not SQLite" * 100)
    with make_client(db_path=db) as client:
        state = health(client)
        assert state["status"] == "degraded" and "corrupt" in state["job_store"]["reason"]
        assert client.post("/api/v1/solve", json=SOLVE).status_code == 200
        assert client.get("/api/v1/curves/slope").status_code == 200
        assert client.post("/api/v1/simulations", json=SMALL).status_code == 503
        # The operator moves the bad file away: a fresh database is made at the next start only,
        # so here a good file is put back, and the running service takes it up.
        db.unlink()
        sqlite3.connect(db).close()
        wait_for(lambda: health(client)["status"] == "ok", timeout=15)
        assert client.post("/api/v1/simulations", json=SMALL, params={"wait": 60}).json()["status"] == "done"
