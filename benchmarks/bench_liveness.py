"""The HTTP worker supervisor against gunicorn's arbiter, under the same stall and burst tests.

    python benchmarks/bench_liveness.py [--requests 1500] [--timeout 5]

Both run two uvicorn workers on 127.0.0.1 (never another address) with a heartbeat timeout of
``--timeout`` seconds: ``nlpsf serve`` (its own supervisor, one SO_REUSEPORT socket per worker) and
``gunicorn -k uvicorn.workers.UvicornWorker`` (its arbiter, heartbeat files, ``--timeout``), with and
without ``--reuse-port``. gunicorn is not a dependency of nlpsf; install it to run this
(``pip install gunicorn``).

- burst: ``--requests`` table solves (POST /api/v1/solve), 50 at a time, a new connection each;
  requests per second, and how many got no answer. Client and server share this machine's cores,
  so compare the rows of one run, not runs of different days.
- stall: SIGSTOP one worker, then one GET /api/v1/health every 0.1 s for 12 s, each on a new
  connection with a 3 s timeout: how many got no answer, when the stopped worker was replaced
  (a new worker process), and when /health first reported it stalled (nlpsf only).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

HOST = "127.0.0.1"  # loopback only
SOLVE = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}


def free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


def children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            cmdline = Path(f"/proc/{entry}/cmdline").read_bytes()
        except OSError:
            continue
        parent = int(stat.rsplit(")", 1)[1].split()[1])
        if parent == pid and b"resource_tracker" not in cmdline and b"forkserver" not in cmdline:
            out.append(int(entry))
    return sorted(out)


def tree_cpu_seconds(pid: int) -> float:
    """CPU time (user + system) of a server and its children, s: what a request costs the server,
    whatever else the machine is doing."""
    total = 0.0
    for member in [pid, *children(pid)]:
        try:
            fields = Path(f"/proc/{member}/stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        total += (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    return total


def start(kind: str, port: int, timeout: float, folder: str) -> subprocess.Popen:
    env = {**os.environ, "NLPSF_DB_PATH": f"{folder}/{kind}.sqlite3", "NLPSF_HEARTBEAT_TIMEOUT_S": str(timeout)}
    if kind.startswith("nlpsf"):
        env["NLPSF_SHARED_SOCKET"] = "false" if kind == "nlpsf-reuse-port" else "true"
        command = [sys.executable, "-m", "nlpsf", "serve", "--host", HOST, "--port", str(port), "--workers", "2"]
    else:
        command = [sys.executable, "-m", "gunicorn", "nlpsf.web.main:app", "-k", "uvicorn.workers.UvicornWorker"]
        command += ["-w", "2", "--timeout", str(int(timeout)), "-b", f"{HOST}:{port}", "--graceful-timeout", "5"]
        if kind == "gunicorn-reuse-port":
            command.append("--reuse-port")
    process = subprocess.Popen(command, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 90
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://{HOST}:{port}/api/v1/health", timeout=1).status_code == 200 and len(children(process.pid)) >= 2:
                time.sleep(3)  # both workers up and past their start
                return process
        except httpx.HTTPError:
            pass
        time.sleep(0.3)
    process.kill()
    raise RuntimeError(f"{kind} did not start")


async def burst(port: int, requests: int, concurrency: int = 50) -> tuple[float, int]:
    limits = httpx.Limits(max_keepalive_connections=0, max_connections=concurrency)
    failures = 0
    async with httpx.AsyncClient(base_url=f"http://{HOST}:{port}", limits=limits, timeout=10) as client:
        semaphore = asyncio.Semaphore(concurrency)

        async def one():
            nonlocal failures
            async with semaphore:
                try:
                    response = await client.post("/api/v1/solve", json=SOLVE)
                    failures += response.status_code != 200
                except httpx.HTTPError:
                    failures += 1

        begin = time.perf_counter()
        await asyncio.gather(*(one() for _ in range(requests)))
        return requests / (time.perf_counter() - begin), failures


def stall(process: subprocess.Popen, port: int, seconds: float = 12.0) -> dict:
    workers = children(process.pid)
    victim = workers[0]
    os.kill(victim, signal.SIGSTOP)
    stopped_at = time.monotonic()
    results: list[bool] = []
    reported_at = replaced_at = None
    lock = threading.Lock()

    def probe():
        nonlocal reported_at
        try:
            response = httpx.get(f"http://{HOST}:{port}/api/v1/health", timeout=3, headers={"connection": "close"})
            ok = response.status_code == 200
            stalled = (response.json().get("http_workers") or {}).get("stalled")
            with lock:
                if stalled and reported_at is None:
                    reported_at = time.monotonic() - stopped_at
        except httpx.HTTPError:
            ok = False
        with lock:
            results.append(ok)

    threads = []
    while time.monotonic() - stopped_at < seconds:
        thread = threading.Thread(target=probe)
        thread.start()
        threads.append(thread)
        if replaced_at is None and victim not in children(process.pid) and len(children(process.pid)) >= 2:
            replaced_at = time.monotonic() - stopped_at
        time.sleep(0.1)
    for thread in threads:
        thread.join()
    with_contextlib_kill(victim)
    return {
        "probes": len(results),
        "unanswered": results.count(False),
        "replaced_after_s": replaced_at,
        "health_reported_after_s": reported_at,
    }


def with_contextlib_kill(pid: int) -> None:
    for sig in (signal.SIGCONT, signal.SIGKILL):
        try:
            os.kill(pid, sig)
        except ProcessLookupError:
            return


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--requests", type=int, default=1500)
    parser.add_argument("--timeout", type=float, default=5.0)
    parser.add_argument("--kinds", default="nlpsf,nlpsf-reuse-port,gunicorn,gunicorn-reuse-port")
    args = parser.parse_args()
    folder = tempfile.mkdtemp(prefix="nlpsf-liveness-")
    print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores, timeout {args.timeout:g} s")
    print(
        "| supervisor | burst req/s | server CPU ms/request | burst failures | stall probes | unanswered (3 s) "
        "| replaced after s | /health said so after s |"
    )
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for kind in args.kinds.split(","):
        port = free_port()
        process = start(kind, port, args.timeout, folder)
        try:
            cpu = tree_cpu_seconds(process.pid)
            rate, failures = asyncio.run(burst(port, args.requests))
            cpu_ms = 1000 * (tree_cpu_seconds(process.pid) - cpu) / args.requests
            result = stall(process, port)
        finally:
            process.send_signal(signal.SIGTERM)
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                process.kill()
        shown = {k: ("-" if v is None else f"{v:.1f}" if isinstance(v, float) else v) for k, v in result.items()}
        print(
            f"| {kind} | {rate:.0f} | {cpu_ms:.2f} | {failures} | {shown['probes']} | {shown['unanswered']} "
            f"| {shown['replaced_after_s']} | {shown['health_reported_after_s']} |",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
