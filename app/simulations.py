"""POST/GET/DELETE /api/v1/simulations: fresh simulations as jobs with progress."""

from __future__ import annotations

import asyncio
import time
from typing import Annotated, Any

from fastapi import APIRouter, Path, Query, Request
from fastapi.responses import Response

from nlpsf.checks import InputError

from . import models, simulation
from .errors import SafeJSONResponse, input_error_response, problem
from .store import FINISHED, NotCancellable, QueueFull

router = APIRouter(prefix="/api/v1/simulations", tags=["simulations"])

JobId = Annotated[str, Path(pattern=r"^[0-9a-f]{32}$", description="job id returned by POST")]

_PROBLEM = {"model": models.Problem}


def _job_response(job: dict[str, Any], status: int) -> SafeJSONResponse:
    job = {k: v for k, v in job.items() if k not in ("owner", "pid")}
    headers = {"Location": f"/api/v1/simulations/{job['id']}"}
    return SafeJSONResponse(job, status_code=status, headers=headers)


@router.post(
    "",
    status_code=202,
    response_model=models.Job,
    responses={
        200: {"model": models.Job, "description": "finished: answered from stored results, or within `wait`"},
        202: {"model": models.Job, "description": "accepted: queued or running; poll the Location"},
        422: {**_PROBLEM, "description": "invalid input or over a work limit (the limit is named)"},
        429: {**_PROBLEM, "description": "the queue is full; retry later (Retry-After)"},
    },
    summary="Start a fresh simulation; returns a job id at once (or the result, if known or quick)",
)
async def submit(
    body: models.SimulationRequest,
    request: Request,
    wait: Annotated[float, Query(ge=0, le=600, allow_inf_nan=False, description="seconds to wait for the result")] = 0.0,
) -> Response:
    app = request.app
    try:
        payload = body.model_dump()
        if body.ma_table is not None and "exptime" not in body.model_fields_set:
            payload["exptime"] = None  # an MA table's exposure is its last read
        normalised = simulation.validate(payload, app.state.settings.limits)
    except InputError as error:
        return input_error_response(error, simulation.request_field(error.argument))
    key = simulation.request_hash(normalised)
    try:
        job, _how = await asyncio.to_thread(app.state.store.submit, normalised, key, app.state.settings.max_queue)
    except QueueFull as full:
        return problem(429, f"the simulation queue is full: {full}", limit="max_queue", headers={"Retry-After": "10"})
    app.state.dispatcher.wake()
    deadline = time.monotonic() + min(wait, app.state.settings.max_wait_s)
    while job["status"] not in FINISHED and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
        job = await asyncio.to_thread(app.state.store.get, job["id"]) or job
    if job["status"] == "done" and job["result"] is None:
        job = await asyncio.to_thread(app.state.store.get, job["id"]) or job
    return _job_response(job, 200 if job["status"] in FINISHED else 202)


@router.get("", response_model=models.JobList, summary="Recent simulation jobs (without their results)")
async def list_jobs(request: Request, limit: Annotated[int, Query(ge=1, le=500)] = 50) -> SafeJSONResponse:
    store = request.app.state.store
    jobs = await asyncio.to_thread(store.list, limit)
    counts = await asyncio.to_thread(store.counts)
    return SafeJSONResponse({"jobs": [{k: v for k, v in j.items() if k not in ("owner", "pid")} for j in jobs], "counts": counts})


@router.get(
    "/{job_id}",
    response_model=models.Job,
    responses={404: _PROBLEM},
    summary="Status and progress of a job; the result once it is done",
)
async def get_job(job_id: JobId, request: Request) -> Response:
    job = await asyncio.to_thread(request.app.state.store.get, job_id)
    if job is None:
        return problem(404, f"no simulation job {job_id}")
    return _job_response(job, 200)


@router.delete(
    "/{job_id}",
    response_model=models.Job,
    responses={404: _PROBLEM, 409: {**_PROBLEM, "description": "the job has already finished"}},
    summary="Cancel a queued or running job",
)
async def cancel_job(job_id: JobId, request: Request) -> Response:
    store = request.app.state.store
    try:
        job = await asyncio.to_thread(store.cancel, job_id)
    except NotCancellable as error:
        return problem(409, str(error))
    if job is None:
        return problem(404, f"no simulation job {job_id}")
    request.app.state.dispatcher.wake()
    # The owner stops a running job within a poll or two; wait briefly so the answer is final.
    deadline = time.monotonic() + 5.0
    while job["status"] not in FINISHED and time.monotonic() < deadline:
        await asyncio.sleep(0.05)
        job = await asyncio.to_thread(store.get, job_id) or job
    return _job_response(job, 200)
