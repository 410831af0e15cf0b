"""A real ``nlpsf serve`` (two HTTP workers, 127.0.0.1 only) under stalls and slow clients (issue 19, items 3-5).

- a stopped (SIGSTOP) worker is reported by /health while it lasts, killed and replaced within
  seconds, and afterwards every request is answered;
- a connection that sends nothing, headers that trickle, a body that never completes and an idle
  kept-alive connection are each closed (with a 408 where a request was begun) within their bound;
- uvicorn's own answers carry the service's headers and no server banner; bodies on GET and
  duplicate JSON keys are refused.

Bounded: about 60 requests and a dozen raw connections, all on loopback.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import time

import httpx
import pytest

from ..servers import free_port, http_workers, start_server, wait_for

pytestmark = pytest.mark.slow

HEARTBEAT_S = 3.0
HEADER_S = 1.0
BODY_S = 1.0
KEEP_ALIVE_S = 1.0
MAX_CONNECTIONS = 8
ENV = {
    "NLPSF_MAX_CONNECTIONS": str(MAX_CONNECTIONS),
    "NLPSF_WORKERS": "2",
    "NLPSF_HEARTBEAT_TIMEOUT_S": str(HEARTBEAT_S),
    "NLPSF_HEADER_TIMEOUT_S": str(HEADER_S),
    "NLPSF_BODY_TIMEOUT_S": str(BODY_S),
    "NLPSF_KEEP_ALIVE_S": str(KEEP_ALIVE_S),
}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    port = free_port()
    process = start_server(tmp_path_factory.mktemp("db") / "jobs.sqlite3", port, ENV)
    wait_for(lambda: len(http_workers(process.pid)) == 2, timeout=30)
    try:
        yield process, port
    finally:
        for pid in http_workers(process.pid):
            with_signal(pid, signal.SIGCONT)
        process.send_signal(signal.SIGTERM)
        process.wait(30)


def with_signal(pid: int, sig: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, sig)


def health(port: int, timeout: float = 3.0) -> dict | None:
    try:
        response = httpx.get(f"http://127.0.0.1:{port}/api/v1/health", timeout=timeout, headers={"connection": "close"})
        return response.json()
    except httpx.HTTPError:
        return None


def raw(port: int, data: bytes = b"", timeout: float = 10.0) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=timeout)
    if data:
        sock.sendall(data)
    return sock


def read_all(sock: socket.socket) -> tuple[bytes, float]:
    """Everything the server sends until it closes the connection, and when it closed (s from now)."""
    begin, chunks = time.monotonic(), []
    while chunk := sock.recv(65536):
        chunks.append(chunk)
    return b"".join(chunks), time.monotonic() - begin


def test_a_worker_that_has_not_beaten_yet_is_starting_not_responding():
    # The supervisor gives a new worker's slot the end of its start grace (a time to come); until its
    # loop first beats it neither responds nor is stalled. Slots: starting, stalled 2 s, beating.
    from nlpsf.web import liveness

    saved = liveness.BEATS, liveness.INDEX, liveness.TIMEOUT_S
    now = time.monotonic()
    try:
        liveness.install([now + 60.0, now - 2.0, now], 2, HEARTBEAT_S)
        report = liveness.report()
    finally:
        liveness.BEATS, liveness.INDEX, liveness.TIMEOUT_S = saved
    assert (report["workers"], report["responding"], report["starting"]) == (3, 1, 1)
    assert [s["worker"] for s in report["stalled"]] == [1]


def stalled_report(port: int, seen: list) -> dict | None:
    """/health's answer when it reports a stalled worker, else None (``seen`` keeps every answer)."""
    answer = health(port, timeout=1.0)  # one shared socket: no probe waits on the stopped worker
    seen.append(None if answer is None else answer["http_workers"])
    return answer if answer and answer["http_workers"]["stalled"] else None


def process_state(pid: int) -> str:
    with contextlib.suppress(OSError), open(f"/proc/{pid}/stat", "rb") as handle:
        return handle.read().rsplit(b")", 1)[1].split()[0].decode()
    return "gone"


def test_a_stopped_worker_is_reported_replaced_and_stops_taking_connections(server):
    process, port = server
    # Both workers beating (one still loading its tables is "starting": stopped then, it would be
    # neither reported nor killed until its start grace ends).
    wait_for(lambda: (h := health(port)) and h["http_workers"]["responding"] == 2, timeout=60)
    victim = http_workers(process.pid)[0]
    # /health from the other worker says so while it lasts: from 1 s of silence until the supervisor
    # kills it at HEARTBEAT_S. The supervisor is held meanwhile (SIGSTOP; its workers run on), so the
    # report is an event this test waits for, not a race against the kill: on a loaded machine a
    # probe (a new client and connection, ~20 ms of CPU) can take a good part of that 2 s window.
    os.kill(process.pid, signal.SIGSTOP)
    try:
        os.kill(victim, signal.SIGSTOP)
        stopped = time.monotonic()
        seen: list = []
        try:
            report = wait_for(lambda: stalled_report(port, seen), timeout=30)
        except AssertionError:
            states = {pid: process_state(pid) for pid in [process.pid, *http_workers(process.pid)]}
            answers = f"{seen[:3]} ... {seen[-3:]}"
            raise AssertionError(f"no stall reported; victim {victim}, states {states}, answers {answers}") from None
        held = time.monotonic() - stopped
    finally:
        os.kill(process.pid, signal.SIGCONT)
    assert report["status"] == "degraded"
    # The server's own account: a worker is stalled once silent for more than 1 s, and the victim was.
    assert all(s["silent_s"] >= 1.0 for s in report["http_workers"]["stalled"]), report
    assert victim in http_workers(process.pid), "the stopped worker was killed while the supervisor was held"
    # Released, the supervisor kills it once silent for HEARTBEAT_S (at once if it already was).
    wait_for(lambda: victim not in http_workers(process.pid), timeout=HEARTBEAT_S + 10)
    replaced = time.monotonic() - stopped
    assert replaced < max(held, HEARTBEAT_S) + 2.0, (replaced, held)
    # Its socket is gone with it: from the moment the replacement is up, every request is answered.
    wait_for(
        lambda: len(http_workers(process.pid)) == 2 and (h := health(port)) and h["http_workers"]["responding"] == 2, timeout=60
    )
    answers = [health(port, timeout=3.0) for _ in range(30)]
    assert all(a is not None and a["status"] == "ok" for a in answers)
    print(f"stopped worker: /health said so after {held:.1f} s, replaced after {replaced:.1f} s")


def test_a_connection_that_sends_nothing_is_closed(server):
    _, port = server
    data, took = read_all(raw(port))
    assert took < HEADER_S + 1.5
    assert data.startswith(b"HTTP/1.1 408")


def test_headers_trickling_a_byte_at_a_time_are_cut_off(server):
    _, port = server
    sock = raw(port)
    begin = time.monotonic()
    request = b"GET /api/v1/health HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"a" * 100
    try:
        for byte in request:
            sock.sendall(bytes([byte]))
            time.sleep(0.1)
            if time.monotonic() - begin > HEADER_S + 3:
                break
    except OSError:
        pass  # closed under us: what we want
    data, _ = read_all(sock)
    assert time.monotonic() - begin < HEADER_S + 3
    assert data.startswith(b"HTTP/1.1 408")


def test_a_body_that_never_completes_gets_408(server):
    _, port = server
    head = b"POST /api/v1/solve HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 60000\r\n\r\n"
    data, took = read_all(raw(port, head + b'{"band": "H'))
    assert took < BODY_S + 1.5
    assert data.startswith(b"HTTP/1.1 408")
    assert b"body_timeout_s" in data


def test_an_idle_kept_alive_connection_is_closed(server):
    _, port = server
    sock = raw(port, b"GET /api/v1/health HTTP/1.1\r\nHost: x\r\n\r\n")
    data, took = read_all(sock)
    assert data.startswith(b"HTTP/1.1 200")
    assert took < KEEP_ALIVE_S + 1.5


def test_uvicorns_own_answers_carry_the_service_headers(server):
    _, port = server
    data, _ = read_all(raw(port, b"NOT HTTP AT ALL\r\n\r\n"))
    head = data.split(b"\r\n\r\n", 1)[0].lower()
    assert head.startswith(b"http/1.1 400")
    assert b"x-content-type-options: nosniff" in head and b"content-security-policy" in head
    assert b"application/problem+json" in head
    response = httpx.get(f"http://127.0.0.1:{port}/api/v1/health")
    assert "server" not in response.headers


def test_get_bodies_and_duplicate_keys_are_refused(server):
    _, port = server
    base = f"http://127.0.0.1:{port}/api/v1"
    assert httpx.request("GET", f"{base}/meta", content=b"x" * 100_000).status_code == 400
    duplicate = b'{"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "tolerance": 1e-2}'
    response = httpx.post(f"{base}/solve", content=duplicate, headers={"content-type": "application/json"})
    assert response.status_code == 422 and "tolerance" in response.json()["detail"]


def test_open_connections_per_worker_are_bounded(server):
    _, port = server
    # 80 silent connections, ten times the limit, shared out by the kernel between the two workers:
    # a worker over its limit answers 503 (until the header deadline closes them).
    silent = [raw(port) for _ in range(80)]
    try:
        answers = [httpx.get(f"http://127.0.0.1:{port}/api/v1/health", timeout=3) for _ in range(5)]
        refused = [r for r in answers if r.status_code == 503]
        assert refused, [r.status_code for r in answers]
        response = refused[0]
        assert response.json()["limit"] == "max_connections" and response.headers["x-frame-options"] == "DENY"
    finally:
        for sock in silent:
            sock.close()
    time.sleep(0.2)
    assert httpx.get(f"http://127.0.0.1:{port}/api/v1/health", timeout=3).status_code == 200
