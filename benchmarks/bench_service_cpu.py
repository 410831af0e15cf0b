"""CPU per POST /api/v1/solve through the whole service app, in one process, no HTTP: the Roman
default's mix against the paper tables' solves (the bodies of ``bench_service.py --only-throughput``).

The load test (``bench_service.py``) measures requests per second over loopback on a machine whose
other load moves its rounds by 2x and more; this measures what those figures are made of, the CPU
of one request through every middleware, the endpoint and the library, with the two kinds timed in
turn in the same process (``time.process_time``, one BLAS thread). Every default request is a body
not sent before (the service keeps answers by request; a repeated one is a look-up), the inline
budget is the whole share (as in the load test's throughput phase), and each kind's figure is its
fastest of ``--rounds`` rounds. The mix's two kinds are also timed apart: a default request at a
position (one field-grid node read) and one without (every node of the SCA), which bounds what the
mix's ratio can reach while the answer states what it does. The throughput ratio it states is paper CPU / default CPU: what the
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


#: What is timed: the paper's solves, the default mix, and the mix's two kinds apart (each its own bodies).
KINDS = ("paper", "default", "default at a position", "default without a position")


async def measure(app, rounds: int, count: int) -> dict[str, float]:
    """Each of :data:`KINDS`' fastest CPU seconds per request over ``rounds`` rounds of ``count``."""
    paper = [json.dumps(b).encode() for b in BODIES]
    roman = [json.dumps(b).encode() for b in default_bodies(count * (rounds + 1), seed=3)]
    # The mix's two kinds apart, from bodies of their own (none of them sent before they are timed).
    apart = default_bodies(2 * count * (rounds + 1), seed=4)
    at = [json.dumps(b).encode() for b in apart if "scene" in b]
    without = [json.dumps(b).encode() for b in apart if "scene" not in b]
    for body in paper * 4 + roman[:count]:  # warm: tables, grid, caches
        await post(app, body)
    times: dict[str, list[float]] = {kind: [] for kind in KINDS}
    for k in range(1, rounds + 1):
        sent = {
            "paper": paper * (count // len(paper)),
            "default": roman[k * count : (k + 1) * count],
            "default at a position": at[k * count : (k + 1) * count],
            "default without a position": without[k * count : (k + 1) * count],
        }
        for kind, bodies in sent.items():
            start = time.process_time()
            for body in bodies:
                status = await post(app, body)
                if status != 200:
                    raise SystemExit(f"a {kind} solve answered {status}: {body[:200]!r}")
            times[kind].append((time.process_time() - start) / len(bodies))
    return {kind: min(found) for kind, found in times.items()}


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

    cpu = asyncio.run(run())
    paper, default = cpu["paper"], cpu["default"]
    print(f"CPU per POST /api/v1/solve through the app, one process, fastest of {args.rounds} rounds of {args.requests}:")
    print(f"  paper-table solves  {1e3 * paper:.3f} ms")
    print(f"  default mix         {1e3 * default:.3f} ms (every body new)")
    for kind in KINDS[2:]:
        print(f"    {kind + ' alone':32s} {1e3 * cpu[kind]:.3f} ms (paper / it: {paper / cpu[kind]:.2f}x)")
    verdict = "meets" if paper / default >= TARGET_RATIO else "MISSES"
    ratio = paper / default
    print(f"RATIO default mix / paper-table throughput, CPU in one process: {ratio:.2f}x ({verdict} >= {TARGET_RATIO:g}x)")
    cheapest = paper / cpu["default at a position"]
    print(
        f"RATIO the mix's cheapest kind alone (at a position: one field-grid node) / paper: {cheapest:.2f}x"
        f" ({'meets' if cheapest >= TARGET_RATIO else 'MISSES'} >= {TARGET_RATIO:g}x)"
    )


if __name__ == "__main__":
    main()
