"""The calculator: POST /solve (two of precision, tolerance, magnitude -> the third) and
POST /solve/batch (many solves at table cost: the tables and the Roman default's field grid).

What they answer inline is budgeted per client (``budget``): each answer's cost is estimated in
units before it runs -- a field-grid node read per position the answer looks at (the Roman default
at a position: one; its SCA range without one: every node of the SCA), a table solve otherwise --
reserved against the client's share (429 with Retry-After past it) and charged as measured. Answers
from the field grid are kept by request (``budget.AnswerCache``), so a repeated one is a look-up.
"""

from __future__ import annotations

import functools
import json
import logging
from typing import Annotated, Any

from fastapi import APIRouter, Query
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from nlpsf import defaults
from nlpsf.checks import InputError
from nlpsf.solve import batch, over_field, solver

from . import budget, job_kinds, job_parts, models
from .deps import CallerDep, ServicesDep
from .errors import SafeJSONResponse, render_json
from .params import ERRORS, JOB_ANSWER_RESPONSES
from .simulations import job_answer

log = logging.getLogger("nlpsf.web")
router = APIRouter(prefix="/api/v1")

#: Points of the field-point tables an over-field answer reads on each SCA (its centre and corners).
OVER_FIELD_POINTS = 5


def answer_key(fields: dict[str, Any], given: set[str]) -> str:
    """A request's answer is a pure function of this (for the tables and the field grid: the shipped
    data and the code are the process's own): its fields as the library reads them, canonically."""
    return json.dumps(job_parts.solve_body(fields, given), sort_keys=True, separators=(",", ":"), default=str)


def units_of(request) -> tuple[str, float]:
    """(kind, units) of inline work answering ``request`` costs: field-grid nodes for the Roman
    default (every node of the SCA without a position), one table solve otherwise."""
    from nlpsf.solve.over_field import range_positions

    if request.policy.field_grid:
        if request.policy.ranges_over_sca and (request.scene is None or request.scene.position is None):
            return budget.NODE, float(len(range_positions(request)))
        return budget.NODE, 1.0
    return budget.TABLE, 1.0


def _answer_inline(request, kind: str, units: float) -> bytes:
    """``batch.answer_from_tables`` (raises ``NeedsSimulation``), metered, as the JSON body it answers
    (rendered once: kept so, a repeated request is sent the same bytes without serialising again)."""
    with budget.metered(kind, units):
        return render_json(batch.answer_from_tables(request).to_dict())


def _keep(key: str, answer: bytes) -> None:
    if (work := budget.active()) is not None:
        work.budget.answers.put(("solve", key), answer, len(answer))


def _kept(key: str) -> bytes | None:
    work = budget.active()
    return work.budget.answers.get(("solve", key)) if work is not None else None


def _json(body: bytes) -> Response:
    """A kept answer's JSON body, as ``SafeJSONResponse`` rendered it."""
    return Response(content=body, media_type=SafeJSONResponse.media_type)


@router.post(
    "/solve",
    response_model=models.SolveResponse,
    responses=JOB_ANSWER_RESPONSES,
    summary="Two of (precision, tolerance, magnitude) -> the third, with its uncertainty",
)
async def solve(
    body: models.SolveRequest,
    services: ServicesDep,
    caller: CallerDep,
    wait: Annotated[
        float | None,
        Query(
            ge=0,
            le=600,
            allow_inf_nan=False,
            description="for an answer that needs a simulation: time to wait for it before the job to poll is returned "
            "(202), in s; default the deployment's solve_wait_s (a page that shows progress asks for less)",
        ),
    ] = None,
) -> Response:
    # A table solve takes microseconds and runs on the event loop (a thread hop would cost more).
    raw = body.model_dump()
    key = answer_key(raw, body.model_fields_set) if body.over_field is None else None
    if key is not None and (kept := _kept(key)) is not None:
        return _json(kept)  # answered before (a valid request, kept by its fields as the library reads them)
    # The library's typed request checks every field, the ramp and the scene (and whether they combine).
    request = job_parts.solve_request(job_parts.solve_body(raw, body.model_fields_set))
    # Another pupil-scale rule than the tables' is simulated: a job, like a scene or a ramp.
    tables_pupil = request.pupil_scale in (None, defaults.PUPIL_SCALE)
    plain = request.ramp is None and request.scene is None and body.over_field is None and tables_pupil
    refused = False
    if plain and request.fidelity in (None, "table") and request.accuracy is None:
        # Microseconds: charged, never refused (a client past its share keeps its table solves). The
        # batch's answer, which refuses what the tables do not hold (another linearisation state is
        # simulated): that is a job, below, never seconds inside this HTTP worker.
        try:
            with budget.metered(budget.TABLE, 1.0):
                return SafeJSONResponse(batch.answer_from_tables(request).to_dict())
        except batch.NeedsSimulation:
            refused = True  # not asked again below
    if body.over_field is None and not refused:
        # Whatever the tables or the Roman default's field grid answer is answered here, whatever the
        # scene: the cost of the answer decides, not its name. The batch's own check and answer
        # (``batch.answer_from_tables``: the plan read first, a simulation refused before it starts),
        # on the event loop like a table solve (a range over the SCA reads its nodes at once: about a
        # millisecond; a thread hop cost the service half its default throughput), one at a time per
        # worker (the turn), not a job; kept by request, and budgeted against the client's share of
        # the inline CPU.
        kind, units = units_of(request)
        budget.admit(kind, units)
        try:
            async with budget.turn():
                if (kept := _kept(key)) is None:  # answered while this request waited its turn?
                    kept = _answer_inline(request, kind, units)
                    _keep(key, kept)
        except batch.NeedsSimulation:
            pass  # it needs a fresh simulation: a job, below
        else:
            return _json(kept)
    over_field_tables = over_field.over_field_from_tables(request.scene, request.fidelity, request.accuracy, request.ramp)
    if tables_pupil and body.over_field is not None and over_field_tables:
        # The worst field point from the shipped field-point tables: up to 90 table solves, a few
        # tens of milliseconds, so off the event loop but not a job.
        rest = job_kinds.request_arguments(request)
        band, sca = rest.pop("band"), rest.pop("sca")
        scas = "all" if body.over_field == "focal_plane" else [sca]
        units = float(OVER_FIELD_POINTS * (18 if scas == "all" else 1))
        budget.admit(budget.TABLE, units)

        def worst() -> dict[str, Any]:
            with budget.metered(budget.TABLE, units):
                return solver.solve_over_field(band, scas, filled_for=sca, **rest).to_dict()

        async with budget.turn():
            return SafeJSONResponse(await run_in_threadpool(worst))
    # What remains -- a simulating level, an accuracy (its effects are measured by simulation even
    # when the table level meets it), a ramp, scene, exposure or rule neither the tables nor the
    # field grid hold, or an over-field answer the field-point tables do not hold -- is a job like
    # any other simulation (queue, limits, idle priority), validated completely at table cost first,
    # never work inside this HTTP worker.
    job = job_kinds.KINDS[job_kinds.SOLVE_KIND].validate(raw, body.model_fields_set, services.settings)
    return await job_answer(services, caller, job, wait)


@router.post(
    "/solve/batch",
    response_model=models.BatchSolveResponse,
    responses={
        **ERRORS,
        413: {"model": models.Problem, "description": "the request body is larger than max_body_bytes"},
        429: {"model": models.Problem, "description": "your share of the inline CPU is used; retry after Retry-After"},
    },
    summary="Many solves at table cost (the tables, the Roman default's field grid); each answered or refused on its own",
)
def solve_batch(body: models.BatchSolveRequest) -> Response:
    """Every entry read first (a bad one refused in its own entry), the batch's cost estimated from
    its entries' units (an entry already answered, or repeated in the batch, costs nothing) and
    admitted as one against the client's share -- more than a client's whole budget is a 422 naming
    ``inline_cpu_burst_s``, more than its balance a 429 -- then every entry answered."""
    rows = body.requests
    work = budget.active()
    if work is not None:
        # Estimated from the rows as sent, before any is read (reading 600 rows is itself 0.1 s): each
        # distinct row's units, and every row's reading.
        costs = work.budget.costs
        distinct = {json.dumps(row, sort_keys=True, default=str): row for row in rows}
        total = costs.estimate(budget.ROW, len(rows)) + sum(costs.estimate(*_sent_units(row)) for row in distinct.values())
        work.budget.check_size(total, "requests", f"this batch of {len(rows):,} requests")
        work.budget.admit(work.meter, total)
    with budget.turn_in_thread():
        with budget.metered(budget.ROW, len(rows)):
            entries = [_read_one(index, item) for index, item in enumerate(rows)]
        results = [_answer_one(entry) for entry in entries]
    answered = sum(1 for r in results if r["ok"])
    return _json(_batch_body(results, answered))


def _batch_body(results: list[dict[str, Any]], answered: int) -> bytes:
    """``SafeJSONResponse``'s rendering of {"results", "answered", "failed"}, byte for byte, with each
    answer's kept JSON body put in as it was rendered (not parsed and serialised again)."""
    rows = [
        b'{"index":%d,"ok":true,"solution":%s}' % (r["index"], r["solution"])
        if isinstance(r.get("solution"), bytes)
        else SafeJSONResponse(r).body
        for r in results
    ]
    return b'{"results":[%s],"answered":%d,"failed":%d}' % (b",".join(rows), answered, len(results) - answered)


def _sent_units(row: Any) -> tuple[str, float]:
    """:func:`units_of` a batch row as sent, before it is read: the paper's scene (or another preset,
    refused in its entry) a table solve; the Roman default one node at a position, every node of its
    SCA without one."""
    from nlpsf.request import presets

    scene = row.get("scene") if isinstance(row, dict) else None
    preset = scene if isinstance(scene, str) else scene.get("preset") if isinstance(scene, dict) else None
    name = presets.preset_of(None) if preset is None else presets.named(preset)  # None: not a preset, refused in its entry
    if name is None or not presets.policy(name).field_grid:
        return budget.TABLE, 1.0
    if isinstance(scene, dict) and scene.get("position") is not None:
        return budget.NODE, 1.0
    return budget.NODE, _range_nodes(str(row.get("band", "")).upper(), str(row.get("sca") or defaults.SCA))


@functools.lru_cache(maxsize=1024)
def _range_nodes(band: str, sca: str) -> float:
    """How many nodes the SCA range of (band, SCA) reads (as sent: a bad one gets the 3 x 3 grid's)."""
    from types import SimpleNamespace

    from nlpsf.solve.over_field import RANGE_GRID, range_positions

    try:
        return float(len(range_positions(SimpleNamespace(band=band, sca=int(float(sca))))))
    except (TypeError, ValueError, KeyError, OverflowError):
        return float(RANGE_GRID**2)


def _read_one(index: int, item: dict[str, Any]) -> dict[str, Any]:
    """One batch entry read into the same typed request as POST /solve (``request``, its answer's
    ``key`` and its cost's ``units``), or its refusal as a finished result (``result``)."""
    from pydantic import ValidationError

    from .errors import input_error_body, validation_problem_body

    try:
        model = models.SolveRequest.model_validate(item)
    except ValidationError as invalid:
        return {"result": {"index": index, "ok": False, "error": validation_problem_body(invalid.errors(), ("body",))}}
    try:
        if model.over_field is not None:
            raise InputError("over_field", "a batch solves one position at a time: send over-field solves to POST /solve")
        raw = model.model_dump()
        request = job_parts.solve_request(job_parts.solve_body(raw, model.model_fields_set))
        return {"index": index, "request": request, "key": answer_key(raw, model.model_fields_set), "units": units_of(request)}
    except InputError as error:
        return {"result": {"index": index, "ok": False, "error": input_error_body(error)}}


def _answer_one(entry: dict[str, Any]) -> dict[str, Any]:
    """One batch entry: answered by the library where the tables or the Roman default's field grid
    hold it (``nlpsf.solve.batch.answer_from_tables``: the very ``solver.answer`` a single solve runs),
    refused on its own otherwise."""
    from nlpsf.checks import SimulationError

    from .errors import INTERNAL_ERROR, input_error_body, needs_simulation_body, problem_body

    if "result" in entry:
        return entry["result"]
    index = entry["index"]
    try:
        if (kept := _kept(entry["key"])) is not None:
            return {"index": index, "ok": True, "solution": kept}
        answer = _answer_inline(entry["request"], *entry["units"])
        _keep(entry["key"], answer)
        return {"index": index, "ok": True, "solution": answer}
    except batch.NeedsSimulation as error:
        return {"index": index, "ok": False, "error": needs_simulation_body(error)}
    except InputError as error:
        return {"index": index, "ok": False, "error": input_error_body(error)}
    except SimulationError as error:
        # Not the request's fault (e.g. missing shipped data): a server error for this item.
        return {"index": index, "ok": False, "error": problem_body(500, str(error))}
    except Exception:  # a fault in one entry must not fail the others
        log.exception("batch entry %d", index)
        return {"index": index, "ok": False, "error": problem_body(500, INTERNAL_ERROR)}
