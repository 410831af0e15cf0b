"""The simulation job system: a bounded pool of worker processes fed from the database queue.

Each web worker process runs one :class:`Dispatcher` on its event loop. It claims queued jobs
while fewer than ``job_workers`` run across the whole service (the claim is one SQLite
transaction), starts one process per job from a forkserver (so a cancel can stop it at once and a
crash in one cannot break a pool), watches them, and keeps its instance's heartbeat fresh.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import multiprocessing
import os
import threading
import time
from multiprocessing.process import BaseProcess

from .settings import Settings
from .store import Store

log = logging.getLogger("nlpsf.jobs")

_POLL_S = 0.1
_HEARTBEAT_S = 2.0
_SWEEP_S = 5.0

_context = multiprocessing.get_context("forkserver")
_context.set_forkserver_preload(["app.worker"])


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

    async def start(self) -> None:
        await asyncio.to_thread(self.store.interrupt_orphans, self.settings.stale_after_s)
        self.instance = await asyncio.to_thread(self.store.register_instance)
        self._task = asyncio.create_task(self._loop(), name="nlpsf-dispatcher")

    def wake(self) -> None:
        self._wake.set()

    async def stop(self) -> None:
        if self._task:
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
                self.store.interrupt_owned(
                    self.instance, "the service was stopped while this simulation was running; submit it again to rerun it"
                )
                self.store.unregister_instance(self.instance)

    async def _loop(self) -> None:
        last_heartbeat = last_sweep = time.monotonic()
        while True:
            try:
                await asyncio.to_thread(self._tick)
                now = time.monotonic()
                if now - last_heartbeat > _HEARTBEAT_S:
                    await asyncio.to_thread(self.store.heartbeat, self.instance)
                    last_heartbeat = now
                if now - last_sweep > _SWEEP_S:
                    await asyncio.to_thread(self.store.interrupt_orphans, self.settings.stale_after_s)
                    last_sweep = now
            except asyncio.CancelledError:
                raise
            except Exception:  # keep dispatching; a transient database error must not stop the service
                log.exception("job dispatcher")
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._wake.wait(), _POLL_S)
            self._wake.clear()

    def _tick(self) -> None:
        with self._lock:
            if not self._stopping:
                self._dispatch()

    def _dispatch(self) -> None:
        for job_id in self.store.cancel_requested(self.instance):
            process = self.processes.pop(job_id, None)
            if process is not None:
                process.terminate()
                process.join(5)
            self.store.end(job_id, "cancelled", "cancelled while running", owner=self.instance)
        for job_id, process in list(self.processes.items()):
            if process.is_alive():
                continue
            process.join()
            del self.processes[job_id]
            # A worker that exited without recording an outcome (killed, out of memory) failed.
            self.store.end(
                job_id,
                "failed",
                f"the simulation process ended unexpectedly (exit code {process.exitcode})",
                {"field": None, "message": f"exit code {process.exitcode}"},
                owner=self.instance,
            )
        while len(self.processes) < self.settings.job_workers:
            job = self.store.claim(self.instance, self.settings.job_workers)
            if job is None:
                break
            from . import worker

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
                ),
                name=f"nlpsf-job-{job['id'][:8]}",
                daemon=True,
            )
            process.start()
            self.processes[job["id"]] = process
            self.store.set_pid(job["id"], process.pid or 0)
