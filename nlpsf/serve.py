"""``nlpsf serve``: the web service (REST API under /api/v1, the page at /).

The service itself lives in the ``app`` package beside ``nlpsf`` (a source checkout or the
container); uvicorn and the app are imported only when the command runs, so ``import nlpsf.cli``
stays light.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import socket
import sys
from pathlib import Path

from .cli import register


def _configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default=None, help="address (default $NLPSF_HOST, else 127.0.0.1; 0.0.0.0 for all)")
    parser.add_argument("--port", type=int, default=None, help="port (default $NLPSF_PORT, else 8000)")
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="HTTP worker processes (default: $NLPSF_WORKERS, else one per core up to 8)",
    )
    parser.add_argument("--access-log", action="store_true", help="log every request (off by default: it costs throughput)")
    parser.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"))


def app_directory() -> str:
    """The folder holding the ``app`` package: beside this package (a checkout), else the cwd."""
    beside = Path(__file__).resolve().parent.parent
    if (beside / "app" / "main.py").is_file():
        return str(beside)
    return os.getcwd()


@register("serve", _configure, "start the web service: REST API under /api/v1, docs at /docs, the page at /")
def _serve(args: argparse.Namespace) -> int:
    from .checks import check_integer

    directory = app_directory()
    if directory not in sys.path:
        sys.path.insert(0, directory)
    from pydantic import ValidationError

    from app.settings import Settings

    try:
        settings = Settings()  # the environment's NLPSF_* variables, checked once, here
    except ValidationError as error:
        problems = "; ".join(f"NLPSF_{'_'.join(map(str, e['loc'])).upper()}: {e['msg']}" for e in error.errors())
        print(f"nlpsf serve: invalid setting: {problems}", file=sys.stderr)
        return 2
    host = args.host if args.host is not None else settings.host
    port = check_integer(args.port if args.port is not None else settings.port, "port", 0, 65535)
    workers = check_integer(args.workers if args.workers is not None else settings.http_workers, "workers", 1, 64)
    # Child processes (HTTP workers, the simulation forkserver) must find the app package too.
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (directory, os.environ.get("PYTHONPATH", "")) if p)
    options = {"access_log": args.access_log, "log_level": args.log_level}
    if workers == 1:
        import uvicorn

        uvicorn.run("app.main:app", host=host, port=port, app_dir=directory, timeout_graceful_shutdown=10, **options)
        return 0
    return _supervise(workers, host, port, directory, options)


def _listening_socket(host: str, port: int) -> socket.socket:
    """A socket of its own for each worker, all on one port: with SO_REUSEPORT the kernel spreads
    connections over the workers. (One shared socket lets whichever worker wakes first accept a
    whole burst of connections, leaving the other idle: half the throughput, seen in the benchmark.)"""
    family, kind, protocol, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
    sock = socket.socket(family, kind, protocol)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    sock.bind(address)
    sock.set_inheritable(True)
    return sock


def _worker(host: str, port: int, directory: str, options: dict) -> None:
    import ctypes

    import uvicorn

    # Die with the supervisor even if it is killed outright (Linux: PR_SET_PDEATHSIG = 1).
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
    if directory not in sys.path:
        sys.path.insert(0, directory)
    config = uvicorn.Config("app.main:app", host=host, port=port, timeout_graceful_shutdown=10, **options)
    uvicorn.Server(config).run(sockets=[_listening_socket(host, port)])


def _supervise(workers: int, host: str, port: int, directory: str, options: dict) -> int:
    """Run ``workers`` HTTP worker processes, restart any that dies, stop them all on SIGTERM/SIGINT."""
    import multiprocessing
    import time

    if not hasattr(socket, "SO_REUSEPORT"):
        import uvicorn

        uvicorn.run("app.main:app", host=host, port=port, workers=workers, app_dir=directory, **options)
        return 0
    _listening_socket(host, port).close()  # fail here, once, if the port is taken
    context = multiprocessing.get_context("spawn")
    stopping, status = False, 0

    started: dict[int, float] = {}

    def start():
        process = context.Process(target=_worker, args=(host, port, directory, options), name="nlpsf-http")
        process.start()
        started[process.pid or 0] = time.monotonic()
        return process

    def stop(signum, frame):
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    processes = [start() for _ in range(workers)]
    print(f"nlpsf serve: {workers} HTTP workers on http://{host}:{port}", file=sys.stderr, flush=True)
    while not stopping:
        time.sleep(0.2)
        for index, process in enumerate(processes):
            if not process.is_alive() and not stopping:
                # Killed by a signal (kill -9, the OOM killer) is not a configuration error: restart it.
                if (process.exitcode or 0) > 0 and time.monotonic() - started.get(process.pid or 0, 0.0) < 10:
                    # Dying at start is a configuration error; restarting would only repeat it.
                    print(f"nlpsf serve: worker {process.pid} failed at start ({process.exitcode}); stopping", file=sys.stderr)
                    stopping, status = True, 1
                    break
                print(f"nlpsf serve: worker {process.pid} exited ({process.exitcode}); starting another", file=sys.stderr)
                processes[index] = start()
    for process in processes:
        if process.is_alive():
            process.terminate()
    for process in processes:
        process.join(30)
        if process.is_alive():
            process.kill()
    return status
