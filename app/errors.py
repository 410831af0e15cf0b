"""Errors as RFC 9457 problem details (``application/problem+json``, ``models.Problem``).

The standard members (``type``, ``title``, ``status``, ``detail``) plus this service's extensions: the
``field`` at fault, the ``limit`` a refusal hit, ``errors`` (one entry per bad field) and ``message``
(the same text as ``detail``, kept for clients written before the problem format). Bad input is a 422
naming the field, whether pydantic or the library caught it; nothing a client sends may produce a 5xx.
"""

from __future__ import annotations

import json
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from nlpsf.checks import InputError
from nlpsf.serialise import json_safe

from .headers import SECURITY_HEADERS
from .store import StoreUnavailable

#: Longest piece of a client's input an error message repeats: enough to recognise it, never the
#: megabytes a hostile request sends.
ECHO_CHARS = 120


def short(text: Any, limit: int = ECHO_CHARS) -> str:
    text = str(text)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text):,} characters)"


#: The encoder of every JSON answer, made once (``json.dumps`` with arguments builds one per call). No
#: circular-reference check: answers are trees of the library's ``to_dict`` (a cycle still fails, as
#: RecursionError), and the check's bookkeeping per container is a tenth of a Roman-default answer's encoding.
_ENCODER = json.JSONEncoder(ensure_ascii=False, allow_nan=False, separators=(",", ":"), check_circular=False)


def render_json(content: Any) -> bytes:
    """``content`` as compact UTF-8 JSON without NaN/Infinity tokens: the fast path first, the
    payload cleaned (``json_safe``) only if it must be. The bytes every JSON answer is sent as."""
    try:
        return _ENCODER.encode(content).encode()
    except (ValueError, TypeError):
        return _ENCODER.encode(json_safe(content)).encode()


class SafeJSONResponse(JSONResponse):
    """JSON without NaN/Infinity tokens (:func:`render_json`)."""

    def render(self, content: Any) -> bytes:
        return render_json(content)


PROBLEM_MEDIA_TYPE = "application/problem+json"

#: Where a request that needs a simulation is answered (as a job), when a batch refuses it.
SOLVE_ENDPOINT = "/api/v1/solve"

#: The ``type`` of each kind of problem: a relative URI naming it (RFC 9457 section 3.1.1); the page
#: /docs lists the statuses. "about:blank" where the HTTP status says all there is.
PROBLEM_TYPES = {
    400: "about:blank",
    401: "/problems/unauthorized",
    404: "about:blank",
    409: "/problems/conflict",
    413: "/problems/limit-exceeded",
    422: "/problems/invalid-input",
    # A rule the schema cannot state, found by the library after the schema passed: fields that
    # conflict (give exactly two of three), a value valid only with others (a star too bright for
    # beta0), a table's shape (increasing wavelengths).
    "combination": "/problems/invalid-combination",
    # Valid, but its answer needs a fresh simulation, which a batch does not run: POST /solve does (a job).
    "needs_simulation": "/problems/needs-simulation",
    429: "/problems/queue-full",
    # A client's (or all clients') share of the HTTP workers' inline CPU is used: retry after Retry-After.
    "throttled": "/problems/inline-cpu-used",
    500: "/problems/internal-error",
    503: "/problems/unavailable",
}


def problem_body(
    status: int, message: str, field: str | None = None, limit: str | None = None, errors=None, kind: str | None = None
) -> dict:
    """The problem object; ``errors`` = [{loc, field, msg, type}] for every bad field found."""
    from http import HTTPStatus

    message = short(message, 4 * ECHO_CHARS)
    try:
        title = HTTPStatus(status).phrase
    except ValueError:
        title = "Error"
    if kind is None:
        kind = "/problems/limit-exceeded" if status == 422 and limit else PROBLEM_TYPES.get(status, "about:blank")
    errors = [{**d, "msg": short(d["msg"], 4 * ECHO_CHARS), "field": d["field"] and short(d["field"])} for d in errors or []]
    return {
        "type": kind,
        "title": title,
        "status": status,
        "detail": message,
        "message": message,
        "field": field and short(field),
        "limit": limit,
        "errors": errors,
    }


class Throttled(Exception):
    """A client (or all clients together) has used its share of inline CPU (``budget``): a 429 with
    Retry-After, the time its share takes to cover the request."""

    def __init__(self, message: str, limit: str, retry_after_s: float):
        super().__init__(message)
        self.message = message
        self.limit = limit
        self.retry_after_s = retry_after_s

    #: Pause before a 429 is sent (s): the client's wait, at least MIN_PAUSE_S, at most MAX_PAUSE_S.
    MIN_PAUSE_S = 0.5
    MAX_PAUSE_S = 1.0

    def retry_after(self) -> str:
        import math

        return str(max(1, math.ceil(self.retry_after_s)))

    def pause_s(self) -> float:
        """How long the refusal waits before it is sent: the client's wait, from half a second to one."""
        return min(max(self.retry_after_s, self.MIN_PAUSE_S), self.MAX_PAUSE_S)

    def body(self) -> dict:
        return problem_body(429, self.message, None, self.limit, kind=PROBLEM_TYPES["throttled"])


class ProblemResponse(SafeJSONResponse):
    media_type = PROBLEM_MEDIA_TYPE


async def send_problem(
    send, status: int, message: str, limit: str | None = None, headers: list | None = None, body: dict | None = None
) -> None:
    """A problem answer written straight to an ASGI ``send``: for the middleware that refuses a
    request before the application sees it (no JSON parsing, no thread). ``body``: the problem
    object, if not the one ``status``, ``message`` and ``limit`` make."""
    body = json.dumps(body or problem_body(status, message, None, limit)).encode()
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


def problem(status: int, message: str, field: str | None = None, limit: str | None = None, detail=None, headers=None):
    body = problem_body(status, message, field, limit, detail)
    return ProblemResponse(body, status_code=status, headers=headers)


def input_error_body(error: InputError, field: str | None = None, location: str = "body") -> dict:
    field = field or error.argument
    limit = getattr(error, "limit", None)
    message = f"{field}: {error.reason}"
    detail = [{"loc": [location, short(field)], "field": field, "msg": error.reason, "type": "limit" if limit else "value_error"}]
    kind = "/problems/limit-exceeded" if limit else PROBLEM_TYPES["combination"]
    return problem_body(422, message, field, limit, detail, kind)


def needs_simulation_body(error: InputError) -> dict:
    """A batch entry that needs a simulation (``nlpsf.solve.batch.NeedsSimulation``): a 422 of its own
    type, naming the field that takes it off the tables and where it is answered (``send_to``)."""
    body = input_error_body(error)
    message = short(f"{body['detail']}; send it to POST {SOLVE_ENDPOINT} (a job)", 5 * ECHO_CHARS)
    return {**body, "type": PROBLEM_TYPES["needs_simulation"], "detail": message, "message": message, "send_to": SOLVE_ENDPOINT}


def input_error_response(error: InputError, field: str | None = None, location: str = "body") -> JSONResponse:
    return ProblemResponse(input_error_body(error, field, location), status_code=422)


def _field_of(loc: tuple | list) -> str | None:
    """The request field at fault, dotted for a nested one (``scene.jitter``): the location's field
    names, without list indices and pydantic's tags for union members (``constrained-float``,
    ``MATableSpec``, ``literal[...]``)."""
    import re

    names = [part for part in loc[1:] if isinstance(part, str) and re.fullmatch(r"[a-z_][a-z0-9_]*", part)]
    return ".".join(names) if names else None


def _readable(error: dict[str, Any]) -> str:
    kind = error.get("type", "")
    if kind == "json_invalid":
        return "the request body is not valid JSON"
    if kind == "missing" and tuple(error.get("loc", ())) == ("body",):
        return "a JSON body is required"
    if kind == "model_attributes_type" or kind == "dict_type":
        return "the request body must be a JSON object"
    if kind == "extra_forbidden":
        return "unknown field (check its spelling)"
    if kind == "finite_number":
        return "must be a finite number (NaN and infinity are not allowed)"
    return str(error.get("msg", "invalid value"))


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    return ProblemResponse(validation_problem_body(exc.errors()), status_code=422)


def _the_meant_member(errors: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each member of a union reports its own error: a scene object with a bad position was also
    "not a preset's name". Where some error lies inside a field (``scene.position``), the errors at
    that field itself (the members the input did not take: a name, a number) are dropped, so that
    the message names what is wrong in what was sent. A string sent where an object may go keeps
    the name's error first, as before."""
    fields = [_field_of(e.get("loc", ())) for e in errors]
    nested = {f.rsplit(".", 1)[0] for f in fields if f and "." in f}
    parents = {p for f in nested for p in _ancestors(f)} | nested
    kept = [e for e, f in zip(errors, fields, strict=True) if f not in parents]
    return kept or errors


def _ancestors(field: str) -> list[str]:
    parts = field.split(".")
    return [".".join(parts[:k]) for k in range(1, len(parts))]


def validation_problem_body(errors: Any, prefix: tuple = ()) -> dict:
    """Pydantic's errors as one problem: every bad field (up to ten) in ``errors``."""
    detail = []
    # At most a few entries, each location cut short: a body of a million unknown keys must not
    # come back as a million errors.
    errors = _the_meant_member([{**e, "loc": (*prefix, *e.get("loc", ()))} for e in errors])
    for error in errors[:10]:
        loc = [short(p) if isinstance(p, str) else p if isinstance(p, int) else short(p) for p in error.get("loc", ())]
        detail.append({"loc": loc, "field": _field_of(loc), "msg": _readable(error), "type": str(error.get("type", ""))})
    first = detail[0] if detail else {"field": None, "msg": "invalid request"}
    message = f"{first['field']}: {first['msg']}" if first["field"] else first["msg"]
    if len(detail) > 1:
        others = ", ".join(str(d["field"]) for d in detail[1:] if d["field"])
        message += f" (and {len(errors) - 1:,} more: {others})" if others else f" (and {len(errors) - 1:,} more errors)"
    return problem_body(422, message, first["field"], None, detail)


async def _input_error(request: Request, exc: InputError) -> JSONResponse:
    return input_error_response(exc, location="query" if request.method == "GET" else "body")


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    if exc.status_code == 400:
        # FastAPI's "error parsing the body" (e.g. bytes that are not UTF-8): bad input like any other.
        return problem(422, "the request body is not valid JSON (UTF-8 text expected)", detail=[])
    message = exc.detail if isinstance(exc.detail, str) else json.dumps(exc.detail)
    return problem(exc.status_code, message, headers=getattr(exc, "headers", None))


#: What a 500 says: never the exception's class or text, which name the server's code (the log has them).
INTERNAL_ERROR = "internal error; please report it with the request that caused it"


async def _server_error(request: Request, exc: Exception) -> JSONResponse:
    # This handler answers outside the middleware stack: add its headers here.
    headers = {name.decode(): value.decode() for name, value in SECURITY_HEADERS}
    return problem(500, INTERNAL_ERROR, headers=headers)


async def _model_error(request: Request, exc: ValidationError) -> JSONResponse:
    """A request model a route builds from what it read (a CSV's rows as a batch): its schema's
    refusal is the client's, a 422 naming the field, as FastAPI's own validation gives."""
    return ProblemResponse(validation_problem_body(exc.errors(), ("body",)), status_code=422)


def store_unavailable_response(error: StoreUnavailable) -> JSONResponse:
    """Simulations need the job database; while it is unusable they are refused with the reason."""
    return problem(503, f"simulations are unavailable: {error.reason}", limit=None, headers={"Retry-After": "30"})


async def _store_unavailable(request: Request, exc: StoreUnavailable) -> JSONResponse:
    return store_unavailable_response(exc)


async def _throttled(request: Request, exc: Throttled) -> JSONResponse:
    import asyncio

    await asyncio.sleep(exc.pause_s())  # see budget.refuse
    return ProblemResponse(exc.body(), status_code=429, headers={"Retry-After": exc.retry_after()})


def install(app: FastAPI) -> None:
    app.add_exception_handler(RequestValidationError, _validation_error)  # type: ignore[arg-type]
    app.add_exception_handler(ValidationError, _model_error)  # type: ignore[arg-type]
    app.add_exception_handler(InputError, _input_error)  # type: ignore[arg-type]
    app.add_exception_handler(StoreUnavailable, _store_unavailable)  # type: ignore[arg-type]
    app.add_exception_handler(Throttled, _throttled)  # type: ignore[arg-type]
    app.add_exception_handler(StarletteHTTPException, _http_error)  # type: ignore[arg-type]
    app.add_exception_handler(Exception, _server_error)
