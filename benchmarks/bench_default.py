"""CPU per answer of the Roman default against the paper's tables, in one process, one BLAS thread.

The same 120 random requests (``scripts/stored_answers.py``'s: band, SCA, metric, mode, two of
precision / tolerance / magnitude) are answered three ways -- the paper's tables (``scene:
"paper"``), the Roman default without a position (the most demanding of the SCA's field-grid nodes)
and with one -- through the service's path (``SolveRequest.from_json``, ``answer``), after the
process has answered 120 other random requests of each kind (tables, grid and caches warm; the
timed requests themselves are new). Then a 1,000-row batch of default requests
(``batch.answer_from_tables``, as ``POST /solve/batch`` answers each row) and the page's limits
(``GET /page/limits``) at 20 conditions. Times are CPU (``time.process_time``); ratios are of one run.

Targets (issue 25): the default with and without a position at most 2x the paper-table answer; the
1,000-row default batch under 2 s of CPU.

Usage: python benchmarks/bench_default.py
"""

from __future__ import annotations

import os

for _name in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_name] = "1"

import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "scripts"))

from stored_answers import base_requests  # noqa: E402

KINDS = ("paper", "default", "default at a position")
TARGET_RATIO, TARGET_BATCH_S = 2.0, 2.0


def bodies(requests: list[dict], kind: str) -> list[dict]:
    out = []
    for request in requests:
        body = dict(request)
        position = body.pop("position")
        if kind == "paper":
            body["scene"] = "paper"
        elif kind == "default at a position":
            body["scene"] = {"position": position}
        out.append(body)
    return out


def cpu_per_answer(items: list[dict]) -> tuple[list[float], int]:
    """CPU seconds of each answer (an InputError answered counts: it is the answer), and how many raised."""
    from nlpsf import InputError, SolveRequest, answer

    times, refused = [], 0
    for body in items:
        start = time.process_time()
        try:
            answer(SolveRequest.from_json(body))
        except InputError:
            refused += 1
        times.append(time.process_time() - start)
    return times, refused


def batch_cpu(rows: int = 1000) -> tuple[float, int]:
    """CPU seconds of a batch of ``rows`` default requests (the 120 and more, without and with a position)."""
    from nlpsf import InputError, SolveRequest
    from nlpsf.solve import batch

    requests = base_requests(seed=31, count=rows // 2)
    items = bodies(requests, "default") + bodies(requests, "default at a position")
    start, failed = time.process_time(), 0
    for body in items:
        try:
            batch.answer_from_tables(SolveRequest.from_json(body))
        except InputError:
            failed += 1
    return time.process_time() - start, failed


def limits_cpu(count: int = 20) -> float:
    """CPU seconds per limits answer of the page (the calculator's brightest answered magnitude)."""
    from nlpsf.web import page_api

    requests = base_requests(seed=41, count=count)
    start = time.process_time()
    for r in requests:
        page_api.limits(r["band"], r["sca"], r["metric"], r["mode"], 168.1, 5e-7, 1.1e5)
    return (time.process_time() - start) / count


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    requests = base_requests()
    warm = base_requests(seed=99)
    for kind in KINDS:
        cpu_per_answer(bodies(warm, kind))
    results = {kind: cpu_per_answer(bodies(requests, kind)) for kind in KINDS}
    print(f"CPU per answer, {len(requests)} random requests, one process, one BLAS thread (ms):")
    paper = statistics.fmean(results["paper"][0])
    for kind, (times, refused) in results.items():
        mean = statistics.fmean(times)
        print(
            f"  {kind:<24} mean {1e3 * mean:7.3f}  median {1e3 * statistics.median(times):7.3f}  "
            f"max {1e3 * max(times):7.2f}   {mean / paper:6.2f}x the paper's   ({refused} refused)"
        )
    for kind in KINDS[1:]:
        ratio = statistics.fmean(results[kind][0]) / paper
        print(f"RATIO {kind} / paper = {ratio:.2f}x ({'meets' if ratio <= TARGET_RATIO else 'MISSES'} <= {TARGET_RATIO:g}x)")
    seconds, failed = batch_cpu()
    verdict = "meets" if seconds < TARGET_BATCH_S else "MISSES"
    print(f"1,000-row default batch: {seconds:.2f} s CPU ({failed} rows refused; {verdict} < {TARGET_BATCH_S:g} s)")
    print(f"page limits: {1e3 * limits_cpu():.1f} ms CPU per answer")


if __name__ == "__main__":
    main()
