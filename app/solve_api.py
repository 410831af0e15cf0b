"""The calculator: POST /solve (two of precision, tolerance, magnitude -> the third) and
POST /solve/batch (many solves at table cost: the tables and the Roman default's field grid)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from nlpsf import defaults
from nlpsf.checks import InputError
from nlpsf.serialise import json_safe
from nlpsf.solve import batch, over_field, solver

from . import job_kinds, models
from .deps import CallerDep, ServicesDep
from .errors import SafeJSONResponse
from .params import ERRORS, JOB_ANSWER_RESPONSES
from .simulations import job_answer

router = APIRouter(prefix="/api/v1")


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
    # The library's typed request checks every field, the ramp and the scene (and whether they combine).
    raw = body.model_dump()
    request = job_kinds.solve_request(job_kinds.solve_body(raw, body.model_fields_set))
    # Another pupil-scale rule than the tables' is simulated: a job, like a scene or a ramp.
    tables_pupil = request.pupil_scale in (None, defaults.PUPIL_SCALE)
    plain = request.ramp is None and request.scene is None and body.over_field is None and tables_pupil
    if plain and request.fidelity in (None, "table") and request.accuracy is None:
        return SafeJSONResponse(solver.answer(request).to_dict())
    if body.over_field is None:
        # Whatever the tables or the Roman default's field grid answer is answered here, whatever the
        # scene: the cost of the answer decides, not its name. The batch's own check and answer
        # (``batch.answer_from_tables``: the plan read first, a simulation refused before it starts),
        # on the event loop like a table solve (a range over the SCA reads its nodes at once: about a
        # millisecond; a thread hop cost the service half its default throughput), not a job.
        try:
            answer = batch.answer_from_tables(request)
        except batch.NeedsSimulation:
            pass  # it needs a fresh simulation: a job, below
        else:
            return SafeJSONResponse(answer.to_dict())
    over_field_tables = over_field.over_field_from_tables(request.scene, request.fidelity, request.accuracy, request.ramp)
    if tables_pupil and body.over_field is not None and over_field_tables:
        # The worst field point from the shipped field-point tables: up to 90 table solves, a few
        # tens of milliseconds, so off the event loop but not a job.
        rest = job_kinds.request_arguments(request)
        band, sca = rest.pop("band"), rest.pop("sca")
        scas = "all" if body.over_field == "focal_plane" else [sca]
        answer = await run_in_threadpool(solver.solve_over_field, band, scas, filled_for=sca, **rest)
        return SafeJSONResponse(answer.to_dict())
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
    responses={**ERRORS, 413: {"model": models.Problem, "description": "the request body is larger than max_body_bytes"}},
    summary="Many solves at table cost (the tables, the Roman default's field grid); each answered or refused on its own",
)
def solve_batch(body: models.BatchSolveRequest) -> SafeJSONResponse:
    results = [_solve_one(index, item) for index, item in enumerate(body.requests)]
    answered = sum(1 for r in results if r["ok"])
    return SafeJSONResponse({"results": results, "answered": answered, "failed": len(results) - answered})


def _solve_one(index: int, item: dict[str, Any]) -> dict[str, Any]:
    """One batch entry: the same typed request as POST /solve, answered by the library where the
    tables or the Roman default's field grid hold it (``nlpsf.solve.batch.answer_from_tables``: the very
    ``solver.answer`` a single solve runs), refused on its own otherwise."""
    from pydantic import ValidationError

    from nlpsf.checks import SimulationError

    from .errors import input_error_body, needs_simulation_body, problem_body, validation_problem_body

    try:
        request = models.SolveRequest.model_validate(item)
    except ValidationError as invalid:
        return {"index": index, "ok": False, "error": validation_problem_body(invalid.errors(), ("body",))}
    try:
        if request.over_field is not None:
            raise InputError("over_field", "a batch solves one position at a time: send over-field solves to POST /solve")
        solve = job_kinds.solve_request(job_kinds.solve_body(request.model_dump(), request.model_fields_set))
        return {"index": index, "ok": True, "solution": json_safe(batch.answer_from_tables(solve).to_dict())}
    except batch.NeedsSimulation as error:
        return {"index": index, "ok": False, "error": needs_simulation_body(error)}
    except InputError as error:
        return {"index": index, "ok": False, "error": input_error_body(error)}
    except SimulationError as error:
        # Not the request's fault (e.g. missing shipped data): a server error for this item.
        return {"index": index, "ok": False, "error": problem_body(500, str(error))}
    except Exception as error:  # a fault in one entry must not fail the others
        message = f"internal error ({type(error).__name__}); please report it with the request that caused it"
        return {"index": index, "ok": False, "error": problem_body(500, message)}
