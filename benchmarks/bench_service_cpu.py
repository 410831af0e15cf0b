"""CPU per POST /api/v1/solve through the whole service app, in one process, no HTTP: the Roman
default's mix against the paper tables' solves (the bodies of ``bench_service.py --only-throughput``).

The load test (``bench_service.py``) measures requests per second over loopback on a machine whose
other load moves its rounds by 2x and more; this measures what those figures are made of, the CPU
of one request through every middleware, the endpoint and the library, with the two kinds timed in
turn in the same process (``time.process_time``, one BLAS thread). Every default request is a body
not sent before (the service keeps answers by request; a repeated one is a look-up), the inline
budget is the whole share (as in the load test's throughput phase), and each kind's figure is its
fastest of ``--rounds`` rounds. The throughput ratio it states is paper CPU / default CPU: what the
load test's ratio tends to where the HTTP server's own share of a request is small.

Usage: python benchmarks/bench_service_cpu.py [--rounds 5] [--requests 400]
"""

from __future__ import annotations

import os

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_name] = "1"

import argparse  # noqa: E402
import asyncio  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_service import BODIES, THROUGHPUT_SHARES, default_bodies  # noqa: E402

#: The load test's target for the default mix's throughput against the paper's (issue 25).
TARGET_RATIO = 0.8


async def post(app, body: bytes) -> int:
    """One POST /api/v1/solve through the ASGI app; its status."""
    scope = {
        "type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST", "scheme": "http",
        "path": "/api/v1/solve", "raw_path": b"/api/v1/solve", "query_string": b"", "root_path": "",
        "headers": [(b"host", b"bench"), (b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())],
        "client": ("127.0.0.1", 50000), "server": ("127.0.0.1", 80), "state": {},
    }  # fmt: skip
    sent, status = [False], []

    async def receive():
        if not sent[0]:
            sent[0] = True
            return {"type": "http.request", "body": body, "more_body": False}
        await asyncio.sleep(3600)  # the client stays connected

    async def send(message):
        if message["type"] == "http.response.start":
            status.append(message["status"])

    await app(scope, receive, send)
    return status[0]


async def measure(app, rounds: int, count: int) -> tuple[float, float]:
    """(paper, default) fastest CPU seconds per request over ``rounds`` rounds of ``count`` each."""
    paper = [json.dumps(b).encode() for b in BODIES]
    roman = [json.dumps(b).encode() for b in default_bodies(count * (rounds + 1), seed=3)]
    for body in paper * 4 + roman[:count]:  # warm: tables, grid, caches
        await post(app, body)
    times: dict[str, list[float]] = {"paper": [], "default": []}
    for k in range(1, rounds + 1):
        for kind, bodies in (("paper", paper * (count // len(paper))), ("default", roman[k * count : (k + 1) * count])):
            start = time.process_time()
            for body in bodies:
                status = await post(app, body)
                if status != 200:
                    raise SystemExit(f"a {kind} solve answered {status}: {body[:200]!r}")
            times[kind].append((time.process_time() - start) / len(bodies))
    return min(times["paper"]), min(times["default"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--requests", type=int, default=400, help="requests of each kind per round (default 400)")
    args = parser.parse_args()
    os.environ.update(THROUGHPUT_SHARES)
    from nlpsf.web.main import create_app
    from nlpsf.web.settings import Settings
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    app = create_app(Settings(db_path=str(Path(tempfile.mkdtemp(prefix="nlpsf-bench-")) / "jobs.sqlite3")))

    async def run() -> tuple[float, float]:
        async with app.router.lifespan_context(app):
            return await measure(app, args.rounds, args.requests)

    paper, default = asyncio.run(run())
    print(f"CPU per POST /api/v1/solve through the app, one process, fastest of {args.rounds} rounds of {args.requests}:")
    print(f"  paper-table solves  {1e3 * paper:.3f} ms")
    print(f"  default mix         {1e3 * default:.3f} ms (every body new)")
    verdict = "meets" if paper / default >= TARGET_RATIO else "MISSES"
    ratio = paper / default
    print(f"RATIO default mix / paper-table throughput, CPU in one process: {ratio:.2f}x ({verdict} >= {TARGET_RATIO:g}x)")


if __name__ == "__main__":
    main()
