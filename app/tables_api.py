"""The shipped slope tables (JSON, ECSV, CSV; ETag-cacheable), their power-law fits and the paper's data."""

from __future__ import annotations

import csv
import io
import math
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import Response

from nlpsf import __version__
from nlpsf.serialise import json_safe
from nlpsf.slopes import tables

from . import data_models
from .errors import SafeJSONResponse
from .health_api import public_table_meta
from .params import ERRORS, OptionalBand, OptionalSca

router = APIRouter(prefix="/api/v1")


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
        return Response(status_code=304, headers={"ETag": etag, **_CACHE})
    return None


@router.get(
    "/tables",
    response_model=data_models.TableJSON,
    responses={**ERRORS, **_NOT_MODIFIED},
    summary="The shipped slope tables as JSON rows (optionally one band / SCA); gzip-compressed, ETag-cacheable",
)
def table_json(request: Request, band: OptionalBand = None, sca: OptionalSca = None) -> Response:
    etag = _table_etag("json", band, sca)
    if (cached := _not_modified(request, etag)) is not None:
        return cached
    table_set = tables.load_tables()
    body = {"meta": public_table_meta(table_set.meta), "rows": tables.table_rows(band, sca)}
    return SafeJSONResponse(body, headers={"ETag": etag, **_CACHE})


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
    etag = _table_etag("ecsv", band, sca)
    if (cached := _not_modified(request, etag)) is not None:
        return cached
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
    headers = {"Content-Disposition": f'attachment; filename="{name}"', "ETag": etag, **_CACHE}
    return Response(out.getvalue(), media_type="text/x-ecsv", headers=headers)


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
    etag = _table_etag("csv", band, sca)
    if (cached := _not_modified(request, etag)) is not None:
        return cached
    rows = tables.table_rows(band, sca)
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: _csv_value(v) for k, v in row.items()} for row in rows)
    name = "nlpsf-slopes" + (f"-{band.upper()}" if band else "") + (f"-sca{sca}" if sca else "") + ".csv"
    headers = {"Content-Disposition": f'attachment; filename="{name}"', "ETag": etag, **_CACHE}
    return Response(out.getvalue(), media_type="text/csv", headers=headers)


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
