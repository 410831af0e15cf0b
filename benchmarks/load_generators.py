"""The load generators of ``bench_service.py`` (and ``bench_service_cpu.py``'s bodies' runs): ``wrk``
(Debian's package, C, epoll; one thread, a Lua script rotating over the bodies) if it is installed,
else an asyncio client on raw keep-alive sockets in its own process. Both are closed-loop: each
connection sends its next request when the previous answer arrives. Each returns the measurement's
req/s, latency quantiles (ms), requests and errors.
"""

from __future__ import annotations

import asyncio
import json
import multiprocessing
import os
import re
import subprocess
import tempfile
import time

import httpx

# --- wrk -----------------------------------------------------------------------------------------


def wrk_script(bodies: list[dict]) -> str:
    bodies = ",\n".join("  [[" + json.dumps(b) + "]]" for b in bodies)
    return f"""
local bodies = {{
{bodies}
}}
local i = 0
request = function()
  i = i % #bodies + 1
  return wrk.format("POST", "/api/v1/solve", {{["Content-Type"] = "application/json"}}, bodies[i])
end
response = function(status, headers, body)
  if status ~= 200 then io.stderr:write("status " .. status .. ": " .. body .. "\\n") end
end
done = function(summary, latency, requests)
  io.write(string.format("RESULT %d %f %f %f %f %f %d\\n", summary.requests, summary.duration / 1e6,
    latency:percentile(50) / 1000, latency:percentile(90) / 1000, latency:percentile(99) / 1000, latency.max / 1000,
    summary.errors.status + summary.errors.connect + summary.errors.read + summary.errors.write + summary.errors.timeout))
end
"""


def run_wrk(url: str, connections: int, duration: float, bodies: list[dict]) -> dict:
    with tempfile.NamedTemporaryFile("w", suffix=".lua", delete=False) as handle:
        handle.write(wrk_script(bodies))
        script = handle.name
    try:
        output = subprocess.run(
            ["wrk", "-t1", f"-c{connections}", f"-d{int(duration)}s", "--timeout", "5s", "-s", script, url],
            capture_output=True,
            text=True,
            timeout=duration + 30,
            check=True,
        )
    finally:
        os.unlink(script)
    match = re.search(r"RESULT (\d+) (\S+) (\S+) (\S+) (\S+) (\S+) (\d+)", output.stdout)
    if not match:
        raise RuntimeError(f"could not read wrk's output:\n{output.stdout}\n{output.stderr}")
    requests, seconds, p50, p90, p99, worst, errors = match.groups()
    return {
        "requests": int(requests),
        "seconds": float(seconds),
        "rps": int(requests) / float(seconds),
        "p50_ms": float(p50),
        "p90_ms": float(p90),
        "p99_ms": float(p99),
        "max_ms": float(worst),
        "errors": int(errors),
    }


# --- the asyncio fallback ------------------------------------------------------------------------


async def _connection(
    host: str,
    port: int,
    deadline: float,
    latencies: list[float],
    errors: list[int],
    offset: int,
    bodies: list[dict],
    stride: int = 1,
) -> None:
    """One keep-alive connection's closed loop: bodies ``offset``, ``offset + 1``, ... (``stride`` > 1:
    ``offset``, ``offset + stride``, ...: the connections send different bodies, none twice while the
    list lasts)."""
    try:
        reader, writer = await asyncio.open_connection(host, port)
    except OSError:
        errors.append(1)  # refused: nothing listening yet
        return
    payloads = [
        (
            f"POST /api/v1/solve HTTP/1.1\r\nHost: {host}\r\nContent-Type: application/json\r\n"
            f"Content-Length: {len(json.dumps(b))}\r\n\r\n{json.dumps(b)}"
        ).encode()
        for b in (bodies if stride == 1 else bodies[offset::stride])
    ]
    i = offset if stride == 1 else 0
    try:
        while time.perf_counter() < deadline:
            start = time.perf_counter()
            writer.write(payloads[i % len(payloads)])
            i += 1
            head = await reader.readuntil(b"\r\n\r\n")
            length = int(re.search(rb"content-length: (\d+)", head.lower()).group(1))
            await reader.readexactly(length)
            latencies.append(time.perf_counter() - start)
            if not head.startswith(b"HTTP/1.1 200"):
                errors.append(1)
    except (OSError, asyncio.IncompleteReadError):
        errors.append(1)
    writer.close()


def _python_child(host: str, port: int, connections: int, duration: float, queue, bodies: list[dict], stride: int) -> None:
    latencies: list[float] = []
    errors: list[int] = []

    async def main() -> float:
        start = time.perf_counter()
        deadline = start + duration
        await asyncio.gather(
            *(_connection(host, port, deadline, latencies, errors, k, bodies, stride) for k in range(connections))
        )
        return time.perf_counter() - start

    seconds = asyncio.run(main())
    queue.put((latencies, seconds, len(errors)))


def run_python(url: str, connections: int, duration: float, bodies: list[dict], distinct: bool = False) -> dict:
    parsed = httpx.URL(url)
    queue = multiprocessing.get_context("spawn").Queue()
    child = multiprocessing.get_context("spawn").Process(
        target=_python_child,
        args=(parsed.host, parsed.port, connections, duration, queue, bodies, connections if distinct else 1),
    )
    child.start()
    latencies, seconds, errors = queue.get(timeout=duration + 60)
    child.join()
    return summary(latencies, seconds, errors)


def summary(latencies: list[float], seconds: float, errors: int) -> dict:
    """A measurement's figures from its requests' latencies (s): req/s, quantiles and the slowest in ms
    (NaN where no request was answered), the requests and the errors."""
    latencies = sorted(latencies)

    def pick(q: float) -> float:
        return 1000 * latencies[min(len(latencies) - 1, int(q * len(latencies)))] if latencies else float("nan")

    return {
        "requests": len(latencies),
        "seconds": seconds,
        "rps": len(latencies) / seconds,
        "p50_ms": pick(0.50),
        "p90_ms": pick(0.90),
        "p99_ms": pick(0.99),
        "max_ms": 1000 * latencies[-1] if latencies else float("nan"),
        "errors": errors,
    }
