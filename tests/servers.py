"""Helpers for tests that run the real service as a separate process (jobs, browser, container)."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import httpx

ROOT = Path(__file__).resolve().parent.parent
T = TypeVar("T")


def wait_for(predicate: Callable[[], T], timeout: float = 60.0, interval: float = 0.05) -> T:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {predicate}")


def finished_job(client, job_id: str, timeout: float = 600.0):
    """GET /simulations/ID until the job has finished (any final status); fails after ``timeout`` s
    (generous: a loaded machine runs the job late, a broken one never)."""

    def poll():
        response = client.get(f"/api/v1/simulations/{job_id}")
        return response if response.json()["status"] not in ("queued", "running") else None

    return wait_for(poll, timeout=timeout, interval=0.1)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def healthy(port: int, process: subprocess.Popen | None = None) -> bool:
    if process is not None:
        assert process.poll() is None, f"the server exited with status {process.returncode}"
    try:
        return httpx.get(f"http://127.0.0.1:{port}/api/v1/health", timeout=1).status_code == 200
    except httpx.HTTPError:
        return False


def start_server(
    db_path: Path,
    port: int,
    env: dict[str, str] | None = None,
    log: Path | None = None,
    cwd: Path | None = None,
    args: tuple[str, ...] = (),
) -> subprocess.Popen:
    """``nlpsf serve`` on 127.0.0.1:port with its own database (started in ``cwd``, default the
    repository); returns once /health answers."""
    environment = {**os.environ, "NLPSF_DB_PATH": str(db_path), "NLPSF_HOST": "127.0.0.1", **(env or {})}
    output = open(log, "wb") if log else subprocess.DEVNULL  # noqa: SIM115 - the server outlives this call
    process = subprocess.Popen(
        [sys.executable, "-c", "import sys; from nlpsf.cli import main; sys.exit(main())", "serve", "--port", str(port), *args],
        cwd=cwd or ROOT,
        env=environment,
        stdout=output,
        stderr=subprocess.STDOUT,
    )
    try:
        wait_for(lambda: healthy(port, process), timeout=60, interval=0.2)
    except BaseException:
        process.kill()
        process.wait(10)
        raise
    return process


def child_pids(pid: int) -> list[int]:
    """Direct children of ``pid`` (Linux /proc): a supervisor's HTTP workers (and its helpers)."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat", "rb") as handle:
                    parent = int(handle.read().rsplit(b")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
            if parent == pid:
                out.append(int(entry))
    return sorted(out)


def http_workers(pid: int) -> list[int]:
    """The HTTP worker processes of the ``nlpsf serve`` supervisor ``pid``."""
    workers = []
    for child in child_pids(pid):
        try:
            with open(f"/proc/{child}/cmdline", "rb") as handle:
                cmdline = handle.read()
        except OSError:
            continue
        if b"resource_tracker" not in cmdline and b"forkserver" not in cmdline:
            workers.append(child)
    return workers


def crash(process: subprocess.Popen) -> None:
    """SIGKILL the whole service at once, supervisor and HTTP workers: a crash, with no chance to clean up."""
    for pid in [process.pid, *child_pids(process.pid)]:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, 9)
    process.wait(10)
