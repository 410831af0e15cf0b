"""Running independent tasks serially, on local processes or on a dask.distributed cluster.

One owner for how the long jobs (``tables build``, ``sweep``) spread their work. The rule that
makes a remote cluster work: a task *returns its data* and the client writes it. Workers may run
on other machines or in other directories, so a task never touches a path the client chose.

Retries: a task that raises is re-run up to ``retries`` times (dask's ``retries=``; the same
loop locally). A worker that dies is dask's business: the scheduler re-runs its tasks elsewhere,
up to ``distributed.scheduler.allowed-failures`` deaths per task (default 3), after which the
task fails with ``KilledWorker``. Failures come back to the caller as values, so one bad task does
not discard the others' results.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from nlpsf.checks import InputError, check_integer

MAX_RETRIES = 100


def write_atomic(table, path: Path) -> None:
    """Write an astropy table as ECSV so that an interrupted run never leaves half a file behind."""
    temporary = path.with_name(path.name + ".tmp")
    table.write(temporary, format="ascii.ecsv", overwrite=True)
    temporary.replace(path)


def check_backend(workers: int, dask_address: str | None, scheduler_file: str | None, retries: int) -> None:
    check_integer(workers, "workers", 1, 4096)
    check_integer(retries, "retries", 0, MAX_RETRIES)
    if dask_address is not None and scheduler_file is not None:
        raise InputError("scheduler_file", "give a scheduler address (dask) or a scheduler file, not both")


@contextlib.contextmanager
def dask_client(address: str | None = None, scheduler_file: str | None = None, workers: int = 1):
    """A ``dask.distributed.Client``: to ``address``, through ``scheduler_file``, or on a LocalCluster
    of ``workers`` processes when ``address`` is "local"."""
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError as error:  # pragma: no cover - depends on the optional extra
        raise InputError("dask", "dask.distributed is not installed: pip install 'nlpsf[dask]'") from error
    cluster = None
    if scheduler_file is not None:
        client = Client(scheduler_file=scheduler_file)
    elif address == "local":
        import dask

        # dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 in its workers, which switches off glibc's
        # dynamic mmap threshold: every large temporary array is then mmapped and page-faulted
        # afresh, and a slope table of the Roman scene costs 3 x the CPU (75.8 s against 22-24 s
        # in a plain process, docs/field.md). None unsets it (distributed's own convention).
        with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
            cluster = LocalCluster(n_workers=max(workers, 1), threads_per_worker=1, processes=True, dashboard_address=None)
        client = Client(cluster)
    else:
        client = Client(address)
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def run_tasks(
    function: Callable,
    tasks: Sequence[tuple],
    workers: int = 1,
    dask_address: str | None = None,
    scheduler_file: str | None = None,
    retries: int = 0,
    client=None,
) -> Iterator[tuple[int, object, BaseException | None]]:
    """``function(*task)`` for each task; yields ``(index, result, None)`` or ``(index, None, error)``
    as tasks finish (in any order). ``client``: an existing dask client (overrides the address)."""
    check_backend(workers, dask_address, scheduler_file, retries)
    if not tasks:
        return
    if client is not None:
        yield from _run_dask(client, function, tasks, retries)
    elif dask_address is not None or scheduler_file is not None:
        with dask_client(dask_address, scheduler_file, workers) as owned:
            yield from _run_dask(owned, function, tasks, retries)
    elif workers > 1 and len(tasks) > 1:
        yield from _run_processes(function, tasks, workers, retries)
    else:
        for index, task in enumerate(tasks):
            for attempt in range(retries + 1):
                try:
                    result = function(*task)
                except Exception as error:  # reported per task, after the retries
                    if attempt == retries:
                        yield index, None, error
                else:
                    yield index, result, None
                    break


def _run_processes(function, tasks, workers, retries):
    with ProcessPoolExecutor(max_workers=workers) as pool:
        pending = {pool.submit(function, *task): (index, 0) for index, task in enumerate(tasks)}
        while pending:
            future = next(as_completed(pending))
            index, attempt = pending.pop(future)
            error = future.exception()
            if error is None:
                yield index, future.result(), None
            elif attempt < retries:
                pending[pool.submit(function, *tasks[index])] = (index, attempt + 1)
            else:
                yield index, None, error


def _run_dask(client, function, tasks, retries):
    from dask.distributed import as_completed as dask_completed

    futures = {client.submit(function, *task, retries=retries, pure=False): index for index, task in enumerate(tasks)}
    try:
        for future in dask_completed(futures):
            index = futures[future]
            try:
                outcome = (index, future.result(), None)
            except Exception as error:  # KilledWorker, or the task's own error after its retries
                outcome = (index, None, error)
            future.release()
            yield outcome
    finally:
        client.cancel(list(futures))
