"""``nlpsf serve``: the web service (REST API under /api/v1, the page at /).

The service itself lives in the ``app`` package beside ``nlpsf`` (a source checkout or the
container); uvicorn and the app are imported only when the command runs, so ``import nlpsf.cli``
stays light.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from .cli import register


def _configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1; 0.0.0.0 for all)")
    parser.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    parser.add_argument(
        "--workers",
        type=int,
        default=None,
        help="HTTP worker processes (default: $NLPSF_WORKERS or 1); simulations run in $NLPSF_JOB_WORKERS more",
    )
    parser.add_argument("--access-log", action="store_true", help="log every request (off by default: it costs throughput)")
    parser.add_argument("--log-level", default="info", choices=("critical", "error", "warning", "info", "debug"))


def app_directory() -> str:
    """The folder holding the ``app`` package: $NLPSF_APP_DIR, else beside this package, else the cwd."""
    if os.environ.get("NLPSF_APP_DIR"):
        return os.environ["NLPSF_APP_DIR"]
    beside = Path(__file__).resolve().parent.parent
    if (beside / "app" / "main.py").is_file():
        return str(beside)
    return os.getcwd()


@register("serve", _configure, "start the web service: REST API under /api/v1, docs at /docs, the page at /")
def _serve(args: argparse.Namespace) -> int:
    from .checks import InputError, check_integer

    check_integer(args.port, "port", 0, 65535)
    raw = args.workers if args.workers is not None else os.environ.get("NLPSF_WORKERS") or 1
    try:
        number = int(raw)
    except ValueError:
        raise InputError("workers", f"must be an integer, got {raw!r}") from None
    workers = check_integer(number, "workers", 1, 64)
    import uvicorn

    directory = app_directory()
    if directory not in sys.path:
        sys.path.insert(0, directory)
    # Child processes (uvicorn workers, the simulation forkserver) must find the app package too.
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (directory, os.environ.get("PYTHONPATH", "")) if p)
    uvicorn.run(
        "app.main:app",
        host=args.host,
        port=args.port,
        workers=workers,
        app_dir=directory,
        access_log=args.access_log,
        log_level=args.log_level,
        timeout_graceful_shutdown=10,
    )
    return 0
