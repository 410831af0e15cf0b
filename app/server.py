"""Running the web service: uvicorn HTTP workers under a small supervisor that watches them.

``nlpsf serve`` (``nlpsf.cli.serve``) calls :func:`serve`; uvicorn and the app are imported only
then, so the command line stays light.

The workers accept from one listening socket the supervisor opens (``shared_socket``, the default: a
stopped worker then takes no new connections; or, with it off, one SO_REUSEPORT socket per worker,
the kernel spreading connections over them), and each has a heartbeat slot (``liveness``) its event
loop writes ten times a second. The supervisor checks every worker five times a second: one that
exited is started again; one silent for ``heartbeat_timeout_s`` (stopped with SIGSTOP, or its loop
blocked) is killed with SIGKILL -- which also closes its own socket, if it has one -- and replaced.
Meanwhile ``/health``, answered by any other worker, reports it as stalled. (gunicorn's arbiter does
the same with heartbeat files; measured against this supervisor in benchmarks/bench_liveness.py:
see docs/service.md for why this one is kept.)
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import sys
import time
from dataclasses import dataclass

#: The ASGI application, as uvicorn imports it in each worker process.
APP = "nlpsf.web.main:app"
#: How long a newly started worker may take to load the tables and start beating, s.
START_GRACE_S = 60.0
#: How often the supervisor looks at its workers, s.
CHECK_S = 0.2


@dataclass(frozen=True)
class ServeOptions:
    """What every worker runs with (from the service settings; see ``Settings``)."""

    access_log: bool = False
    log_level: str = "info"
    heartbeat_timeout_s: float = 3.0
    header_timeout_s: float = 10.0
    keep_alive_s: float = 5.0
    max_connections: int = 1000
    #: one listening socket for all workers (True), or one per worker with SO_REUSEPORT (False)
    shared_socket: bool = True
    #: trusted reverse proxies (the setting forwarded_allow_ips): only their X-Forwarded-For is read;
    #: empty, none is (uvicorn's own default would trust 127.0.0.1)
    forwarded_allow_ips: tuple[str, ...] = ()


def serve(host: str, port: int, workers: int, options: ServeOptions | None = None) -> int:
    """Serve until SIGTERM/SIGINT; returns the exit status."""
    options = options or ServeOptions()
    if not hasattr(socket, "SO_REUSEPORT"):  # not Linux/BSD: uvicorn's own process manager, unwatched
        import uvicorn

        uvicorn.run(APP, host=host, port=port, workers=workers, **_uvicorn_options(options))
        return 0
    return _supervise(workers, host, port, options)


def _uvicorn_options(options: ServeOptions) -> dict:
    from .protocol import GuardedHttpTools

    return {
        "access_log": options.access_log,
        "log_level": options.log_level,
        "timeout_graceful_shutdown": 10,
        "server_header": False,  # no "server: uvicorn" banner
        "timeout_keep_alive": options.keep_alive_s,
        # Open connections (and requests in progress) per worker; beyond it uvicorn answers 503.
        "limit_concurrency": options.max_connections,
        "http": GuardedHttpTools,
        # The client is the socket's peer unless that peer is a proxy the operator named: uvicorn's
        # defaults would read X-Forwarded-For from 127.0.0.1, so any local client could claim to be
        # another and take a fresh share of the queue and of the inline CPU.
        "proxy_headers": bool(options.forwarded_allow_ips),
        "forwarded_allow_ips": list(options.forwarded_allow_ips) or None,
    }


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


def _worker(host: str, port: int, options: ServeOptions, beats, index: int, shared: socket.socket | None) -> None:
    import ctypes

    import uvicorn

    from . import liveness

    # Die with the supervisor even if it is killed outright (Linux: PR_SET_PDEATHSIG = 1).
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
    liveness.install(beats, index, options.heartbeat_timeout_s)

    class Server(uvicorn.Server):
        async def on_tick(self, counter: int) -> bool:
            liveness.beat()  # from the event loop itself: a blocked loop stops beating
            return await super().on_tick(counter)

    config = uvicorn.Config(APP, host=host, port=port, **_uvicorn_options(options))
    config.header_timeout_s = options.header_timeout_s  # read by protocol.GuardedHttpTools
    Server(config).run(sockets=[shared if shared is not None else _listening_socket(host, port)])


def _supervise(workers: int, host: str, port: int, options: ServeOptions) -> int:
    """Run ``workers`` HTTP worker processes; restart any that dies, replace any that stalls, stop
    them all on SIGTERM/SIGINT."""
    import multiprocessing

    first = _listening_socket(host, port)  # fail here, once, if the port is taken
    shared = first if options.shared_socket else None
    if shared is not None:
        shared.listen(2048)
    else:
        first.close()
    context = multiprocessing.get_context("spawn")
    beats = context.Array("d", workers, lock=False)
    stopping, status = False, 0
    started: dict[int, float] = {}

    def start(index: int):
        beats[index] = time.monotonic() + START_GRACE_S  # silent until it has loaded the tables
        process = context.Process(target=_worker, args=(host, port, options, beats, index, shared), name=f"nlpsf-http-{index}")
        process.start()
        started[process.pid or 0] = time.monotonic()
        return process

    def stop(signum, frame):
        nonlocal stopping
        stopping = True

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    processes = [start(index) for index in range(workers)]
    print(f"nlpsf serve: {workers} HTTP workers on http://{host}:{port}", file=sys.stderr, flush=True)
    while not stopping:
        time.sleep(CHECK_S)
        now = time.monotonic()
        for index, process in enumerate(processes):
            if stopping:
                break
            if not process.is_alive():
                # Killed by a signal (kill -9, the OOM killer) is not a configuration error: restart it.
                if (process.exitcode or 0) > 0 and now - started.get(process.pid or 0, 0.0) < 10:
                    # Dying at start is a configuration error; restarting would only repeat it.
                    print(f"nlpsf serve: worker {process.pid} failed at start ({process.exitcode}); stopping", file=sys.stderr)
                    stopping, status = True, 1
                    break
                print(f"nlpsf serve: worker {process.pid} exited ({process.exitcode}); starting another", file=sys.stderr)
                processes[index] = start(index)
            elif now - beats[index] > options.heartbeat_timeout_s:
                silent = now - beats[index]
                print(
                    f"nlpsf serve: worker {process.pid} silent for {silent:.1f} s (heartbeat_timeout_s "
                    f"{options.heartbeat_timeout_s:g}); killing it and starting another",
                    file=sys.stderr,
                    flush=True,
                )
                # SIGKILL works on a stopped process too; its socket closes with it.
                with contextlib.suppress(ProcessLookupError):
                    os.kill(process.pid or 0, signal.SIGKILL)
                process.join(5)
                processes[index] = start(index)
    for process in processes:
        if process.is_alive():
            process.terminate()
            with contextlib.suppress(ProcessLookupError):
                os.kill(process.pid or 0, signal.SIGCONT)  # a stopped worker must run to see its SIGTERM
    for process in processes:
        process.join(30)
        if process.is_alive():
            process.kill()
    return status
