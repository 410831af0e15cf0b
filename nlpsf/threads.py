"""How many BLAS threads the simulation kernels use: one, unless ``NLPSF_BLAS_THREADS`` says otherwise.

A simulation is thousands of small matrix products (96 x 96 stamps, 5 x 5 Jacobians). numpy's
OpenBLAS starts a thread per core for each of them, and the threads spin between products: from
the shell a Fig. 3 band cost 0.58 CPU-s with the default environment against 0.35 CPU-s on one BLAS
thread, in the same wall time. So the kernels (``experiment.prepare``, ``simulate``, ``slopes``)
run inside ``single_blas``, which limits BLAS to ``blas_threads()`` threads for the call and
restores the caller's setting after it; the rest of the process (and a user's own numpy work) is
left as it was.

``NLPSF_BLAS_THREADS`` (read here and nowhere else, at every kernel call):

- unset or empty: 1 thread;
- a positive integer: that many;
- ``0``: leave BLAS as configured (its default of one thread per core, or ``OPENBLAS_NUM_THREADS``
  and the like, which otherwise do not reach the kernels).

threadpoolctl (joblib's, maintained) is imported on the first kernel call only, so ``nlpsf --help``
and a table solve do not pay for it.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from threading import Lock
from typing import Any, TypeVar

from .checks import InputError

VARIABLE = "NLPSF_BLAS_THREADS"
DEFAULT_THREADS = 1

_F = TypeVar("_F", bound=Callable[..., Any])
# The BLAS thread count is one setting for the whole process: the first kernel to enter sets it,
# the last to leave restores it, whichever Python thread they run on.
_lock = Lock()
_depth = 0
_limiter: Any = None


def blas_threads() -> int | None:
    """BLAS threads for the simulation kernels (None: leave BLAS as configured)."""
    text = os.environ.get(VARIABLE, "").strip()
    if not text:
        return DEFAULT_THREADS
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise InputError(VARIABLE, f"must be a whole number of threads >= 0 (0: the BLAS default), not {text!r}")
    return value or None


@contextmanager
def limited_blas() -> Iterator[None]:
    """Run the block on ``blas_threads()`` BLAS threads; nested blocks keep the outermost's limit."""
    global _depth, _limiter
    threads = blas_threads()
    with _lock:
        if _depth == 0 and threads is not None:
            from threadpoolctl import threadpool_limits

            _limiter = threadpool_limits(limits=threads, user_api="blas")
        _depth += 1
    try:
        yield
    finally:
        with _lock:
            _depth -= 1
            if _depth == 0 and _limiter is not None:
                _limiter.restore_original_limits()
                _limiter = None


def single_blas(function: _F) -> _F:
    """Decorate a simulation kernel: it runs inside ``limited_blas``."""

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        with limited_blas():
            return function(*args, **kwargs)

    return wrapper  # type: ignore[return-value]
