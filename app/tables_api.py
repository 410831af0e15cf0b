"""The shipped slope tables (JSON, ECSV, CSV; ETag-cacheable), their power-law fits and the paper's data.

The tables are large fixed documents (the whole set: 6.6 MB of JSON, 3.5 MB of CSV or ECSV): each
selection (format, band, SCA) is built once per HTTP worker and compressed once, kept and sent by
``documents`` (gzip where accepted, 304 for a matching ETag, paced slices, HEAD from the kept
document's headers, or without a body length before it was ever built).
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Callable
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import Response

from nlpsf._version import __version__
from nlpsf.serialise import json_safe
from nlpsf.slopes import tables

from . import data_models
from .documents import CACHE_CONTROL, Document, DocumentResponse, Documents, document, not_modified
from .errors import SafeJSONResponse
from .health_api import public_table_meta
from .params import ERRORS, OptionalBand, OptionalSca

router = APIRouter(prefix="/api/v1")

#: Units of the cost model: building one document (its cost grows with the selection; measured).
DOCUMENT = "document"


def _table_etag(kind: str, band: str | None, sca: int | None) -> str:
    """A strong validator: the tables' fingerprint (their content) and the selection asked for."""
    fingerprint = tables.load_tables().meta.get("fingerprint", "")
    return f'"{fingerprint}-{__version__}-{kind}-{band or "all"}-{sca or "all"}"'


_CACHE = {"Cache-Control": CACHE_CONTROL}
_NOT_MODIFIED = {304: {"description": "not modified: the tables are unchanged since the ETag sent in If-None-Match"}}


def _answer(request: Request, kind: str, band: str | None, sca: int | None, build: Callable[[], Document]) -> Response:
    etag = _table_etag(kind, band, sca)
    if not_modified(request.scope, etag):
        return Response(status_code=304, headers={"ETag": etag, "Vary": "Accept-Encoding", **_CACHE})
    documents: Documents = request.app.state.documents
    key = ("tables", kind, band, sca)
    if request.scope.get("nlpsf.head") and documents.peek(key) is None:
        # HEAD before the document was ever built: its headers, without building it for a length.
        media = {"json": "application/json", "csv": "text/csv; charset=utf-8", "ecsv": "text/x-ecsv; charset=utf-8"}[kind]
        return Response(status_code=200, media_type=media, headers={"ETag": etag, "Vary": "Accept-Encoding", **_CACHE})
    whole = band is None and sca is None  # the whole tables: once per process, for everyone
    kept = documents.get(key, lambda: build_with(build, etag), f"{DOCUMENT}:{kind}", pinned=whole)
    return DocumentResponse(kept)


def build_with(build: Callable[[], Document], etag: str) -> Document:
    made = build()
    return Document(made.media_type, made.body, made.gzipped, made.headers, etag)


@router.get(
    "/tables",
    response_model=data_models.TableJSON,
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
    response_model=data_models.Fits,
    responses=ERRORS,
    summary="Power-law fits slope = A 10^(B (m - 20)) per band and SCA (the paper's Table 2 form)",
)
def fits(band: OptionalBand = None, sca: OptionalSca = None) -> SafeJSONResponse:
    bands = [band] if band else None
    scas = [sca] if sca else None
    return SafeJSONResponse({"fits": json_safe(tables.powerlaw_fits(bands, scas))})


@router.get(
    "/paper",
    response_model=data_models.PaperData,
    summary="The paper's published figure data (Figs. 2, 3, 5, Table 2; Cycle-5 optics)",
)
def paper() -> SafeJSONResponse:
    return SafeJSONResponse(json_safe(tables.paper_data()))
