"""What every request passes before the API sees it: a body size limit (413 before any parsing), an
optional API key, and the security headers every response carries. Plain ASGI middleware, so a
refused request costs no JSON parsing and no thread.

The Host check is Starlette's ``TrustedHostMiddleware`` (see ``main.create_app``).
"""

from __future__ import annotations

import asyncio
import hashlib
import hmac
import json
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from starlette.concurrency import run_in_threadpool

from .errors import Throttled, send_problem, short
from .headers import SECURITY_HEADERS

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]


class SecurityHeaders:
    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        api = scope.get("path", "").startswith("/api/")

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = [(name, value) for name, value in message.get("headers", []) if name.lower() != b"server"]
                present = {name.lower() for name, _ in headers}
                extra = [h for h in SECURITY_HEADERS if h[0] not in present]
                if api and b"cache-control" not in present:
                    # API answers are not to be kept by a cache unless they say so (the tables do): a job's
                    # id is its capability, and answers differ by caller.
                    extra.append((b"cache-control", b"no-store"))
                message["headers"] = [*headers, *extra]
            await send(message)

        await self.app(scope, receive, with_headers)


#: Methods whose requests carry no body here: one that sends a body anyway is refused (400).
BODILESS = ("GET", "HEAD", "OPTIONS", "DELETE")


#: A UTF-8 byte-order mark: JSON (RFC 8259 section 8.1) and CSV parsers may ignore one; this
#: service drops it from the front of every body, so a spreadsheet's "UTF-8 with BOM" CSV reads.
UTF8_BOM = b"\xef\xbb\xbf"
#: Bodies up to this size are checked on the event loop (well under a millisecond, whatever they
#: hold); larger ones in a worker thread, so the loop stays free whatever a body holds.
INLINE_PARSE_BYTES = 1024


#: Most keys one JSON object of a request may have (the widest request model has a few dozen fields).
MAX_OBJECT_KEYS = 256


def _parse(body: bytes) -> tuple[Any, str | None, int] | None:
    """(the value, the first key given twice in one of its objects or None, the most keys of any of
    its objects), or None for a body that is not JSON. Linear in the body: json's own parser hands
    each object's pairs to the hook once, and the hook looks a key up in a set only when the object
    came out smaller than its pairs (a key was repeated)."""
    found: list[str] = []
    widest = 0

    def pairs(items: list[tuple[str, Any]]) -> dict:
        nonlocal widest
        result = dict(items)
        widest = max(widest, len(items))
        if len(result) != len(items) and not found:
            seen: set[str] = set()
            for key, _ in items:
                if key in seen:
                    found.append(key)
                    break
                seen.add(key)
        return result

    try:
        value = json.loads(body, object_pairs_hook=pairs)
    except (ValueError, RecursionError):
        return None
    return value, (found[0] if found else None), widest


def duplicate_keys(body: bytes) -> str | None:
    """The first key that appears twice in one JSON object of ``body``, or None (also for a body
    that is not JSON: the application says what is wrong with it)."""
    found = _parse(body)
    return found[1] if found is not None else None


def _is_json(scope: Scope) -> bool:
    """Whether the application reads this body as JSON (FastAPI does for a JSON media type or none)."""
    for name, value in scope.get("headers", []):
        if name == b"content-type":
            media = value.split(b";", 1)[0].strip().lower()
            return media == b"application/json" or media.endswith(b"+json")
    return True


def _encoding(scope: Scope) -> bytes | None:
    """The body's Content-Encoding, None for none (or ``identity``)."""
    for name, value in scope.get("headers", []):
        if name == b"content-encoding" and value.strip().lower() not in (b"", b"identity"):
            return value.strip()
    return None


class BodyLimit:
    """Refuse a body over ``max_bytes`` with 413, before the application reads or parses any of it;
    a body that takes longer than ``timeout_s`` to arrive with 408 (the connection is closed); a body
    on a GET, HEAD, OPTIONS or DELETE with 400; a compressed body (``Content-Encoding``) with 415. A
    UTF-8 byte-order mark at the body's start is dropped. The application gets the body in one piece.

    A declared Content-Length over the limit is refused at once; a chunked body is read up to the
    limit (small by default) and refused as soon as it passes it."""

    def __init__(self, app: ASGIApp, max_bytes: int, timeout_s: float = 30.0):
        self.app = app
        self.max_bytes = max_bytes
        self.timeout_s = timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if scope["method"] in BODILESS:
            for name, value in scope.get("headers", []):
                if (name == b"content-length" and value.strip() not in (b"0", b"")) or name == b"transfer-encoding":
                    close = [(b"connection", b"close")]
                    await send_problem(send, 400, f"a {scope['method']} request carries no body here; send none", None, close)
                    return
            await self.app(scope, receive, send)
            return
        if (encoding := _encoding(scope)) is not None:
            # Never parsed as text: a compressed body is refused, unread (it would only save a few of
            # at most max_body_bytes, and decompressing it is work a client could multiply).
            named = short(encoding.decode(errors="replace"), 40)
            why = f"a request body encoded as {named!r} (Content-Encoding) is not accepted; send it uncompressed"
            await send_problem(send, 415, why, None, [(b"accept-encoding", b"identity"), (b"connection", b"close")])
            return
        message = f"the request body is larger than {self.max_bytes:,} bytes (the setting max_body_bytes)"
        for name, value in scope.get("headers", []):
            if name == b"content-length":
                try:
                    declared = int(value)
                except ValueError:
                    await send_problem(send, 400, "the Content-Length header is not a number")
                    return
                if declared > self.max_bytes:
                    await send_problem(send, 413, message, "max_body_bytes", [(b"connection", b"close")])
                    return
        chunks: list[bytes] = []
        size = 0
        deadline = asyncio.get_running_loop().time() + self.timeout_s
        while True:
            try:
                event = await asyncio.wait_for(receive(), max(deadline - asyncio.get_running_loop().time(), 0.0))
            except TimeoutError:
                slow = f"the request body did not arrive within {self.timeout_s:g} s (the setting body_timeout_s)"
                await send_problem(send, 408, slow, None, [(b"connection", b"close")])
                return
            if event["type"] != "http.request":
                break  # the client went away; let the application see it
            chunk = event.get("body", b"")
            size += len(chunk)
            if size > self.max_bytes:
                await send_problem(send, 413, message, "max_body_bytes", [(b"connection", b"close")])
                return
            chunks.append(chunk)
            if not event.get("more_body", False):
                break
        body = b"".join(chunks).removeprefix(UTF8_BOM)
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


class JsonBodies:
    """A JSON body is parsed and checked before the application sees it: a key given twice in one
    object is refused (422), and so is an object of more than :data:`MAX_OBJECT_KEYS` keys (no
    request has one: their schemas' objects are small). A body larger than
    :data:`INLINE_PARSE_BYTES` is parsed -- and, for the routes in ``schemas``, validated against its
    request model, an invalid one answered 422 from there -- in a worker thread, not on the event loop,
    its cost estimated (``budget.BODY_KIB``) and admitted against the client's share first (a client
    past it gets a 429 before a byte is parsed) and charged as measured: 8,000 strings where numbers
    belong cost pydantic 150 ms of errors, which must not stop every other request on this worker.

    Inside ``budget.InlineWork`` (the request's meter) and after ``BodyLimit`` (the whole body)."""

    def __init__(self, app: ASGIApp, schemas: dict[str, Any]):
        from pydantic import TypeAdapter

        self.app = app
        self.adapters = {path: TypeAdapter(model) for path, model in schemas.items()}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] in BODILESS or not _is_json(scope):
            await self.app(scope, receive, send)
            return
        from . import budget

        event = await receive()
        body = event.get("body", b"")
        if body:
            if len(body) <= INLINE_PARSE_BYTES:
                problem = self._check(body, None)
            else:
                kib = len(body) / 1024
                adapter = self.adapters.get(scope.get("path", ""))
                try:
                    budget.admit(budget.BODY_KIB, kib, always=True)
                    async with budget.turn():
                        problem = await run_in_threadpool(self._check_metered, body, adapter, kib)
                except Throttled as refused:
                    await budget.refuse(send, refused)
                    return
            if problem is not None:
                await send_problem(send, 422, problem["detail"], body=problem)
                return
        await self.app(scope, replay_first(event, receive), send)

    def _check_metered(self, body: bytes, adapter: Any, kib: float) -> dict | None:
        from . import budget

        with budget.metered(budget.BODY_KIB, kib):
            return self._check(body, adapter)

    @staticmethod
    def _check(body: bytes, adapter: Any) -> dict | None:
        """The problem with ``body`` (a 422's problem object), or None: it goes to the application."""
        from pydantic import ValidationError

        from .errors import problem_body, validation_problem_body

        found = _parse(body)
        if found is None:
            return None  # not JSON: the application says what is wrong with it
        value, repeated, widest = found
        if repeated is not None:
            return problem_body(422, f"the JSON body gives the key {short(repeated)!r} twice; give each key once")
        if widest > MAX_OBJECT_KEYS:
            return problem_body(422, f"a JSON object in the body has {widest:,} keys; no request field takes more than "
                                     f"{MAX_OBJECT_KEYS}")  # fmt: skip
        if adapter is not None:
            try:
                adapter.validate_python(value)
            except ValidationError as invalid:
                return validation_problem_body(invalid.errors(include_url=False, include_input=False), ("body",))
        return None


def client_of(key: str) -> str:
    """The identity a job listing groups by: a hash of the API key (never the key itself)."""
    return hashlib.sha256(key.encode()).hexdigest()[:24]


#: Besides /api/, what a keyed service answers only with a key: the API's schema and its docs page.
KEYED_PATHS = ("/openapi.json", "/docs", "/docs.html")


class ApiKey:
    """With keys configured, /api/v1 (but /api/v1/health, for probes), the OpenAPI schema and /docs
    need one of them, as ``Authorization: Bearer <key>`` or ``X-API-Key: <key>``; the caller's
    identity is then its key's hash."""

    def __init__(self, app: ASGIApp, keys: list[str]):
        self.app = app
        self.keys = [k.encode() for k in keys]

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path = scope.get("path", "")
        keyed = path.startswith("/api/") or path in KEYED_PATHS
        if scope["type"] != "http" or not keyed or path == "/api/v1/health":
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
            await send_problem(send, 401, "an API key is required (Authorization: Bearer <key>, or X-API-Key)", None,
                           [(b"www-authenticate", b"Bearer")])  # fmt: skip
            return
        scope.setdefault("state", {})["client"] = client_of(match.decode())
        await self.app(scope, receive, send)


class ApiMethods:
    """Methods on /api/ paths answered as HTTP says: OPTIONS with 204 and ``Allow``, a method the
    route does not take with 405 and ``Allow`` (HEAD wherever GET is), an unknown path with 404 --
    never the page's static files, which would otherwise answer every path the API does not hold."""

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not scope.get("path", "").startswith("/api/"):
            await self.app(scope, receive, send)
            return
        from starlette.routing import Match, Mount

        routes = [r for r in getattr(scope.get("app"), "routes", []) if not (isinstance(r, Mount) and r.path in ("", "/"))]
        if scope["method"] not in ("OPTIONS", "HEAD") and any(r.matches(scope)[0] == Match.FULL for r in routes):
            await self.app(scope, receive, send)  # the common case: a route takes this method
            return
        allowed = {
            method
            for method in ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE")
            if any(route.matches({**scope, "method": method})[0] == Match.FULL for route in routes)
        }
        if not allowed:
            await send_problem(send, 404, "no such API path (see /docs)")
            return
        if "GET" in allowed:
            allowed.add("HEAD")
        allow = ", ".join(sorted(allowed | {"OPTIONS"}))
        if scope["method"] == "OPTIONS":
            await send({"type": "http.response.start", "status": 204, "headers": [(b"allow", allow.encode())]})
            await send({"type": "http.response.body", "body": b""})
            return
        if scope["method"] not in allowed:
            await send_problem(send, 405, f"{scope['method']} is not a method of this path; it takes {allow}", None,
                           [(b"allow", allow.encode())])  # fmt: skip
            return
        if scope["method"] == "HEAD":
            # HEAD is GET without the body (RFC 9110 9.3.2): the same status and headers.
            async def headers_only(message: Message) -> None:
                if message["type"] == "http.response.body":
                    message = {**message, "body": b""}
                await send(message)

            # "nlpsf.head": a route that can answer HEAD without building its body (the tables) may.
            await self.app({**scope, "method": "GET", "nlpsf.head": True}, receive, headers_only)
            return
        await self.app(scope, receive, send)


def replay_first(event: Any, receive: Any) -> Any:
    """An ASGI ``receive`` that hands ``event`` (one already read, to look at it) back first, then
    reads on from ``receive``."""
    replayed = False

    async def replay() -> Any:
        nonlocal replayed
        if not replayed:
            replayed = True
            return event
        return await receive()

    return replay
