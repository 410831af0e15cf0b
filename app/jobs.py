"""The simulation job system: a bounded pool of worker processes fed from the database queue.

Each web worker process runs one :class:`Dispatcher` on its event loop. It claims queued jobs
while fewer than ``job_workers`` run across the whole service (the claim is one SQLite
transaction), starts one process per job from a forkserver (so a cancel can stop it at once and a
crash in one cannot break a pool), watches them, keeps its instance's heartbeat fresh (the
heartbeat is also the probe that tells a broken job database from a working one) and applies the
retention rule. One :class:`Notifier` per web worker answers every ``?wait=`` with one query.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import os
import threading
import time
from collections.abc import Iterator
from multiprocessing.process import BaseProcess

from .settings import Settings
from .store import FINISHED, Store, StoreUnavailable

log = logging.getLogger("nlpsf.jobs")

_POLL_S = 0.1
#: Heartbeat (and the job database's integrity check, PRAGMA quick_check) every this many s: damage
#: shows in /health within about this long, in every worker.
_HEARTBEAT_S = 1.0
#: How often running jobs are checked for progress and wall time, s.
_WATCH_S = 1.0
#: CPU time a job must use between checks to count as working when it reports no progress, s (a
#: stopped or deadlocked process uses none; its parent-watch thread, a few microseconds a second).
_WORKING_CPU_S = 0.05
_SWEEP_S = 5.0
_PRUNE_S = 60.0

_WORKER_MODULE = f"{__package__}.worker"
_context = multiprocessing.get_context("forkserver")
_context.set_forkserver_preload([_WORKER_MODULE])


@contextlib.contextmanager
def safe_path() -> Iterator[None]:
    """Processes started inside do not put the working directory on ``sys.path`` (PYTHONSAFEPATH).

    The forkserver is a fresh interpreter started with ``python -c``, which puts the working
    directory first on its path, and Python before 3.13 ignores the parent's path it is handed:
    started from a clone's root, ``import nlpsf`` there would find the source folder ``./nlpsf``
    instead of the installed package (which holds ``nlpsf.web``, and is what the service runs), and
    every job would fail. Set while a process is started, so the forkserver (started with the first
    job, and again if it dies) never looks there."""
    before = os.environ.get("PYTHONSAFEPATH")
    os.environ["PYTHONSAFEPATH"] = "1"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("PYTHONSAFEPATH", None)
        else:
            os.environ["PYTHONSAFEPATH"] = before


class Dispatcher:
    def __init__(self, store: Store, settings: Settings):
        self.store = store
        self.settings = settings
        self.instance = ""
        self.processes: dict[str, BaseProcess] = {}
        self._task: asyncio.Task | None = None
        self._wake = asyncio.Event()
        # _tick runs in a thread that cancelling the task cannot stop: stopping waits for it.
        self._lock = threading.Lock()
        self._stopping = False
        #: set by stop(): the loop ends at its next turn even if the cancellation below is lost
        self._closing = False
        #: per running job: start (monotonic), wall-time limit, last CPU time, last progress write, last sign of work
        self.watch: dict[str, dict[str, float]] = {}
        self._last_watch = 0.0

    async def start(self) -> None:
        await asyncio.to_thread(self._register)
        self._task = asyncio.create_task(self._loop(), name="nlpsf-dispatcher")

    def _register(self) -> None:
        try:
            self.store.interrupt_orphans(self.settings.stale_after_s)
            self.instance = self.store.register_instance()
        except StoreUnavailable:
            pass  # retried by the loop; the store has logged the reason once

    def wake(self) -> None:
        self._wake.set()

    async def stop(self) -> None:
        if self._task:
            # Python 3.11's asyncio.wait_for loses a cancellation that arrives as the awaited wake-up
            # completes (a job woke the loop as the service stopped; fixed in 3.12): the task then
            # ran on and this await never returned (a shutdown that hung). The flag ends the loop anyway.
            self._closing = True
            self._wake.set()
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        await asyncio.to_thread(self._stop_processes)

    def _stop_processes(self) -> None:
        with self._lock:
            self._stopping = True
            for process in self.processes.values():
                process.terminate()
            for process in self.processes.values():
                process.join(5)
                if process.is_alive():
                    process.kill()
                    process.join(5)
            self.processes.clear()
            if self.instance:
                with contextlib.suppress(StoreUnavailable):
                    # Back to the queue: another worker, or this service after a restart, runs them.
                    self.store.release_owned(self.instance)
                    self.store.unregister_instance(self.instance)

    async def _loop(self) -> None:
        last_heartbeat = last_sweep = time.monotonic()
        last_prune = 0.0
        while not self._closing:
            try:
                now = time.monotonic()
                if not self.instance:
                    await asyncio.to_thread(self._register)
                if now - last_heartbeat > _HEARTBEAT_S or self.store.state != "ok":
                    if self.instance:
                        await asyncio.to_thread(self.store.heartbeat, self.instance)
                    last_heartbeat = now
                if self.instance and self.store.state == "ok":
                    await asyncio.to_thread(self._tick)
                    if now - last_sweep > _SWEEP_S:
                        await asyncio.to_thread(self.store.interrupt_orphans, self.settings.stale_after_s)
                        last_sweep = now
                    if now - last_prune > _PRUNE_S:
                        await asyncio.to_thread(self._prune)
                        last_prune = now
            except asyncio.CancelledError:
                raise
            except StoreUnavailable:
                pass  # the store logged it once; the heartbeat probes until it is back
            except Exception:  # keep dispatching; a bug here must not stop the service
                log.exception("job dispatcher")
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), _POLL_S if self.store.state == "ok" else 1.0)
            self._wake.clear()

    def _prune(self) -> None:
        removed = self.store.prune(self.settings.retention_s, self.settings.max_stored_results)
        if any(removed.values()):
            log.info("retention: removed %(results)d results, %(jobs)d jobs, %(tickets)d tickets", removed)

    def _tick(self) -> None:
        with self._lock:
            if not self._stopping:
                self._dispatch()

    def _dispatch(self) -> None:
        for job_id in self.store.cancel_requested(self.instance):
            process = self.processes.pop(job_id, None)
            self.watch.pop(job_id, None)
            if process is not None:
                process.terminate()
                process.join(5)
            self.store.end(job_id, "cancelled", "cancelled while running", owner=self.instance)
        for job_id, process in list(self.processes.items()):
            if process.is_alive():
                continue
            process.join()
            # A worker that exited without recording an outcome (killed, out of memory) failed. The
            # entry is dropped only once that is recorded, so a database fault cannot leave it "running".
            self.store.end(
                job_id,
                "failed",
                f"the simulation process ended unexpectedly (exit code {process.exitcode})",
                {"field": None, "message": f"exit code {process.exitcode}"},
                owner=self.instance,
            )
            del self.processes[job_id]
            self.watch.pop(job_id, None)
        if time.monotonic() - self._last_watch > _WATCH_S:
            self._last_watch = time.monotonic()
            self._end_stalled()
        while len(self.processes) < self.settings.job_workers:
            job = self.store.claim(self.instance, self.settings.job_workers)
            if job is None:
                break
            import importlib

            worker = importlib.import_module(_WORKER_MODULE)
            process = _context.Process(
                target=worker.run_job,
                args=(
                    self.store.path,
                    job["id"],
                    self.instance,
                    job["request_hash"],
                    job["request"],
                    os.getpid(),
                    self.settings.job_nice,
                    self.settings.job_memory_mb,
                ),
                name=f"nlpsf-job-{job['id'][:8]}",
                daemon=True,
            )
            with safe_path():
                process.start()
            self.processes[job["id"]] = process
            now = time.monotonic()
            self.watch[job["id"]] = {
                "started": now,
                "limit": self.settings.job_time_limit_s(_estimate(job["request"])),
                "cpu": 0.0,
                "updated": 0.0,
                "seen": now,
            }
            self.store.set_pid(job["id"], process.pid or 0)

    def _end_stalled(self) -> None:
        """End a running job that has shown no sign of work (no progress written, no CPU time used)
        for job_stall_s, or has run past its wall-time limit: killed, recorded failed, its place freed."""
        if not self.processes:
            return
        updated = self.store.running_updates(self.instance)
        now = time.monotonic()
        for job_id, process in list(self.processes.items()):
            watch = self.watch.get(job_id)
            if watch is None or not process.is_alive():
                continue
            cpu = _cpu_seconds(process.pid or 0)
            if cpu - watch["cpu"] > _WORKING_CPU_S or updated.get(job_id, 0.0) != watch["updated"]:
                watch.update(cpu=cpu, updated=updated.get(job_id, 0.0), seen=now)
            stall = self.settings.job_stall_s
            if now - watch["seen"] > stall:
                why, limit = (
                    f"the simulation made no progress for {stall:g} s (no progress report and no CPU time; "
                    "the setting job_stall_s) and was ended",
                    "job_stall_s",
                )
            elif now - watch["started"] > watch["limit"]:
                why, limit = (
                    f"the simulation ran past its wall-time limit of {watch['limit']:,.0f} s (job_time_factor x its "
                    f"estimated duration, at least 10 x job_stall_s) and was ended",
                    "job_time_factor",
                )
            else:
                continue
            log.error("job %s: %s", job_id, why)
            process.kill()  # SIGKILL: a stopped process cannot run a SIGTERM handler
            process.join(5)
            self.store.end(job_id, "failed", why, {"field": None, "message": why, "limit": limit}, owner=self.instance)
            self.processes.pop(job_id, None)
            self.watch.pop(job_id, None)


def _estimate(request: dict) -> float | None:
    """The job's estimated duration on one core, s (None where its kind cannot price it)."""
    from . import job_kinds

    try:
        return job_kinds.estimate(request)
    except Exception:  # an estimate must never stop a job from starting
        return None


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process, s (Linux /proc; 0 elsewhere)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as handle:
            fields = handle.read().rsplit(b")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return 0.0


class Notifier:
    """Every ``?wait=`` of this web worker waits on one poll: one query for all watched tickets every
    ``interval`` s (and only while someone waits), not a connection per waiter."""

    def __init__(self, store: Store, interval: float = 0.1):
        self.store = store
        self.interval = interval
        self._waiters: dict[str, list[asyncio.Future[str]]] = {}
        self._task: asyncio.Task | None = None

    async def wait(self, ticket: str, timeout: float) -> str | None:
        """The ticket's finished status, or None if it has not finished within ``timeout``."""
        if timeout <= 0:
            return None
        future: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        self._waiters.setdefault(ticket, []).append(future)
        if self._task is None or self._task.done():
            self._task = asyncio.create_task(self._poll(), name="nlpsf-notifier")
        try:
            return await asyncio.wait_for(asyncio.shield(future), timeout)
        except TimeoutError:
            return None
        finally:
            waiters = self._waiters.get(ticket, [])
            if future in waiters:
                waiters.remove(future)
            if not waiters:
                self._waiters.pop(ticket, None)

    async def _poll(self) -> None:
        while self._waiters:
            await asyncio.sleep(self.interval)
            try:
                statuses = await asyncio.to_thread(self.store.statuses, list(self._waiters))
            except StoreUnavailable:
                continue
            for ticket, status in statuses.items():
                if status in FINISHED:
                    for future in self._waiters.pop(ticket, []):
                        if not future.done():
                            future.set_result(status)

    async def stop(self) -> None:
        if self._task:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
