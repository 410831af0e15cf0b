"""The calculator: POST /solve (two of precision, tolerance, magnitude -> the third) and
POST /solve/batch (many table solves)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from nlpsf import defaults, solver
from nlpsf.checks import InputError

from . import job_kinds, models
from .deps import CallerDep, ServicesDep
from .errors import SafeJSONResponse, json_safe
from .params import ERRORS, JOB_ANSWER_RESPONSES
from .simulations import job_answer

router = APIRouter(prefix="/api/v1")


@router.post(
    "/solve",
    response_model=models.SolveResponse,
    responses=JOB_ANSWER_RESPONSES,
    summary="Two of (precision, tolerance, magnitude) -> the third, with its uncertainty",
)
async def solve(body: models.SolveRequest, services: ServicesDep, caller: CallerDep) -> Response:
    # A table solve takes microseconds and runs on the event loop (a thread hop would cost more).
    ramp_keys = ("ramp", "ma_table", "ramp_fit", "read_noise")
    scene_keys = ("scene", "over_field")
    raw = body.model_dump()
    arguments = {k: v for k, v in raw.items() if k not in ramp_keys and k not in scene_keys}
    ramp, arguments["exptime"] = body.ramp_arguments(body.exptime, body.sca)  # validates the ramp
    from .job_kinds import build_scene, check_scene_bounds

    scene = build_scene(raw["scene"]) if raw["scene"] is not None else None  # validates the scene
    if scene is not None:
        check_scene_bounds(scene, body.full_well)
    if scene is not None and ramp is not None:
        raise InputError("scene", "a scene and a ramp cannot be combined yet; give one of them")
    # Another pupil-scale rule than the tables' is simulated: a job, like a scene or a ramp.
    tables_pupil = body.pupil_scale in (None, defaults.PUPIL_SCALE)
    plain = ramp is None and scene is None and body.over_field is None and tables_pupil
    if plain and body.fidelity in (None, "table") and body.accuracy is None:
        return SafeJSONResponse(solver.solve(**arguments).to_dict())
    if tables_pupil and body.over_field is not None and solver.over_field_from_tables(scene, body.fidelity, body.accuracy, ramp):
        # The worst field point from the shipped field-point tables: up to 90 table solves, a few
        # tens of milliseconds, so off the event loop but not a job.
        scas = "all" if body.over_field == "focal_plane" else [body.sca]
        rest = {k: v for k, v in arguments.items() if k not in ("band", "sca")}
        answer = await run_in_threadpool(solver.solve_over_field, body.band, scas, **rest)
        return SafeJSONResponse(answer.to_dict())
    # What remains -- a simulating level, an accuracy (its effects are measured by simulation even
    # when the table level meets it), a ramp, a scene, or an over-field answer the field-point tables
    # do not hold -- is a job like any other simulation (queue, limits, idle priority), validated
    # completely at table cost first, never work inside this HTTP worker.
    job = job_kinds.KINDS[job_kinds.SOLVE_KIND].validate(raw, body.model_fields_set, services.settings)
    return await job_answer(services, caller, job)


@router.post(
    "/solve/batch",
    response_model=models.BatchSolveResponse,
    responses={**ERRORS, 413: {"model": models.Problem, "description": "the request body is larger than max_body_bytes"}},
    summary="Many table solves in one call; each request is answered or refused on its own",
)
def solve_batch(body: models.BatchSolveRequest) -> SafeJSONResponse:
    results = [_solve_one(index, item) for index, item in enumerate(body.requests)]
    answered = sum(1 for r in results if r["ok"])
    return SafeJSONResponse({"results": results, "answered": answered, "failed": len(results) - answered})


def _solve_one(index: int, item: dict[str, Any]) -> dict[str, Any]:
    from pydantic import ValidationError

    from nlpsf.checks import SimulationError

    from .errors import input_error_body, problem_body, validation_problem_body

    try:
        request = models.SolveRequest.model_validate(item)
    except ValidationError as invalid:
        return {"index": index, "ok": False, "error": validation_problem_body(invalid.errors(), ("body",))}
    raw = request.model_dump()
    job_only = ("ramp", "ma_table", "ramp_fit", "read_noise", "scene", "over_field")
    arguments = {k: v for k, v in raw.items() if k not in job_only}
    try:
        ramp, arguments["exptime"] = request.ramp_arguments(request.exptime, request.sca)
        for name in ("scene", "over_field"):
            if raw[name] is not None:
                raise InputError(name, "a batch solves from the tables only: send scenes and over-field solves to POST /solve")
        simulating = request.fidelity not in (None, "table") or request.pupil_scale not in (None, defaults.PUPIL_SCALE)
        if ramp is not None or simulating or request.accuracy is not None:
            # A batch answers at table cost; a simulating solve is a job (POST /solve), one at a time.
            raise InputError("fidelity", "a batch solves from the tables only: send ramps and simulating levels to POST /solve")
        return {"index": index, "ok": True, "solution": json_safe(solver.solve(**arguments).to_dict())}
    except InputError as error:
        return {"index": index, "ok": False, "error": input_error_body(error)}
    except SimulationError as error:
        # Not the request's fault (e.g. missing shipped data): a server error for this item.
        return {"index": index, "ok": False, "error": problem_body(500, str(error))}
