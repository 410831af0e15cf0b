"""What runs inside a simulation process (started from a forkserver that preloaded this module).

The process is niced so the HTTP workers win the CPU, writes its progress to the database, stops
when the job is cancelled, and exits if the service that started it is gone (no orphans).
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
import traceback
from typing import Any

# Imported here so the forkserver has numpy, scipy and the simulator loaded before it forks.
from nlpsf import experiment  # noqa: F401
from nlpsf.checks import InputError

from . import simulation
from .store import Store

_PROGRESS_INTERVAL_S = 0.2


class Cancelled(Exception):
    pass


def _watch_parent(service_pid: int) -> None:
    while True:
        time.sleep(1.0)
        try:
            os.kill(service_pid, 0)
        except ProcessLookupError:
            os._exit(3)
        except PermissionError:
            pass


def run_job(
    db_path: str, job_id: str, owner: str, request_hash: str, request: dict[str, Any], service_pid: int, nice: int
) -> None:
    if nice:
        os.nice(nice)
        # Below every normal process: the calculator keeps the CPU whenever it wants it (Linux only).
        with contextlib.suppress(AttributeError, OSError):
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    threading.Thread(target=_watch_parent, args=(service_pid,), daemon=True).start()
    store = Store(db_path)
    last = 0.0

    def progress(fraction: float, message: str) -> None:
        nonlocal last
        now = time.monotonic()
        if fraction < 1.0 and now - last < _PROGRESS_INTERVAL_S:
            return
        last = now
        if not store.progress(job_id, owner, fraction, message):
            raise Cancelled

    try:
        result = simulation.run(request, progress)
    except Cancelled:
        store.end(job_id, "cancelled", "cancelled while running", owner=owner)
        return
    except InputError as error:
        field = simulation.request_field(error.argument)
        store.end(job_id, "failed", str(error), {"field": field, "message": error.reason}, owner=owner)
        return
    except Exception as error:  # a bug or resource failure: report it on the job, never lose it
        store.end(
            job_id,
            "failed",
            f"simulation failed: {type(error).__name__}: {error}",
            {"field": None, "message": str(error), "traceback": traceback.format_exc(limit=8)},
            owner=owner,
        )
        return
    store.finish(job_id, owner, request_hash, result)
