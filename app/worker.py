"""What runs inside a simulation process (started from a forkserver that preloaded this module).

The process is niced so the HTTP workers win the CPU, lives within its memory budget
(RLIMIT_AS: a job that asks for more fails with a MemoryError on the job, the host is untouched),
writes its progress to the database, stops when the job is cancelled, and exits if the service that
started it is gone (no orphans). A finished result is written even through a passing database fault:
the write is retried while the service lives.
"""

from __future__ import annotations

import contextlib
import os
import resource
import threading
import time
import traceback
from typing import Any

from nlpsf.checks import InputError

# Imported here so the forkserver has numpy, scipy and the simulator loaded before it forks.
from nlpsf.sim import experiment  # noqa: F401

from . import job_kinds
from .store import Store, StoreUnavailable

_PROGRESS_INTERVAL_S = 0.2
_RECORD_RETRY_S = 600.0


class Cancelled(Exception):
    pass


def _watch_parent(service_pid: int) -> None:
    while True:
        time.sleep(1.0)
        if not _alive(service_pid):
            os._exit(3)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


def _virtual_size() -> int:
    """This process's address space now (VmSize), bytes: libraries mapped, thread stacks reserved."""
    with open("/proc/self/status") as handle:
        for line in handle:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    return 0


def limit_memory(budget_mb: int) -> None:
    """Cap the address space at what is mapped now plus ``budget_mb``: the job's arrays get the
    budget, whatever the interpreter and libraries reserved at start (Linux; elsewhere a no-op)."""
    with contextlib.suppress(OSError, ValueError):
        limit = _virtual_size() + budget_mb * 1024**2
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))


def _record(action, service_pid: int) -> None:
    """Write an outcome, retrying through a database fault for as long as the service lives."""
    deadline = time.monotonic() + _RECORD_RETRY_S
    delay = 0.2
    while True:
        try:
            action()
            return
        except StoreUnavailable:
            if time.monotonic() > deadline or not _alive(service_pid):
                raise
            time.sleep(delay)
            delay = min(2 * delay, 5.0)


def run_job(
    db_path: str,
    job_id: str,
    owner: str,
    request_hash: str,
    request: dict[str, Any],
    service_pid: int,
    nice: int,
    memory_mb: int | None = None,
) -> None:
    if nice:
        os.nice(nice)
        # Below every normal process: the calculator keeps the CPU whenever it wants it (Linux only).
        with contextlib.suppress(AttributeError, OSError):
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    threading.Thread(target=_watch_parent, args=(service_pid,), daemon=True).start()
    if memory_mb:
        limit_memory(memory_mb)
    store = Store(db_path)
    last = 0.0

    def progress(fraction: float, message: str) -> None:
        nonlocal last
        now = time.monotonic()
        if fraction < 1.0 and now - last < _PROGRESS_INTERVAL_S:
            return
        last = now
        try:
            going_on = store.progress(job_id, owner, fraction, message)
        except StoreUnavailable:
            return  # progress is a courtesy; the result is what must not be lost
        if not going_on:
            raise Cancelled

    def end(status: str, message: str, error: dict[str, Any] | None = None) -> None:
        _record(lambda: store.end(job_id, status, message, error, owner=owner), service_pid)

    try:
        result = job_kinds.run(request, progress)
    except Cancelled:
        end("cancelled", "cancelled while running")
        return
    except InputError as error:
        field = job_kinds.request_field(error.argument, request)
        end("failed", str(error), {"field": field, "message": error.reason})
        return
    except MemoryError:
        message = f"the simulation needed more than its memory budget ({memory_mb} MB, the setting job_memory_mb)"
        end("failed", message, {"field": None, "message": message, "limit": "job_memory_mb"})
        return
    except Exception:  # a bug or resource failure: report it on the job, never lose it
        traceback.print_exc()  # to the service's log; the job says what failed, without server paths
        # Not the exception's class or text: they name the server's code (the log above has them).
        message = "the simulation failed unexpectedly; please report it with the request that caused it"
        end("failed", message, {"field": None, "message": message})
        return
    _record(lambda: store.finish(job_id, owner, request_hash, result), service_pid)
