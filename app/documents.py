"""Answers built once and sent many times: the large fixed documents (the tables) and the answers of
routes that are pure functions of their request (the page's curves, /fits, /meta).

A :class:`Document` is an answer's bytes with their gzip, made once. :class:`Documents` keeps them
per HTTP worker (pinned for the process's life, or the least recently used out past a size);
:func:`send_document` sends one as the client takes it -- gzip where accepted, ``304`` for a
matching ``If-None-Match``, no body for HEAD, a large one in paced slices, at most
:data:`SENDS_PER_CLIENT` at once per client, cut off when the reader stalls -- so that twenty
readers of the 6.6 MB tables, or two hundred that never read, cost the worker little.

:class:`CachedAnswers` (middleware) keeps the answers of the routes it is given by request and
admits a miss against the client's share of the inline CPU (``budget``).
"""

from __future__ import annotations

import asyncio
import contextlib
import gzip
import hashlib
import threading
from collections import OrderedDict
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from . import budget
from .errors import Throttled
from .security import replay_first

#: Slices a large document is sent in: the worker waits for the client to take one before the next.
CHUNK_BYTES = 64 * 1024
#: Documents one client may be sent at once by one HTTP worker; a further request waits its turn
#: (up to SEND_WAIT_S, then 429): twenty readers from one address take two readers' bandwidth.
SENDS_PER_CLIENT = 2
#: How long a request waits for its client's turn to be sent a document, s.
SEND_WAIT_S = 10.0
#: A client that takes no slice of a document for this long is cut off (its connection closed), s.
SEND_STALL_S = 30.0
#: Bytes per second one client is sent large documents at, at most, per HTTP worker (each of its
#: SENDS_PER_CLIENT documents at its part): the whole tables' gzip (1.9 MB) in a quarter of a
#: second, while a loopback reader that re-reads them for ever costs the worker little.
SEND_RATE_BYTES = 16 * 1024**2
#: gzip level of the kept documents (built once per process).
GZIP_LEVEL = 6
#: Answers smaller than this are sent identity (gzip would gain nothing).
GZIP_MIN_BYTES = 1024
CACHE_CONTROL = "public, max-age=3600, must-revalidate"


@dataclass(frozen=True)
class Document:
    """A fixed answer, built once: its bytes, their gzip (None for a small one), the headers both
    carry and a strong validator."""

    media_type: str
    body: bytes
    gzipped: bytes | None
    headers: dict[str, str] = field(default_factory=dict)
    etag: str = ""

    @property
    def size(self) -> int:
        return len(self.body) + len(self.gzipped or b"") + 512


def document(media_type: str, text: str | bytes, headers: dict[str, str] | None = None, etag: str | None = None) -> Document:
    """A :class:`Document` of ``text`` (its ETag, if none is given: a hash of the bytes)."""
    body = text.encode() if isinstance(text, str) else text
    packed = gzip.compress(body, GZIP_LEVEL, mtime=0) if len(body) >= GZIP_MIN_BYTES else None
    return Document(media_type, body, packed, dict(headers or {}), etag or f'"{hashlib.sha256(body).hexdigest()[:32]}"')


class Documents:
    """The documents of one HTTP worker by key: pinned ones for the process's life, the others up to
    ``max_bytes`` in all, the least recently used going first. A document asked for by many
    clients at once is built by one of them; the others wait for it."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self._pinned: dict[Any, Document] = {}
        self._kept: OrderedDict[Any, Document] = OrderedDict()
        self._size = 0
        self._lock = threading.Lock()
        self._building: dict[Any, threading.Lock] = {}

    def peek(self, key: Any) -> Document | None:
        with self._lock:
            kept = self._pinned.get(key) or self._kept.get(key)
            if key in self._kept:
                self._kept.move_to_end(key)
            return kept

    def put(self, key: Any, kept: Document, pinned: bool = False) -> None:
        with self._lock:
            if pinned:
                self._pinned[key] = kept
                return
            if (old := self._kept.pop(key, None)) is not None:
                self._size -= old.size
            self._kept[key] = kept
            self._size += kept.size
            while self._size > self.max_bytes and len(self._kept) > 1:
                self._size -= self._kept.popitem(last=False)[1].size

    def get(self, key: Any, build: Callable[[], Document], kind: str, pinned: bool = False) -> Document:
        """The document under ``key``, built by ``build`` (in this thread: call from a worker thread)
        if it is not kept. A pinned one is built once per process for everyone, at no client's cost;
        another at the cost of the client that first asks for it (one unit of ``kind``, admitted
        against its share)."""
        if (kept := self.peek(key)) is not None:
            return kept
        with self._lock:
            building = self._building.setdefault(key, threading.Lock())
        with building:
            if (kept := self.peek(key)) is not None:
                return kept
            if pinned:
                with budget.turn_in_thread(), budget.uncharged():
                    kept = build()
            else:
                budget.admit(kind, 1.0)
                with budget.turn_in_thread(), budget.metered(kind, 1.0):
                    kept = build()
            self.put(key, kept, pinned)
            with self._lock:
                self._building.pop(key, None)
            return kept


# --- sending ---------------------------------------------------------------------------------------


class _Turns:
    """How many documents each client is being sent now (one HTTP worker; the event loop's only)."""

    def __init__(self) -> None:
        self.sending: dict[str, tuple[asyncio.Semaphore, list[int]]] = {}

    @contextlib.asynccontextmanager
    async def turn(self, client: str) -> AsyncIterator[None]:
        semaphore, users = self.sending.setdefault(client, (asyncio.Semaphore(SENDS_PER_CLIENT), [0]))
        users[0] += 1
        try:
            try:
                await asyncio.wait_for(semaphore.acquire(), SEND_WAIT_S)
            except TimeoutError:
                raise Throttled(
                    f"you are being sent {SENDS_PER_CLIENT} documents already; retry when one has arrived",
                    "documents_per_client",
                    1.0,
                ) from None
            try:
                yield
            finally:
                semaphore.release()
        finally:
            users[0] -= 1
            if users[0] == 0:
                self.sending.pop(client, None)  # idle: forget the client


TURNS = _Turns()


def _header(scope: Any, name: bytes) -> str:
    for key, value in scope.get("headers", []):
        if key == name:
            return value.decode("latin-1")
    return ""


def not_modified(scope: Any, etag: str) -> bool:
    sent = _header(scope, b"if-none-match")
    return bool(etag) and (etag in [tag.strip().removeprefix("W/") for tag in sent.split(",")] or sent.strip() == "*")


async def send_document(scope: Any, send: Any, kept: Document, cache_control: str | None = None) -> None:
    """``kept`` as this request takes it: 304 when it sends back the ETag; gzip if it accepts gzip;
    no body for HEAD (``nlpsf.head``: ``security.ApiMethods`` turned it into a GET); a large one in
    paced slices, at most :data:`SENDS_PER_CLIENT` at once per client, cut off if the reader stalls."""
    common = [(b"etag", kept.etag.encode()), (b"vary", b"Accept-Encoding")]
    if cache_control:
        common.append((b"cache-control", cache_control.encode()))
    if not_modified(scope, kept.etag):
        await send({"type": "http.response.start", "status": 304, "headers": common})
        await send({"type": "http.response.body", "body": b""})
        return
    compressed = kept.gzipped is not None and "gzip" in _header(scope, b"accept-encoding").lower()
    body = kept.gzipped if compressed else kept.body
    assert body is not None
    headers = [
        (b"content-type", kept.media_type.encode()),
        (b"content-length", str(len(body)).encode()),
        *common,
        *((name.lower().encode(), value.encode()) for name, value in kept.headers.items()),
    ]
    if compressed:
        headers.append((b"content-encoding", b"gzip"))
    if scope.get("nlpsf.head") or len(body) <= CHUNK_BYTES:
        await send({"type": "http.response.start", "status": 200, "headers": headers})
        await send({"type": "http.response.body", "body": b"" if scope.get("nlpsf.head") else body})
        return
    loop = asyncio.get_running_loop()
    try:
        async with TURNS.turn(budget.client_key(scope)), asyncio.timeout(SEND_STALL_S) as deadline:
            await send({"type": "http.response.start", "status": 200, "headers": headers})
            view = memoryview(body)
            began = loop.time()
            for start in range(0, len(body), CHUNK_BYTES):
                end = min(start + CHUNK_BYTES, len(body))
                deadline.reschedule(loop.time() + SEND_STALL_S)
                await send({"type": "http.response.body", "body": bytes(view[start:end]), "more_body": end < len(body)})
                # Paced (and the loop serves others between slices).
                await asyncio.sleep(max(0.0, began + end * SENDS_PER_CLIENT / SEND_RATE_BYTES - loop.time()))
    except Throttled as refused:
        await budget.refuse(send, refused)
    except TimeoutError:
        return  # the client stopped reading: the response ends unfinished and its connection is closed


class DocumentResponse(Response):
    """A route's answer that is a :class:`Document` (sent by :func:`send_document`)."""

    def __init__(self, kept: Document, cache_control: str | None = CACHE_CONTROL):
        self.kept = kept
        self.cache_control = cache_control
        super().__init__(status_code=200, media_type=kept.media_type)

    def render(self, content: Any) -> bytes:
        return b""

    async def __call__(self, scope, receive, send) -> None:  # type: ignore[override]
        await send_document(scope, send, self.kept, self.cache_control)


# --- the answers of pure routes, kept by request ---------------------------------------------------


def _canonical_query(query_string: bytes) -> tuple[tuple[str, str], ...]:
    """A query as a key: its parameters by name (a name's repeated values keep their order)."""
    from urllib.parse import parse_qsl

    pairs = parse_qsl(query_string.decode("latin-1"), keep_blank_values=True)
    return tuple(sorted(pairs, key=lambda pair: pair[0]))


#: Response headers a kept answer keeps (the rest -- length, encoding -- are the sender's).
_KEPT_HEADERS = (b"content-disposition",)


class CachedAnswers:
    """ASGI middleware for the routes in ``routes`` (path -> method) whose answer is a pure function
    of the request (its query, and its body for a POST): the page's curves, /fits, /meta. An answer
    given is kept (:class:`Document`: gzip made once, an ETag; small ones in the budget's answer
    cache, large ones in ``documents``) and sent again by :func:`send_document`; a request not
    answered yet is admitted against the client's share (one unit of its path, learned as measured)
    and computed in its turn (``budget.Turns``). Inside the compression and the body's reading."""

    def __init__(self, app: Any, budget: budget.InlineBudget, documents: Documents, routes: dict[str, str]):
        self.app = app
        self.budget = budget
        self.documents = documents
        self.routes = routes

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        work = budget.active()
        if scope["type"] != "http" or self.routes.get(scope.get("path", "")) != scope["method"] or work is None:
            await self.app(scope, receive, send)
            return
        body = b""
        if scope["method"] != "GET":
            event = await receive()  # the whole body, as BodyLimit hands it on
            body = event.get("body", b"")
            receive = replay_first(event, receive)
        path = scope["path"]
        key = (scope["method"], path, _canonical_query(scope.get("query_string", b"")), body)
        if await self._send_kept(key, scope, send):
            return
        try:
            self.budget.admit(work.meter, self.budget.costs.estimate(path, 1.0))
            async with self.budget.turns.turn(work.meter.client):
                if not await self._send_kept(key, scope, send):  # answered while this request waited its turn?
                    await self._answer(scope, receive, send, work, key)
        except Throttled as refused:
            await budget.refuse(send, refused)

    def _kept(self, key: Any) -> Document | None:
        return self.budget.answers.get(key) or self.documents.peek(key)

    async def _send_kept(self, key: Any, scope: Any, send: Any) -> bool:
        if (kept := self._kept(key)) is None:
            return False
        await send_document(scope, send, kept)
        return True

    async def _answer(self, scope: Any, receive: Any, send: Any, work: budget.Work, key: Any) -> None:
        start: dict[str, Any] = {}
        chunks: list[bytes] = []
        used_before = work.meter.used_s

        async def keep(message: Any) -> None:
            if message["type"] == "http.response.start":
                start.update(message, headers=list(message.get("headers", [])))  # as this route sent them
            elif message["type"] == "http.response.body":
                chunks.append(message.get("body", b""))
            await send(message)

        await self.app(scope, receive, keep)
        self.budget.costs.observe(scope["path"], 1.0, work.meter.used_s - used_before)
        if start.get("status") == 200 and not scope.get("nlpsf.head"):
            headers = dict(start["headers"])
            media = headers.get(b"content-type", b"application/json").decode("latin-1")
            kept_headers = {k.decode(): v.decode("latin-1") for k, v in headers.items() if k in _KEPT_HEADERS}
            made = await run_in_threadpool(document, media, b"".join(chunks), kept_headers)
            if made.size <= self.budget.answers.max_bytes // 16:
                self.budget.answers.put(key, made, made.size)
            else:
                self.documents.put(key, made)
