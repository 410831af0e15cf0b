"""uvicorn's httptools protocol with the limits it lacks: a deadline for a request's headers and
the service's own answer (problem JSON, security headers) where uvicorn answers by itself.

uvicorn times out an idle keep-alive connection only after a first response, so a connection that
sends nothing, or trickles its headers a byte at a time, would stay open for ever. Here every
request's headers must be complete within ``header_timeout_s`` of its first byte (of the connection,
for the first request), else the connection gets a 408 and is closed. The body's deadline is the
ASGI middleware's (``security.BodyLimit``), where the body is read.
"""

from __future__ import annotations

import asyncio
import json

from uvicorn.protocols.http import httptools_impl
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from .errors import PROBLEM_MEDIA_TYPE, problem_body, send_problem
from .headers import SECURITY_HEADERS

#: Default deadline for a request's headers, s (the setting header_timeout_s).
HEADER_TIMEOUT_S = 10.0


def raw_problem(status: int, phrase: str, message: str) -> bytes:
    """A complete HTTP/1.1 problem response with the security headers, for answers written to the
    socket before (or without) the application."""
    body = json.dumps(problem_body(status, message)).encode()
    lines = [
        f"HTTP/1.1 {status} {phrase}".encode(),
        f"content-type: {PROBLEM_MEDIA_TYPE}".encode(),
        f"content-length: {len(body)}".encode(),
        b"connection: close",
        *(name + b": " + value for name, value in SECURITY_HEADERS),
    ]
    return b"\r\n".join(lines) + b"\r\n\r\n" + body


async def _too_many_connections(scope, receive, send) -> None:
    """uvicorn's answer past limit_concurrency (max_connections), as the service's problem JSON with
    its headers; uvicorn's own is plain text without them."""
    message = "this worker has as many open connections as it takes (the setting max_connections); retry shortly"
    headers = [(b"retry-after", b"1"), (b"connection", b"close"), *SECURITY_HEADERS]
    await send_problem(send, 503, message, "max_connections", headers)


# uvicorn calls this module-level name for every request over its limit; there is no option for it.
httptools_impl.service_unavailable = _too_many_connections


class GuardedHttpTools(HttpToolsProtocol):
    _header_timer: asyncio.TimerHandle | None = None

    def _arm(self) -> None:
        if self._header_timer is None:
            timeout = getattr(self.config, "header_timeout_s", HEADER_TIMEOUT_S)
            self._header_timer = self.loop.call_later(timeout, self._headers_too_slow)

    def _disarm(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()  # a connection that never sends a byte is closed too

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._arm()  # the next request on a kept-alive connection

    def on_headers_complete(self) -> None:
        self._disarm()
        super().on_headers_complete()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _headers_too_slow(self) -> None:
        self._header_timer = None
        if self.transport.is_closing():
            return
        if self.cycle is not None and not self.cycle.response_complete:
            return  # a pipelined request behind a response still on its way: that response goes first
        timeout = getattr(self.config, "header_timeout_s", HEADER_TIMEOUT_S)
        message = f"the request's headers did not arrive within {timeout:g} s (the setting header_timeout_s)"
        self.transport.write(raw_problem(408, "Request Timeout", message))
        self.transport.close()

    def send_400_response(self, msg: str) -> None:
        # uvicorn's own plain-text 400 (a request it cannot parse), as the service's problem JSON with
        # the security headers.
        self.transport.write(raw_problem(400, "Bad Request", f"the request is not valid HTTP/1.1: {msg}"))
        self.transport.close()
