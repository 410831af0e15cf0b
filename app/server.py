"""Running the web service: one uvicorn worker, or several behind a small supervisor.

``nlpsf serve`` (``nlpsf.cli.serve``) calls :func:`serve`; uvicorn and the app are imported only
then, so the command line stays light.
"""

from __future__ import annotations

import contextlib
import signal
import socket
import sys

#: The ASGI application, as uvicorn imports it in each worker process.
APP = "nlpsf.web.main:app"


def serve(host: str, port: int, workers: int, access_log: bool = False, log_level: str = "info") -> int:
    """Serve until SIGTERM/SIGINT; returns the exit status."""
    options = {"access_log": access_log, "log_level": log_level}
    if workers == 1:
        import uvicorn

        uvicorn.run(APP, host=host, port=port, timeout_graceful_shutdown=10, **options)
        return 0
    return _supervise(workers, host, port, options)


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


def _worker(host: str, port: int, options: dict) -> None:
    import ctypes

    import uvicorn

    # Die with the supervisor even if it is killed outright (Linux: PR_SET_PDEATHSIG = 1).
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
    config = uvicorn.Config(APP, host=host, port=port, timeout_graceful_shutdown=10, **options)
    uvicorn.Server(config).run(sockets=[_listening_socket(host, port)])


def _supervise(workers: int, host: str, port: int, options: dict) -> int:
    """Run ``workers`` HTTP worker processes, restart any that dies, stop them all on SIGTERM/SIGINT."""
    import multiprocessing
    import time

    if not hasattr(socket, "SO_REUSEPORT"):
        import uvicorn

        uvicorn.run(APP, host=host, port=port, workers=workers, **options)
        return 0
    _listening_socket(host, port).close()  # fail here, once, if the port is taken
    context = multiprocessing.get_context("spawn")
    stopping, status = False, 0

    started: dict[int, float] = {}

    def start():
        process = context.Process(target=_worker, args=(host, port, options), name="nlpsf-http")
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
