"""Jobs and results in an embedded SQLite database.

Every web worker process and every simulation process opens its own connection; WAL mode lets
readers (status polls) go on while a worker writes progress. The database is the only shared
state, so any web worker can answer for any job, and what is in it survives a restart:

- ``results``: finished results keyed by the content hash of the request (code and data versions
  included), so a repeated request is answered from here at once;
- ``jobs``: one row per submitted simulation; ``owner`` names the service instance that runs it;
- ``instances``: the live service processes and their heartbeats, so a job whose owner died is
  reported as interrupted rather than left "running" forever.
"""

from __future__ import annotations

import json
import os
import socket
import sqlite3
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

ACTIVE = ("queued", "running")
FINISHED = ("done", "failed", "cancelled", "interrupted")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS results (
    hash TEXT PRIMARY KEY,
    result TEXT NOT NULL,
    created_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    request_hash TEXT NOT NULL,
    request TEXT NOT NULL,
    status TEXT NOT NULL,
    progress REAL NOT NULL DEFAULT 0,
    message TEXT NOT NULL DEFAULT '',
    cached INTEGER NOT NULL DEFAULT 0,
    error TEXT,
    owner TEXT,
    pid INTEGER,
    cancel_requested INTEGER NOT NULL DEFAULT 0,
    created_at REAL NOT NULL,
    started_at REAL,
    finished_at REAL,
    updated_at REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS jobs_by_status ON jobs (status, created_at);
CREATE INDEX IF NOT EXISTS jobs_by_hash ON jobs (request_hash, status);
CREATE TABLE IF NOT EXISTS instances (
    id TEXT PRIMARY KEY,
    hostname TEXT NOT NULL,
    pid INTEGER NOT NULL,
    pid_start TEXT,
    heartbeat REAL NOT NULL,
    started_at REAL NOT NULL
);
"""


class QueueFull(Exception):
    def __init__(self, queued: int, limit: int):
        super().__init__(f"{queued} simulations are already waiting (limit {limit}); try again later")
        self.queued = queued
        self.limit = limit


class NotCancellable(Exception):
    pass


def process_start_time(pid: int) -> str | None:
    """The kernel's start time of ``pid`` (tells a live process from a reused pid); None if gone."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as handle:
            fields = handle.read().rsplit(b")", 1)[1].split()
        return fields[19].decode()
    except (OSError, IndexError):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:
            return "unknown"
        return "unknown"


class Store:
    def __init__(self, path: str | os.PathLike[str]):
        self.path = str(path)
        Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        with self.connect() as db:
            db.execute("PRAGMA journal_mode=WAL")
            db.executescript(_SCHEMA)

    @contextmanager
    def connect(self) -> Iterator[sqlite3.Connection]:
        db = sqlite3.connect(self.path, timeout=15.0, isolation_level=None)
        db.row_factory = sqlite3.Row
        try:
            db.execute("PRAGMA busy_timeout=15000")
            db.execute("PRAGMA synchronous=NORMAL")
            yield db
        finally:
            db.close()

    @contextmanager
    def transaction(self) -> Iterator[sqlite3.Connection]:
        """A write transaction taken at once (BEGIN IMMEDIATE), so check-then-write is atomic."""
        with self.connect() as db:
            db.execute("BEGIN IMMEDIATE")
            try:
                yield db
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")

    # --- submitting and reading ---------------------------------------------------------------

    def submit(self, request: dict[str, Any], request_hash: str, max_queue: int) -> tuple[dict[str, Any], str]:
        """Queue a request, or answer it from the results, or join the same request in flight.

        Returns the job and how it was handled: "cached", "joined" or "queued".
        """
        now = time.time()
        with self.transaction() as db:
            if db.execute("SELECT 1 FROM results WHERE hash = ?", (request_hash,)).fetchone():
                job_id = uuid.uuid4().hex
                db.execute(
                    "INSERT INTO jobs (id, request_hash, request, status, progress, message, cached, created_at, started_at,"
                    " finished_at, updated_at) VALUES (?, ?, ?, 'done', 1, 'answered from stored results', 1, ?, ?, ?, ?)",
                    (job_id, request_hash, json.dumps(request), now, now, now, now),
                )
                how = "cached"
            else:
                row = db.execute(
                    "SELECT id FROM jobs WHERE request_hash = ? AND status IN ('queued', 'running') AND cancel_requested = 0"
                    " ORDER BY created_at LIMIT 1",
                    (request_hash,),
                ).fetchone()
                if row:
                    job_id, how = row["id"], "joined"
                else:
                    queued = db.execute("SELECT COUNT(*) FROM jobs WHERE status = 'queued'").fetchone()[0]
                    if queued >= max_queue:
                        raise QueueFull(queued, max_queue)
                    job_id, how = uuid.uuid4().hex, "queued"
                    db.execute(
                        "INSERT INTO jobs (id, request_hash, request, status, message, created_at, updated_at)"
                        " VALUES (?, ?, ?, 'queued', 'waiting for a worker', ?, ?)",
                        (job_id, request_hash, json.dumps(request), now, now),
                    )
            job = self._read(db, job_id)
        assert job is not None
        return job, how

    def get(self, job_id: str) -> dict[str, Any] | None:
        with self.connect() as db:
            return self._read(db, job_id)

    def list(self, limit: int = 50) -> list[dict[str, Any]]:
        with self.connect() as db:
            rows = db.execute("SELECT id FROM jobs ORDER BY created_at DESC LIMIT ?", (limit,)).fetchall()
            return [job for row in rows if (job := self._read(db, row["id"], with_result=False))]

    def _read(self, db: sqlite3.Connection, job_id: str, with_result: bool = True) -> dict[str, Any] | None:
        row = db.execute("SELECT * FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            return None
        job = dict(row)
        job["request"] = json.loads(job["request"])
        job["error"] = json.loads(job["error"]) if job["error"] else None
        job["cached"] = bool(job["cached"])
        job["cancel_requested"] = bool(job["cancel_requested"])
        job["result"] = None
        if job["status"] == "queued":
            job["queue_position"] = db.execute(
                "SELECT COUNT(*) FROM jobs WHERE status = 'queued' AND created_at <= ?", (job["created_at"],)
            ).fetchone()[0]
        else:
            job["queue_position"] = None
        if with_result and job["status"] == "done":
            result = db.execute("SELECT result FROM results WHERE hash = ?", (job["request_hash"],)).fetchone()
            job["result"] = json.loads(result["result"]) if result else None
        return job

    def cancel(self, job_id: str) -> dict[str, Any] | None:
        """Cancel a queued job at once; ask the owner of a running one to stop it."""
        now = time.time()
        with self.transaction() as db:
            job = self._read(db, job_id, with_result=False)
            if job is None:
                return None
            if job["status"] in FINISHED:
                raise NotCancellable(f"job {job_id} has already finished ({job['status']})")
            if job["status"] == "queued":
                db.execute(
                    "UPDATE jobs SET status = 'cancelled', message = 'cancelled before it started', cancel_requested = 1,"
                    " finished_at = ?, updated_at = ? WHERE id = ?",
                    (now, now, job_id),
                )
            else:
                db.execute("UPDATE jobs SET cancel_requested = 1, updated_at = ? WHERE id = ?", (now, job_id))
            return self._read(db, job_id, with_result=False)

    def counts(self) -> dict[str, int]:
        with self.connect() as db:
            rows = db.execute("SELECT status, COUNT(*) AS n FROM jobs GROUP BY status").fetchall()
        return {row["status"]: row["n"] for row in rows}

    # --- the dispatcher's side ----------------------------------------------------------------

    def claim(self, owner: str, max_running: int) -> dict[str, Any] | None:
        """Take the oldest queued job if fewer than ``max_running`` run anywhere."""
        now = time.time()
        with self.transaction() as db:
            running = db.execute("SELECT COUNT(*) FROM jobs WHERE status = 'running'").fetchone()[0]
            if running >= max_running:
                return None
            row = db.execute("SELECT id FROM jobs WHERE status = 'queued' ORDER BY created_at LIMIT 1").fetchone()
            if row is None:
                return None
            db.execute(
                "UPDATE jobs SET status = 'running', owner = ?, message = 'starting', started_at = ?, updated_at = ?"
                " WHERE id = ?",
                (owner, now, now, row["id"]),
            )
            return self._read(db, row["id"], with_result=False)

    def set_pid(self, job_id: str, pid: int) -> None:
        with self.connect() as db:
            db.execute("UPDATE jobs SET pid = ? WHERE id = ?", (pid, job_id))

    def cancel_requested(self, owner: str) -> list[str]:
        with self.connect() as db:
            rows = db.execute(
                "SELECT id FROM jobs WHERE owner = ? AND status = 'running' AND cancel_requested = 1", (owner,)
            ).fetchall()
        return [row["id"] for row in rows]

    def progress(self, job_id: str, owner: str, fraction: float, message: str) -> bool:
        """Record progress; False when the job should stop (cancelled, or no longer this owner's)."""
        with self.connect() as db:
            changed = db.execute(
                "UPDATE jobs SET progress = ?, message = ?, updated_at = ? WHERE id = ? AND owner = ? AND status = 'running'",
                (fraction, message, time.time(), job_id, owner),
            ).rowcount
            row = db.execute("SELECT cancel_requested FROM jobs WHERE id = ?", (job_id,)).fetchone()
        return bool(changed) and not (row and row["cancel_requested"])

    def finish(self, job_id: str, owner: str, request_hash: str, result: dict[str, Any]) -> bool:
        now = time.time()
        text = json.dumps(result, allow_nan=False)
        with self.transaction() as db:
            db.execute("INSERT OR REPLACE INTO results (hash, result, created_at) VALUES (?, ?, ?)", (request_hash, text, now))
            return bool(
                db.execute(
                    "UPDATE jobs SET status = 'done', progress = 1, message = 'done', finished_at = ?, updated_at = ?"
                    " WHERE id = ? AND owner = ? AND status = 'running'",
                    (now, now, job_id, owner),
                ).rowcount
            )

    def end(self, job_id: str, status: str, message: str, error: dict[str, Any] | None = None, owner: str | None = None) -> bool:
        """Move an active job to a finished state (failed, cancelled, interrupted)."""
        now = time.time()
        sql = (
            "UPDATE jobs SET status = ?, message = ?, error = ?, finished_at = ?, updated_at = ?"
            " WHERE id = ? AND status IN ('queued', 'running')"
        )
        args: list[Any] = [status, message, json.dumps(error) if error else None, now, now, job_id]
        if owner is not None:
            sql += " AND owner = ?"
            args.append(owner)
        with self.connect() as db:
            return bool(db.execute(sql, args).rowcount)

    def interrupt_owned(self, owner: str, message: str) -> int:
        now = time.time()
        with self.connect() as db:
            return db.execute(
                "UPDATE jobs SET status = 'interrupted', message = ?, finished_at = ?, updated_at = ?"
                " WHERE owner = ? AND status = 'running'",
                (message, now, now, owner),
            ).rowcount

    # --- service instances --------------------------------------------------------------------

    def register_instance(self) -> str:
        instance = uuid.uuid4().hex
        now = time.time()
        with self.connect() as db:
            db.execute(
                "INSERT INTO instances (id, hostname, pid, pid_start, heartbeat, started_at) VALUES (?, ?, ?, ?, ?, ?)",
                (instance, socket.gethostname(), os.getpid(), process_start_time(os.getpid()), now, now),
            )
        return instance

    def heartbeat(self, instance: str) -> None:
        with self.connect() as db:
            db.execute("UPDATE instances SET heartbeat = ? WHERE id = ?", (time.time(), instance))

    def unregister_instance(self, instance: str) -> None:
        with self.connect() as db:
            db.execute("DELETE FROM instances WHERE id = ?", (instance,))

    def interrupt_orphans(self, stale_after_s: float) -> list[str]:
        """Jobs running under a service instance that is gone become "interrupted".

        An instance is gone when its heartbeat is older than ``stale_after_s``, or at once when it
        ran on this host and its process no longer exists (a crash or kill -9 followed by a restart).
        """
        now = time.time()
        host = socket.gethostname()
        interrupted = []
        with self.transaction() as db:
            alive = set()
            for row in db.execute("SELECT * FROM instances").fetchall():
                gone = now - row["heartbeat"] > stale_after_s
                if not gone and row["hostname"] == host:
                    started = process_start_time(row["pid"])
                    gone = started is None or (row["pid_start"] not in (None, "unknown") and started != row["pid_start"])
                if gone:
                    db.execute("DELETE FROM instances WHERE id = ?", (row["id"],))
                else:
                    alive.add(row["id"])
            for row in db.execute("SELECT id, owner FROM jobs WHERE status = 'running'").fetchall():
                if row["owner"] not in alive:
                    db.execute(
                        "UPDATE jobs SET status = 'interrupted', message = ?, finished_at = ?, updated_at = ? WHERE id = ?",
                        (
                            "the service stopped while this simulation was running; submit it again to rerun it",
                            now,
                            now,
                            row["id"],
                        ),
                    )
                    interrupted.append(row["id"])
        return interrupted
