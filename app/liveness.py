"""HTTP worker heartbeats: how the supervisor (``server.py``) tells a working worker from a stopped
or hung one, and how ``/health`` reports it.

The supervisor gives every worker process one slot of a shared array of doubles. The worker's event
loop writes ``time.monotonic()`` there on every uvicorn tick (10 a second): a beat comes from the
loop itself, so a worker whose loop is blocked (a handler that never yields) falls silent exactly
like one that is stopped (SIGSTOP) or swapped out. Linux's monotonic clock is one clock for every
process, so the supervisor and every worker compare the same numbers.

Without a supervisor (the in-process TestClient, ``uvicorn nlpsf.web.main:app``) nothing is shared
and ``report()`` returns None.
"""

from __future__ import annotations

import time
from typing import Any

#: The shared beats (a multiprocessing.Array of doubles) and this process's slot, set by the
#: supervisor's worker entry before uvicorn starts.
BEATS: Any = None
INDEX: int | None = None
#: Silence after which the supervisor kills a worker (its heartbeat_timeout_s).
TIMEOUT_S: float = 3.0
#: Silence after which /health reports a worker as stalled: ten missed beats, or the kill timeout
#: if that is shorter. Reported from here until the supervisor has replaced it.
REPORT_AFTER_S: float = 1.0


def install(beats: Any, index: int, timeout_s: float) -> None:
    global BEATS, INDEX, TIMEOUT_S
    BEATS, INDEX, TIMEOUT_S = beats, index, timeout_s


def beat() -> None:
    if BEATS is not None and INDEX is not None:
        BEATS[INDEX] = time.monotonic()


def silence(index: int, now: float | None = None) -> float:
    """Seconds since worker ``index`` last beat (negative while a new worker is within its start grace)."""
    return (time.monotonic() if now is None else now) - BEATS[index]


def report() -> dict[str, Any] | None:
    """Every HTTP worker's state as /health shows it: how many there are, how many respond (have
    beaten within the last second), how many are still starting (no beat yet: their slot holds the
    end of their start grace, a time to come) and which are silent and for how long."""
    if BEATS is None:
        return None
    now = time.monotonic()
    silent = {index: silence(index, now) for index in range(len(BEATS))}
    threshold = min(REPORT_AFTER_S, TIMEOUT_S)
    stalled = [{"worker": index, "silent_s": round(age, 1)} for index, age in silent.items() if age > threshold]
    starting = sum(1 for age in silent.values() if age < 0)
    return {
        "workers": len(BEATS),
        "responding": len(BEATS) - len(stalled) - starting,
        "starting": starting,
        "stalled": stalled,
        "heartbeat_timeout_s": TIMEOUT_S,
        "this_worker": INDEX,
    }
