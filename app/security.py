"""What every request passes before the API sees it: a body size limit (413 before any parsing), an
optional API key, and the security headers every response carries. Plain ASGI middleware, so a
refused request costs no JSON parsing and no thread.

The Host check is Starlette's ``TrustedHostMiddleware`` (see ``main.create_app``).
"""

from __future__ import annotations

import hashlib
import hmac
import json
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

#: The page and /docs load only their own files (JS libraries vendored); nothing may frame them.
#: Inline styles stay allowed: uPlot and Swagger UI set element styles.
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
    "connect-src 'self'; font-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
SECURITY_HEADERS = [
    (b"content-security-policy", CONTENT_SECURITY_POLICY.encode()),
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
    (b"cross-origin-opener-policy", b"same-origin"),
    (b"permissions-policy", b"camera=(), microphone=(), geolocation=()"),
]


async def _problem(send: Send, status: int, message: str, limit: str | None = None, headers: list | None = None) -> None:
    from .errors import PROBLEM_MEDIA_TYPE, problem_body

    body = json.dumps(problem_body(status, message, None, limit)).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", PROBLEM_MEDIA_TYPE.encode()),
                (b"content-length", str(len(body)).encode()),
                *(headers or []),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class SecurityHeaders:
    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                present = {name.lower() for name, _ in message.get("headers", [])}
                message["headers"] = [*message.get("headers", []), *(h for h in SECURITY_HEADERS if h[0] not in present)]
            await send(message)

        await self.app(scope, receive, with_headers)


class BodyLimit:
    """Refuse a body over ``max_bytes`` with 413, before the application reads or parses any of it.

    A declared Content-Length over the limit is refused at once; a chunked body is read up to the
    limit (small by default) and refused as soon as it passes it."""

    def __init__(self, app: ASGIApp, max_bytes: int):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS"):
            await self.app(scope, receive, send)
            return
        message = f"the request body is larger than {self.max_bytes:,} bytes (the setting max_body_bytes)"
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    await _problem(send, 400, "the Content-Length header is not a number")
                    return
                if declared > self.max_bytes:
                    await _problem(send, 413, message, "max_body_bytes", [(b"connection", b"close")])
                    return
        chunks: list[bytes] = []
        size = 0
        while True:
            event = await receive()
            if event["type"] != "http.request":
                break  # the client went away; let the application see it
            chunk = event.get("body", b"")
            size += len(chunk)
            if size > self.max_bytes:
                await _problem(send, 413, message, "max_body_bytes", [(b"connection", b"close")])
                return
            chunks.append(chunk)
            if not event.get("more_body", False):
                break
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": b"".join(chunks), "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


def client_of(key: str) -> str:
    """The identity a job listing groups by: a hash of the API key (never the key itself)."""
    return hashlib.sha256(key.encode()).hexdigest()[:24]


class ApiKey:
    """With keys configured, /api/v1 (but /api/v1/health, for probes) needs one of them, as
    ``Authorization: Bearer <key>`` or ``X-API-Key: <key>``; the caller's identity is then its key's hash."""

    def __init__(self, app: ASGIApp, keys: list[str]):
        self.app = app
        self.keys = [k.encode() for k in keys]

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        if scope["type"] != "http" or not path.startswith("/api/") or path == "/api/v1/health":
            await self.app(scope, receive, send)
            return
        offered = b""
        for name, value in scope.get("headers", []):
            if name == b"x-api-key":
                offered = value.strip()
            elif name == b"authorization" and value[:7].lower() == b"bearer ":
                offered = value[7:].strip()
        match = next((k for k in self.keys if hmac.compare_digest(k, offered)), None) if offered else None
        if match is None:
            await _problem(send, 401, "an API key is required (Authorization: Bearer <key>, or X-API-Key)", None,
                           [(b"www-authenticate", b"Bearer")])  # fmt: skip
            return
        scope.setdefault("state", {})["client"] = client_of(match.decode())
        await self.app(scope, receive, send)
