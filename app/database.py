"""The job database: its schema, its connections, and its faults.

Every web worker process and every simulation process opens its own connection; WAL mode lets
readers (status polls) go on while a worker writes progress. Storage faults (file deleted, corrupt,
read-only, disk full) raise :class:`StoreUnavailable` with a reason a client may see (never the
file's path); :attr:`Database.state` follows them (any failure sets it, only a heartbeat write
clears it, so it cannot flicker), and the log says so once per change. Nothing is cached across
calls, so a file that comes back is used again at once, without a restart. What the tables hold
and how jobs move through them is ``store``'s.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

log = logging.getLogger("nlpsf.store")

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
    attempts INTEGER NOT NULL DEFAULT 0,
    created_at REAL NOT NULL,
    started_at REAL,
    finished_at REAL,
    updated_at REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS jobs_by_status ON jobs (status, created_at);
CREATE INDEX IF NOT EXISTS jobs_by_hash ON jobs (request_hash, status);
CREATE TABLE IF NOT EXISTS tickets (
    hash TEXT PRIMARY KEY,
    job_id TEXT NOT NULL,
    client TEXT,
    cancelled INTEGER NOT NULL DEFAULT 0,
    created_at REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS tickets_by_job ON tickets (job_id);
CREATE INDEX IF NOT EXISTS tickets_by_client ON tickets (client, created_at);
CREATE TABLE IF NOT EXISTS instances (
    id TEXT PRIMARY KEY,
    hostname TEXT NOT NULL,
    pid INTEGER NOT NULL,
    pid_start TEXT,
    heartbeat REAL NOT NULL,
    started_at REAL NOT NULL
);
"""

T = TypeVar("T")


class StoreUnavailable(Exception):
    """The job database cannot be used; ``reason`` is safe to show a client (no paths)."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


def describe_fault(error: BaseException, path: str) -> str:
    """What is wrong with the database, in words a client may read (the path stays in the log)."""
    text = str(error).lower()
    # SQLite often says only "disk I/O error" or "unable to open": ask the file system first.
    with contextlib.suppress(OSError):
        filesystem = os.statvfs(os.path.dirname(os.path.abspath(path)))
        if filesystem.f_flag & os.ST_RDONLY:
            return "the job database is read-only (its file system is mounted read-only)"
        if filesystem.f_bavail * filesystem.f_frsize < 64 * 1024:
            return "the disk holding the job database is full"
    if isinstance(error, OSError) and error.errno in (errno.ENOSPC, errno.EDQUOT):
        return "the disk holding the job database is full"
    if "disk is full" in text or "database or disk is full" in text:
        return "the disk holding the job database is full"
    if "readonly" in text or "read-only" in text or (isinstance(error, OSError) and error.errno in (errno.EACCES, errno.EROFS)):
        return "the job database is read-only (no permission to write it)"
    if "not a database" in text or "malformed" in text or "corrupt" in text:
        return "the job database is corrupt"
    if not os.path.exists(path):
        return "the job database file is missing"
    if "unable to open" in text or "disk i/o" in text or isinstance(error, OSError):
        return "the job database cannot be opened or written (I/O error)"
    if "locked" in text or "busy" in text:
        return "the job database is locked by another process"
    if "no such table" in text:
        return "the job database has lost its tables"
    return "the job database failed (an error it does not name; the service's log has it)"


def _migrate(db: sqlite3.Connection) -> None:
    db.executescript(_SCHEMA)
    columns = {row[1] for row in db.execute("PRAGMA table_info(jobs)")}
    if "attempts" not in columns:  # databases written before jobs were requeued
        db.execute("ALTER TABLE jobs ADD COLUMN attempts INTEGER NOT NULL DEFAULT 0")


class Database:
    """One SQLite file of the job store: connections, write transactions, and the state its faults set."""

    def __init__(self, path: str | os.PathLike[str]):
        self.path = str(path)
        self._schema_ready = False
        self._state_lock = threading.Lock()
        #: "ok" or "unavailable", and why; updated by every call, logged when it changes
        self.state = "ok"
        self.reason: str | None = None
        self.since = time.time()
        # A database that cannot be opened at start leaves the calculator running: the log says why,
        # the dispatcher keeps probing, and /health reports it.
        with contextlib.suppress(StoreUnavailable):
            self._guard(self._create)

    # --- connections and faults ---------------------------------------------------------------

    def _create(self) -> None:
        # Only at start is a missing file created: a file deleted later is a fault to report, not
        # an empty database to write over the operator's restore.
        Path(self.path).parent.mkdir(parents=True, exist_ok=True)
        db = sqlite3.connect(self.path, timeout=15.0, isolation_level=None)
        try:
            db.execute("PRAGMA journal_mode=WAL")
            _migrate(db)
        finally:
            db.close()
        self._schema_ready = True

    def _open(self) -> sqlite3.Connection:
        # mode=rw: never create the file behind a fault (a deleted database stays a reported fault).
        db = sqlite3.connect(f"file:{self.path}?mode=rw", uri=True, timeout=15.0, isolation_level=None)
        db.row_factory = sqlite3.Row
        try:
            db.execute("PRAGMA busy_timeout=15000")
            db.execute("PRAGMA synchronous=NORMAL")
            if not self._schema_ready:
                _migrate(db)  # a database restored from elsewhere, or created empty
                self._schema_ready = True
        except BaseException:
            db.close()
            raise
        return db

    def _guard(self, operation: Callable[[], T]) -> T:
        try:
            value = operation()
        except (sqlite3.Error, OSError) as error:
            self._schema_ready = False
            reason = describe_fault(error, self.path)
            self._set_state("unavailable", reason, error)
            raise StoreUnavailable(reason) from error
        return value

    def _set_state(self, state: str, reason: str | None, error: BaseException | None = None) -> None:
        with self._state_lock:
            if (state, reason) == (self.state, self.reason):
                return
            self.state, self.reason, self.since = state, reason, time.time()
        if state == "ok":
            log.warning("job database %s is usable again", self.path)
        else:
            log.error("job database %s unavailable: %s (%s: %s)", self.path, reason, type(error).__name__, error)

    def status(self) -> dict[str, Any]:
        return {"state": self.state, "reason": self.reason, "since": self.since}

    @contextmanager
    def connect(self) -> Iterator[sqlite3.Connection]:
        db = self._open()
        try:
            yield db
        finally:
            db.close()

    @contextmanager
    def _transaction_raw(self) -> Iterator[sqlite3.Connection]:
        """A write transaction taken at once (BEGIN IMMEDIATE), so check-then-write is atomic."""
        with self.connect() as db:
            db.execute("BEGIN IMMEDIATE")
            try:
                yield db
            except BaseException:
                db.execute("ROLLBACK")
                raise
            db.execute("COMMIT")

    def _read_op(self, function: Callable[[sqlite3.Connection], T]) -> T:
        def run() -> T:
            with self.connect() as db:
                return function(db)

        return self._guard(run)

    def _write_op(self, function: Callable[[sqlite3.Connection], T]) -> T:
        def run() -> T:
            with self._transaction_raw() as db:
                return function(db)

        return self._guard(run)
