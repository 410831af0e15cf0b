"""Jobs and results in an embedded SQLite database (``database``: the file, its connections and faults).

The database is the only shared state, so any web worker can answer for any job, and what is in it
survives a restart:

- ``results``: finished results keyed by the content hash of the request (code and data versions
  included), so a repeated request is answered from here at once;
- ``jobs``: one row per run of a request; ``owner`` names the service instance that runs it;
- ``tickets``: one per submission, the capability a client holds: reading or cancelling a job
  needs its ticket (an unguessable 128-bit token, stored only as its SHA-256). Identical requests
  in flight share one run but not a ticket, and a run is cancelled only when every ticket on it is;
- ``instances``: the live service processes and their heartbeats, so a job whose owner died is
  queued again (or, after ``MAX_ATTEMPTS`` starts, reported interrupted) rather than left "running".

A storage fault raises :class:`StoreUnavailable` (``database``), and :attr:`Store.state` follows it.
"""

from __future__ import annotations

import hashlib
import json
import os
import secrets
import socket
import sqlite3
import time
import uuid
from typing import Any

from .database import Database, StoreUnavailable

__all__ = ["ACTIVE", "FINISHED", "MAX_ATTEMPTS", "NotCancellable", "QueueFull", "Store", "StoreUnavailable"]

ACTIVE = ("queued", "running")
FINISHED = ("done", "failed", "cancelled", "interrupted")


class QueueFull(Exception):
    """The queue, or this client's share of it, is full; ``setting`` names the limit that was hit."""

    def __init__(self, queued: int, limit: int, setting: str = "max_queue"):
        whose = "of yours are" if setting == "max_queue_per_client" else "are already"
        super().__init__(f"{queued} simulations {whose} waiting (limit {limit}, the setting {setting}); try again later")
        self.queued = queued
        self.limit = limit
        self.setting = setting


class NotCancellable(Exception):
    pass


def new_ticket() -> str:
    return secrets.token_hex(16)


def ticket_hash(ticket: str) -> str:
    return hashlib.sha256(ticket.encode()).hexdigest()


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


#: Runs of one job: a job whose service process died is queued again until it has started this often.
MAX_ATTEMPTS = 3


class Store(Database):
    """The job store: submissions and their tickets, results, the dispatcher's side, and the live
    service instances (the file, its connections and faults: :class:`Database`)."""

    # --- submitting and reading ---------------------------------------------------------------

    def submit(
        self,
        request: dict[str, Any],
        request_hash: str,
        max_queue: int,
        client: str | None = None,
        max_per_client: int | None = None,
    ) -> tuple[dict[str, Any], str]:
        """Queue a request, or answer it from the results, or join the same request in flight.

        A new run is queued only while fewer than ``max_queue`` wait, and fewer than
        ``max_per_client`` of them are ``client``'s (its API key, else its address): one client
        cannot hold the whole queue while others wait.

        Returns the job as the submitter sees it (``id`` is their ticket) and how it was handled:
        "cached", "joined" or "queued".
        """
        now = time.time()
        ticket = new_ticket()

        def run(db: sqlite3.Connection) -> tuple[str, str]:
            if db.execute("SELECT 1 FROM results WHERE hash = ?", (request_hash,)).fetchone():
                job_id = uuid.uuid4().hex
                db.execute(
                    "INSERT INTO jobs (id, request_hash, request, status, progress, message, cached, created_at, started_at,"
                    " finished_at, updated_at) VALUES (?, ?, ?, 'done', 1, 'answered from stored results', 1, ?, ?, ?, ?)",
                    (job_id, request_hash, json.dumps(request), now, now, now, now),
                )
                # A result in use is a fresh result for retention.
                db.execute("UPDATE results SET created_at = ? WHERE hash = ?", (now, request_hash))
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
                    if client is not None and max_per_client is not None:
                        mine = db.execute(
                            "SELECT COUNT(DISTINCT j.id) FROM tickets t JOIN jobs j ON j.id = t.job_id"
                            " WHERE t.client = ? AND t.cancelled = 0 AND j.status = 'queued'",
                            (client,),
                        ).fetchone()[0]
                        if mine >= max_per_client:
                            raise QueueFull(mine, max_per_client, "max_queue_per_client")
                    job_id, how = uuid.uuid4().hex, "queued"
                    db.execute(
                        "INSERT INTO jobs (id, request_hash, request, status, message, created_at, updated_at)"
                        " VALUES (?, ?, ?, 'queued', 'waiting for a worker', ?, ?)",
                        (job_id, request_hash, json.dumps(request), now, now),
                    )
            db.execute(
                "INSERT INTO tickets (hash, job_id, client, created_at) VALUES (?, ?, ?, ?)",
                (ticket_hash(ticket), job_id, client, now),
            )
            return job_id, how

        _, how = self._write_op(run)
        job = self.get(ticket)
        assert job is not None
        return job, how

    def get(self, ticket: str) -> dict[str, Any] | None:
        """The job a ticket holds, as its holder sees it; None for an unknown ticket."""
        return self._read_op(lambda db: self._read_ticket(db, ticket_hash(ticket), ticket))

    def job_of(self, ticket: str) -> str | None:
        row = self._read_op(lambda db: db.execute("SELECT job_id FROM tickets WHERE hash = ?", (ticket_hash(ticket),)).fetchone())
        return row["job_id"] if row else None

    def list(self, client: str | None, everyone: bool = False, limit: int = 50) -> list[dict[str, Any]]:
        """Recent jobs of ``client`` (every job if ``everyone``), without results or tickets."""

        def run(db: sqlite3.Connection) -> list[dict[str, Any]]:
            if everyone:
                rows = db.execute("SELECT hash, job_id FROM tickets ORDER BY created_at DESC LIMIT ?", (limit,)).fetchall()
            elif client is not None:
                rows = db.execute(
                    "SELECT hash, job_id FROM tickets WHERE client = ? ORDER BY created_at DESC LIMIT ?", (client, limit)
                ).fetchall()
            else:
                return []
            # The ticket itself is not shown: a listing must not hand out capabilities. Its hash
            # prefix identifies the entry.
            shown = [(row["hash"], "h-" + row["hash"][:30]) for row in rows]
            return [job for hashed, name in shown if (job := self._read_ticket(db, hashed, name, with_result=False))]

        return self._read_op(run)

    def _read_ticket(self, db: sqlite3.Connection, hashed: str, shown_id: str, with_result: bool = True) -> dict[str, Any] | None:
        row = db.execute("SELECT job_id, cancelled FROM tickets WHERE hash = ?", (hashed,)).fetchone()
        if row is None:
            return None
        job = self._read(db, row["job_id"], with_result=with_result)
        if job is None:
            return None
        job["id"] = shown_id
        if row["cancelled"] and job["status"] in ACTIVE:
            job.update(status="cancelled", message="cancelled; the same request may still run for another client", result=None)
            job["queue_position"] = None
        if row["cancelled"]:
            job["cancel_requested"] = True
        return job

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

    def statuses(self, tickets: list[str]) -> dict[str, str]:
        """Status of each ticket's job, in one query (the shared notifier of ``?wait=``)."""
        if not tickets:
            return {}
        hashes = {ticket_hash(t): t for t in tickets}

        def run(db: sqlite3.Connection) -> dict[str, str]:
            marks = ",".join("?" * len(hashes))
            rows = db.execute(
                f"SELECT t.hash, t.cancelled, j.status FROM tickets t JOIN jobs j ON j.id = t.job_id WHERE t.hash IN ({marks})",
                list(hashes),
            ).fetchall()
            return {hashes[r["hash"]]: ("cancelled" if r["cancelled"] and r["status"] in ACTIVE else r["status"]) for r in rows}

        return self._read_op(run)

    def cancel(self, ticket: str) -> dict[str, Any] | None:
        """Withdraw a ticket; the run stops (at once if queued, by its owner if running) when no
        other ticket holder still wants it."""
        now = time.time()
        hashed = ticket_hash(ticket)

        def run(db: sqlite3.Connection) -> dict[str, Any] | None:
            job = self._read_ticket(db, hashed, ticket, with_result=False)
            if job is None:
                return None
            if job["status"] in FINISHED:
                raise NotCancellable(f"job {ticket} has already finished ({job['status']})")
            job_id = db.execute("SELECT job_id FROM tickets WHERE hash = ?", (hashed,)).fetchone()["job_id"]
            db.execute("UPDATE tickets SET cancelled = 1 WHERE hash = ?", (hashed,))
            wanted = db.execute("SELECT COUNT(*) FROM tickets WHERE job_id = ? AND cancelled = 0", (job_id,)).fetchone()[0]
            if not wanted:
                if job["status"] == "queued":
                    db.execute(
                        "UPDATE jobs SET status = 'cancelled', message = 'cancelled before it started', cancel_requested = 1,"
                        " finished_at = ?, updated_at = ? WHERE id = ?",
                        (now, now, job_id),
                    )
                else:
                    db.execute("UPDATE jobs SET cancel_requested = 1, updated_at = ? WHERE id = ?", (now, job_id))
            return self._read_ticket(db, hashed, ticket, with_result=False)

        return self._write_op(run)

    def counts(self, client: str | None = None, everyone: bool = True) -> dict[str, int]:
        """Jobs per status: every job (``everyone``), or those ``client`` holds a ticket to, as it sees them."""
        if everyone:
            rows = self._read_op(lambda db: db.execute("SELECT status, COUNT(*) AS n FROM jobs GROUP BY status").fetchall())
            return {row["status"]: row["n"] for row in rows}
        if client is None:
            return {}
        rows = self._read_op(
            lambda db: db.execute(
                "SELECT CASE WHEN t.cancelled = 1 AND j.status IN ('queued', 'running') THEN 'cancelled' ELSE j.status END"
                " AS status, COUNT(*) AS n FROM tickets t JOIN jobs j ON j.id = t.job_id WHERE t.client = ? GROUP BY 1",
                (client,),
            ).fetchall()
        )
        return {row["status"]: row["n"] for row in rows}

    # --- the dispatcher's side ----------------------------------------------------------------

    def claim(self, owner: str, max_running: int) -> dict[str, Any] | None:
        """Take the oldest queued job if fewer than ``max_running`` run anywhere."""
        now = time.time()

        def run(db: sqlite3.Connection) -> dict[str, Any] | None:
            running = db.execute("SELECT COUNT(*) FROM jobs WHERE status = 'running'").fetchone()[0]
            if running >= max_running:
                return None
            row = db.execute("SELECT id FROM jobs WHERE status = 'queued' ORDER BY created_at LIMIT 1").fetchone()
            if row is None:
                return None
            db.execute(
                "UPDATE jobs SET status = 'running', owner = ?, message = 'starting', started_at = ?, updated_at = ?,"
                " attempts = attempts + 1 WHERE id = ?",
                (owner, now, now, row["id"]),
            )
            return self._read(db, row["id"], with_result=False)

        return self._write_op(run)

    def set_pid(self, job_id: str, pid: int) -> None:
        self._read_op(lambda db: db.execute("UPDATE jobs SET pid = ? WHERE id = ?", (pid, job_id)))

    def cancel_requested(self, owner: str) -> list[str]:
        rows = self._read_op(
            lambda db: db.execute(
                "SELECT id FROM jobs WHERE owner = ? AND status = 'running' AND cancel_requested = 1", (owner,)
            ).fetchall()
        )
        return [row["id"] for row in rows]

    def running_updates(self, owner: str) -> dict[str, float]:
        """When each of ``owner``'s running jobs last wrote progress (Unix time, s)."""
        rows = self._read_op(
            lambda db: db.execute("SELECT id, updated_at FROM jobs WHERE owner = ? AND status = 'running'", (owner,)).fetchall()
        )
        return {row["id"]: row["updated_at"] for row in rows}

    def progress(self, job_id: str, owner: str, fraction: float, message: str) -> bool:
        """Record progress; False when the job should stop (cancelled, or no longer this owner's)."""

        def run(db: sqlite3.Connection) -> bool:
            changed = db.execute(
                "UPDATE jobs SET progress = ?, message = ?, updated_at = ? WHERE id = ? AND owner = ? AND status = 'running'",
                (fraction, message, time.time(), job_id, owner),
            ).rowcount
            row = db.execute("SELECT cancel_requested FROM jobs WHERE id = ?", (job_id,)).fetchone()
            return bool(changed) and not (row and row["cancel_requested"])

        return self._read_op(run)

    def finish(self, job_id: str, owner: str, request_hash: str, result: dict[str, Any]) -> bool:
        now = time.time()
        text = json.dumps(result, allow_nan=False)

        def run(db: sqlite3.Connection) -> bool:
            db.execute("INSERT OR REPLACE INTO results (hash, result, created_at) VALUES (?, ?, ?)", (request_hash, text, now))
            return bool(
                db.execute(
                    "UPDATE jobs SET status = 'done', progress = 1, message = 'done', finished_at = ?, updated_at = ?"
                    " WHERE id = ? AND owner = ? AND status = 'running'",
                    (now, now, job_id, owner),
                ).rowcount
            )

        return self._write_op(run)

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
        return self._read_op(lambda db: bool(db.execute(sql, args).rowcount))

    def release_owned(self, owner: str) -> int:
        """A stopping service instance hands its running jobs back to the queue (another instance,
        or this service after a restart, runs them again from the start)."""
        return self._write_op(lambda db: _requeue(db, "owner = ?", (owner,), "its service process stopped"))

    # --- retention ----------------------------------------------------------------------------

    def prune(self, max_age_s: float, max_results: int, max_jobs: int | None = None) -> dict[str, int]:
        """Delete finished jobs and stored results older than ``max_age_s`` and beyond the newest
        ``max_results`` results (``max_jobs``, default 4x that, finished jobs); tickets go with their job.

        A result's age is counted from its last use (a cached answer renews it), so a kept job never
        points to a deleted result: a done job whose result is gone is deleted with it.
        """
        max_jobs = 4 * max_results if max_jobs is None else max_jobs
        cutoff = time.time() - max_age_s
        finished = "('done', 'failed', 'cancelled', 'interrupted')"

        def run(db: sqlite3.Connection) -> dict[str, int]:
            results = db.execute("DELETE FROM results WHERE created_at < ?", (cutoff,)).rowcount
            newest = "SELECT hash FROM results ORDER BY created_at DESC LIMIT ?"
            results += db.execute(f"DELETE FROM results WHERE hash NOT IN ({newest})", (max_results,)).rowcount
            jobs = db.execute(f"DELETE FROM jobs WHERE status IN {finished} AND finished_at < ?", (cutoff,)).rowcount
            jobs += db.execute(
                "DELETE FROM jobs WHERE status = 'done' AND request_hash NOT IN (SELECT hash FROM results)"
            ).rowcount
            jobs += db.execute(
                f"DELETE FROM jobs WHERE status IN {finished} AND id NOT IN"
                f" (SELECT id FROM jobs WHERE status IN {finished} ORDER BY finished_at DESC LIMIT ?)",
                (max_jobs,),
            ).rowcount
            tickets = db.execute("DELETE FROM tickets WHERE job_id NOT IN (SELECT id FROM jobs)").rowcount
            return {"results": results, "jobs": jobs, "tickets": tickets}

        return self._write_op(run)

    # --- service instances --------------------------------------------------------------------

    def register_instance(self) -> str:
        instance = uuid.uuid4().hex
        self.heartbeat(instance)
        return instance

    def heartbeat(self, instance: str) -> None:
        """Record that ``instance`` is alive, re-registering it if a peer has removed it meanwhile
        (a worker stalled past the stale window comes back as itself, with its jobs)."""
        now = time.time()

        def run(db: sqlite3.Connection) -> None:
            db.execute(
                "INSERT INTO instances (id, hostname, pid, pid_start, heartbeat, started_at) VALUES (?, ?, ?, ?, ?, ?)"
                " ON CONFLICT(id) DO UPDATE SET heartbeat = excluded.heartbeat",
                (instance, socket.gethostname(), os.getpid(), process_start_time(os.getpid()), now, now),
            )
            # A write that succeeds proves one page; the whole file's structure is checked too, so a
            # damaged table elsewhere is reported (and not cleared by this write) within a heartbeat.
            verdict = db.execute("PRAGMA quick_check(1)").fetchone()[0]
            if verdict != "ok":
                raise sqlite3.DatabaseError(f"database disk image is malformed (quick_check: {str(verdict)[:80]})")

        self._write_op(run)
        self._set_state("ok", None)

    def unregister_instance(self, instance: str) -> None:
        self._read_op(lambda db: db.execute("DELETE FROM instances WHERE id = ?", (instance,)))

    def interrupt_orphans(self, stale_after_s: float) -> list[str]:
        """Jobs running under a service instance that is gone are queued again (or, after
        ``MAX_ATTEMPTS`` starts, reported "interrupted"); returns their ids.

        On this host an instance is gone exactly when its process is (the pid and its kernel start
        time): a stalled process is alive, however late its heartbeat, so a peer never takes its
        jobs from it. An instance on another host sharing the file is gone when its heartbeat is
        older than ``stale_after_s``.
        """
        now = time.time()
        host = socket.gethostname()

        def run(db: sqlite3.Connection) -> list[str]:
            interrupted = []
            alive = set()
            for row in db.execute("SELECT * FROM instances").fetchall():
                if row["hostname"] == host:
                    started = process_start_time(row["pid"])
                    gone = started is None or (row["pid_start"] not in (None, "unknown") and started != row["pid_start"])
                else:
                    gone = now - row["heartbeat"] > stale_after_s
                if gone:
                    db.execute("DELETE FROM instances WHERE id = ?", (row["id"],))
                else:
                    alive.add(row["id"])
            for row in db.execute("SELECT id, owner FROM jobs WHERE status = 'running'").fetchall():
                if row["owner"] not in alive:
                    _requeue(db, "id = ?", (row["id"],), "its service process ended")
                    interrupted.append(row["id"])
            return interrupted

        return self._write_op(run)


def _requeue(db: sqlite3.Connection, where: str, args: tuple, why: str) -> int:
    """Running jobs matching ``where`` go back to the queue, keeping their place (created_at); one
    that has already started ``MAX_ATTEMPTS`` times is reported interrupted instead."""
    now = time.time()
    queued = db.execute(
        "UPDATE jobs SET status = 'queued', owner = NULL, pid = NULL, progress = 0, started_at = NULL, updated_at = ?,"
        f" message = 'queued again: {why} while it ran' WHERE {where} AND status = 'running' AND attempts < ?",
        (now, *args, MAX_ATTEMPTS),
    ).rowcount
    interrupted = db.execute(
        "UPDATE jobs SET status = 'interrupted', finished_at = ?, updated_at = ?,"
        f" message = 'interrupted: {why} while it ran, {MAX_ATTEMPTS} times; submit it again to rerun it'"
        f" WHERE {where} AND status = 'running'",
        (now, now, *args),
    ).rowcount
    return queued + interrupted
