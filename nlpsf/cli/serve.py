"""``nlpsf serve``: start the web service (REST API under /api/v1, docs at /docs, the page at /)."""

from __future__ import annotations

import argparse
import os


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0 for all interfaces)")
    parser.add_argument("--port", type=int, default=8000, help="TCP port")
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
    from ..checks import InputError, check_integer
    from ..web.server import default_workers, serve

    check_integer(args.port, "port", 0, 65535)
    raw = args.workers if args.workers is not None else os.environ.get("NLPSF_WORKERS") or default_workers()
    try:
        number = int(raw)
    except ValueError:
        raise InputError("workers", f"must be an integer, got {raw!r}") from None
    workers = check_integer(number, "workers", 1, 64)
    return serve(args.host, args.port, workers, access_log=args.access_log, log_level=args.log_level)
