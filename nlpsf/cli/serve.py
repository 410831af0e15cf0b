"""``nlpsf serve``: start the web service (REST API under /api/v1, docs at /docs, the page at /).

Where it listens and how many workers it runs come from the service settings (``NLPSF_HOST``,
``NLPSF_PORT``, ``NLPSF_WORKERS``, ...; ``nlpsf.web.settings``, the only reader of the environment);
the options here override them.
"""

from __future__ import annotations

import argparse
import sys


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--host", default=None, help="address to listen on (default $NLPSF_HOST, else 127.0.0.1; 0.0.0.0 for all)"
    )
    parser.add_argument("--port", type=int, default=None, help="TCP port (default $NLPSF_PORT, else 8000)")
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="HTTP worker processes (default: $NLPSF_WORKERS, else one per core up to 8)",
    )
    parser.add_argument("--access-log", action="store_true", help="log every request (off: it costs throughput)")
    parser.add_argument(
        "--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"), help="log level"
    )


def run(args: argparse.Namespace) -> int:
    from pydantic import ValidationError

    from ..checks import check_integer
    from ..web.server import ServeOptions, serve
    from ..web.settings import Settings

    try:
        settings = Settings()  # the NLPSF_* variables, checked once, here, before any worker starts
    except ValidationError as error:
        problems = "; ".join(f"NLPSF_{'_'.join(map(str, e['loc'])).upper()}: {e['msg']}" for e in error.errors())
        print(f"nlpsf serve: invalid setting: {problems}", file=sys.stderr)
        return 2
    host = args.host if args.host is not None else settings.host
    port = check_integer(args.port if args.port is not None else settings.port, "port", 0, 65535)
    workers = check_integer(args.workers if args.workers is not None else settings.http_workers, "workers", 1, 64)
    options = ServeOptions(
        access_log=args.access_log,
        log_level=args.log_level,
        heartbeat_timeout_s=settings.heartbeat_timeout_s,
        header_timeout_s=settings.header_timeout_s,
        keep_alive_s=settings.keep_alive_s,
        max_connections=settings.max_connections,
        shared_socket=settings.shared_socket,
        forwarded_allow_ips=tuple(settings.forwarded_allow_ips),
    )
    return serve(host, port, workers, options)
