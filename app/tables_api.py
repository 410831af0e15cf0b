"""The shipped slope tables (JSON, ECSV, CSV; ETag-cacheable), their power-law fits and the paper's data.

The tables are large fixed documents (the whole set: 6.6 MB of JSON, 3.5 MB of CSV or ECSV): each
selection (format, band, SCA) is built once per HTTP worker, compressed once (gzip), kept
(:class:`Documents`, bounded) and sent in slices, so a reader that does not read holds a few tens of
kilobytes of the worker's memory, not the document. A request that sends back the ETag gets 304;
HEAD answers from the kept document's headers, or without a body length before it was ever built.
"""

from __future__ import annotations

import asyncio
import contextlib
import csv
import gzip
import io
import math
import threading
from collections import OrderedDict
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import Response

from nlpsf import __version__
from nlpsf.serialise import json_safe
from nlpsf.slopes import tables

from . import budget, models
from .errors import SafeJSONResponse, Throttled
from .health_api import public_table_meta
from .params import ERRORS, OptionalBand, OptionalSca

router = APIRouter(prefix="/api/v1")

#: Slices a document is sent in: the worker waits for the client to take one before it writes the next.
CHUNK_BYTES = 64 * 1024
#: Documents one client may be sent at once by one HTTP worker; a further request waits its turn
#: (up to SEND_WAIT_S, then 429): twenty readers from one address take two readers' bandwidth.
SENDS_PER_CLIENT = 2
#: How long a request waits for its client's turn to be sent a document, s.
SEND_WAIT_S = 10.0
#: A client that takes no slice of a document for this long is cut off (its connection closed), s.
SEND_STALL_S = 30.0
#: Bytes per second one client is sent documents at, at most, per HTTP worker (each of its
#: SENDS_PER_CLIENT documents at its part): the whole tables' gzip (1.9 MB) in a quarter of a
#: second, while a loopback reader that re-reads them for ever costs the worker little.
SEND_RATE_BYTES = 16 * 1024**2
#: gzip level of the kept documents (built once per process).
GZIP_LEVEL = 6
#: Units of the cost model: building one document (its cost grows with the selection; measured).
DOCUMENT = "document"


def _table_etag(kind: str, band: str | None, sca: int | None) -> str:
    """A strong validator: the tables' fingerprint (their content) and the selection asked for."""
    fingerprint = tables.load_tables().meta.get("fingerprint", "")
    return f'"{fingerprint}-{__version__}-{kind}-{band or "all"}-{sca or "all"}"'


_CACHE = {
    "Cache-Control": "public, max-age=3600, must-revalidate",
}
_NOT_MODIFIED = {304: {"description": "not modified: the tables are unchanged since the ETag sent in If-None-Match"}}


def _not_modified(request: Request, etag: str) -> Response | None:
    sent = request.headers.get("if-none-match", "")
    if etag in [tag.strip().removeprefix("W/") for tag in sent.split(",")] or sent.strip() == "*":
        return Response(status_code=304, headers={"ETag": etag, "Vary": "Accept-Encoding", **_CACHE})
    return None


@dataclass(frozen=True)
class Document:
    """A fixed answer, built once: its bytes, their gzip, and the headers both carry."""

    media_type: str
    body: bytes
    gzipped: bytes
    headers: dict[str, str]

    @property
    def size(self) -> int:
        return len(self.body) + len(self.gzipped)


class Documents:
    """The documents of one HTTP worker by key. The whole tables (no band, no SCA: three documents)
    are built on first request at no client's cost and kept for the process's life; a selection's
    document is built at the cost of the client that first asks for it (``budget``) and kept up to
    ``max_bytes`` in all, the least recently used going first. A document asked for by many
    clients at once is built by one of them; the others wait for it."""

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self._pinned: dict[tuple, Document] = {}
        self._kept: OrderedDict[tuple, Document] = OrderedDict()
        self._size = 0
        self._lock = threading.Lock()
        self._building: dict[tuple, threading.Lock] = {}

    def peek(self, key: tuple) -> Document | None:
        with self._lock:
            return self._pinned.get(key) or self._kept.get(key)

    def get(self, key: tuple, build: Callable[[], Document], whole: bool) -> Document:
        with self._lock:
            if (kept := self._pinned.get(key) or self._kept.get(key)) is not None:
                if key in self._kept:
                    self._kept.move_to_end(key)
                return kept
            building = self._building.setdefault(key, threading.Lock())
        with building:
            if (kept := self.peek(key)) is not None:
                return kept
            if whole:
                with budget.turn_in_thread(), budget.uncharged():
                    document = build()  # once per process, for everyone: charged to no one
            else:
                kind = f"{DOCUMENT}:{key[0]}"
                budget.admit(kind, 1.0)
                with budget.turn_in_thread(), budget.metered(kind, 1.0):
                    document = build()
            with self._lock:
                if whole:
                    self._pinned[key] = document
                else:
                    self._kept[key] = document
                    self._size += document.size
                    while self._size > self.max_bytes and len(self._kept) > 1:
                        self._size -= self._kept.popitem(last=False)[1].size
                self._building.pop(key, None)
            return document


def document(media_type: str, text: str | bytes, headers: dict[str, str] | None = None) -> Document:
    body = text.encode() if isinstance(text, str) else text
    return Document(media_type, body, gzip.compress(body, GZIP_LEVEL, mtime=0), dict(headers or {}))


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


class DocumentResponse(Response):
    """A :class:`Document` as the client takes it (gzip if it accepts it), in slices; no body for
    HEAD. At most :data:`SENDS_PER_CLIENT` at once per client, at :data:`SEND_RATE_BYTES` in all;
    between slices the event loop serves others (a loopback client takes megabytes without ever
    making the worker wait); a client that stops taking slices for :data:`SEND_STALL_S` is cut off."""

    def __init__(self, kept: Document, request: Request, etag: str):
        self.kept = kept
        self.compressed = "gzip" in request.headers.get("accept-encoding", "").lower()
        self.head = bool(request.scope.get("nlpsf.head"))
        super().__init__(status_code=200, headers={**kept.headers, "ETag": etag, "Vary": "Accept-Encoding", **_CACHE},
                         media_type=kept.media_type)  # fmt: skip

    def render(self, content: Any) -> bytes:
        return b""

    async def __call__(self, scope, receive, send) -> None:  # type: ignore[override]
        body = self.kept.gzipped if self.compressed else self.kept.body
        headers = [(k, v) for k, v in self.raw_headers if k != b"content-length"]
        headers.append((b"content-length", str(len(body)).encode()))
        if self.compressed:
            headers.append((b"content-encoding", b"gzip"))
        if self.head or not body:
            await send({"type": "http.response.start", "status": 200, "headers": headers})
            await send({"type": "http.response.body", "body": b""})
            return
        loop = asyncio.get_running_loop()
        try:
            async with TURNS.turn(budget.client_key(scope)), asyncio.timeout(SEND_STALL_S) as deadline:
                await send({"type": "http.response.start", "status": 200, "headers": headers})
                view = memoryview(body)
                began = loop.time()
                for start in range(0, len(body), CHUNK_BYTES):
                    end = start + CHUNK_BYTES
                    piece = {"type": "http.response.body", "body": bytes(view[start:end]), "more_body": end < len(body)}
                    deadline.reschedule(loop.time() + SEND_STALL_S)
                    await send(piece)
                    # Paced (and the loop serves others between slices).
                    await asyncio.sleep(max(0.0, began + min(end, len(body)) * SENDS_PER_CLIENT / SEND_RATE_BYTES - loop.time()))
        except Throttled as refused:
            await budget.refuse(send, refused)
        except TimeoutError:
            return  # the client stopped reading: the response ends unfinished and its connection is closed


def _answer(request: Request, kind: str, band: str | None, sca: int | None, build: Callable[[], Document]) -> Response:
    etag = _table_etag(kind, band, sca)
    if (cached := _not_modified(request, etag)) is not None:
        return cached
    documents: Documents = request.app.state.documents
    key = (kind, band, sca)
    if request.scope.get("nlpsf.head") and (kept := documents.peek(key)) is None:
        # HEAD before the document was ever built: its headers, without building it for a length.
        media = {"json": "application/json", "csv": "text/csv; charset=utf-8", "ecsv": "text/x-ecsv; charset=utf-8"}[kind]
        return Response(status_code=200, media_type=media, headers={"ETag": etag, "Vary": "Accept-Encoding", **_CACHE})
    kept = documents.get(key, build, whole=band is None and sca is None)
    return DocumentResponse(kept, request, etag)


@router.get(
    "/tables",
    response_model=models.TableJSON,
    responses={**ERRORS, **_NOT_MODIFIED},
    summary="The shipped slope tables as JSON rows (optionally one band / SCA); gzip-compressed, ETag-cacheable",
)
def table_json(request: Request, band: OptionalBand = None, sca: OptionalSca = None) -> Response:
    def build() -> Document:
        body = {"meta": public_table_meta(tables.load_tables().meta), "rows": tables.table_rows(band, sca)}
        return document("application/json", SafeJSONResponse(body).body)

    return _answer(request, "json", band, sca, build)


#: Units of the table columns (the shipped ECSV's own ``units`` metadata, as astropy units).
_SLOPE_UNIT = "electron"


def _column_unit(name: str) -> str | None:
    if name == "magnitude":
        return "mag(AB)"
    if name in ("flux_electrons", "peak_electrons") or name.startswith(("bias_", "scatter_")):
        return _SLOPE_UNIT
    return None


@router.get(
    "/tables.ecsv",
    responses={
        **ERRORS,
        **_NOT_MODIFIED,
        200: {"content": {"text/x-ecsv": {}}, "description": "ECSV (astropy), units on the columns; one row per (band, SCA, m)"},
    },
    summary="The shipped slope tables as ECSV with units on the columns",
)
def table_ecsv(request: Request, band: OptionalBand = None, sca: OptionalSca = None) -> Response:
    def build() -> Document:
        from astropy.table import Table

        rows = tables.table_rows(band, sca)
        table = Table(rows=rows, names=list(rows[0]))
        for name in table.colnames:
            if (unit := _column_unit(name)) is not None:
                table[name].unit = unit
        table.meta = {
            "description": "nlpsf slope tables: bias slopes d(metric)/dbeta and scatter slopes sigma(metric)/sigma_beta; "
            "slopes in e- (a dimensionless metric per 1/e- of beta); peak_electrons per fine pixel x N^2",
            "tables": public_table_meta(tables.load_tables().meta),
        }
        out = io.StringIO()
        table.write(out, format="ascii.ecsv")
        name = "nlpsf-slopes" + (f"-{band.upper()}" if band else "") + (f"-sca{sca}" if sca else "") + ".ecsv"
        return document("text/x-ecsv; charset=utf-8", out.getvalue(), {"Content-Disposition": f'attachment; filename="{name}"'})

    return _answer(request, "ecsv", band, sca, build)


@router.get(
    "/tables.csv",
    responses={
        **ERRORS,
        **_NOT_MODIFIED,
        200: {"content": {"text/csv": {}}, "description": "CSV, one row per (band, SCA, magnitude)"},
    },
    summary="The shipped slope tables as a CSV download; ETag-cacheable",
)
def table_csv(request: Request, band: OptionalBand = None, sca: OptionalSca = None) -> Response:
    def build() -> Document:
        rows = tables.table_rows(band, sca)
        out = io.StringIO()
        writer = csv.DictWriter(out, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows({k: _csv_value(v) for k, v in row.items()} for row in rows)
        name = "nlpsf-slopes" + (f"-{band.upper()}" if band else "") + (f"-sca{sca}" if sca else "") + ".csv"
        return document("text/csv; charset=utf-8", out.getvalue(), {"Content-Disposition": f'attachment; filename="{name}"'})

    return _answer(request, "csv", band, sca, build)


def _csv_value(value: Any) -> Any:
    return "" if isinstance(value, float) and not math.isfinite(value) else value


@router.get(
    "/fits",
    response_model=models.Fits,
    responses=ERRORS,
    summary="Power-law fits slope = A 10^(B (m - 20)) per band and SCA (the paper's Table 2 form)",
)
def fits(band: OptionalBand = None, sca: OptionalSca = None) -> SafeJSONResponse:
    bands = [band] if band else None
    scas = [sca] if sca else None
    return SafeJSONResponse({"fits": json_safe(tables.powerlaw_fits(bands, scas))})


@router.get(
    "/paper",
    response_model=models.PaperData,
    summary="The paper's published figure data (Figs. 2, 3, 5, Table 2; Cycle-5 optics)",
)
def paper() -> SafeJSONResponse:
    return SafeJSONResponse(json_safe(tables.paper_data()))
