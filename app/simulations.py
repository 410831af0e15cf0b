"""POST/GET/DELETE /api/v1/simulations: fresh simulations as jobs with progress.

The ``id`` a submission returns is its capability: an unguessable token that reads or cancels that
job and nothing else (identical requests share one run, each with its own id; the run stops when
every holder has cancelled). Listing shows only the caller's jobs (by API key), or every job when
the operator allows it (``list_all_jobs``), and never hands out ids that grant access.
"""

from __future__ import annotations

import asyncio
from typing import Annotated, Any

from fastapi import APIRouter, Path, Query
from fastapi.responses import Response

from nlpsf.checks import InputError

from . import job_kinds, models
from .deps import Caller, CallerDep, Services, ServicesDep
from .errors import SafeJSONResponse, input_error_response, problem
from .store import FINISHED, NotCancellable, QueueFull

router = APIRouter(prefix="/api/v1/simulations", tags=["simulations"])

JobId = Annotated[str, Path(pattern=r"^[0-9a-f]{32}$", description="the job's id as POST returned it (its capability)")]

_PROBLEM = {"model": models.Problem}
_HIDDEN = ("owner", "pid", "attempts")


def job_response(job: dict[str, Any], status: int) -> SafeJSONResponse:
    job = {k: v for k, v in job.items() if k not in _HIDDEN}
    headers = {"Location": f"/api/v1/simulations/{job['id']}"}
    return SafeJSONResponse(job, status_code=status, headers=headers)


async def submit_job(services: Services, caller: Caller, normalised: dict[str, Any], wait: float) -> tuple[dict[str, Any], int]:
    """Queue (or answer from stored results, or join) a validated job request and wait up to ``wait``
    seconds for it; returns the job as its submitter sees it and the HTTP status (200 finished, 202 not).
    Raises QueueFull (a 429) and StoreUnavailable (503, by the app's handler)."""
    key = job_kinds.request_hash(normalised)
    settings = services.settings
    job, _how = await asyncio.to_thread(
        services.store.submit, normalised, key, settings.max_queue, caller.share, settings.queue_per_client
    )
    services.dispatcher.wake()
    if job["status"] not in FINISHED:
        finished = await services.notifier.wait(job["id"], min(wait, settings.max_wait_s))
        if finished:
            job = await asyncio.to_thread(services.store.get, job["id"]) or job
    return job, 200 if job["status"] in FINISHED else 202


def queue_full_response(full: QueueFull) -> Response:
    """429 naming the limit hit (max_queue: the whole queue; max_queue_per_client: this client's share)."""
    mine = full.setting == "max_queue_per_client"
    what = "your share of the simulation queue is full" if mine else "the simulation queue is full"
    return problem(429, f"{what}: {full}", limit=full.setting, headers={"Retry-After": "10"})


async def job_answer(services: Services, caller: Caller, job_request: dict[str, Any], wait: float | None = None) -> Response:
    """Submit a job and answer with its result when it finishes within ``wait`` seconds (None: the
    deployment's ``solve_wait_s``) (200), with its input error (422), its failure (500) or its
    cancellation (503), or with the job to poll (202)."""
    wait = services.settings.solve_wait_s if wait is None else wait
    try:
        job, status = await submit_job(services, caller, job_request, wait)
    except QueueFull as full:
        return queue_full_response(full)
    if job.get("status") == "done" and job.get("result") is not None:
        return SafeJSONResponse(job["result"], headers={"Location": f"/api/v1/simulations/{job['id']}"})
    location = {"Location": f"/api/v1/simulations/{job['id']}"}
    if job.get("status") == "failed" and (job.get("error") or {}).get("field"):
        error = job["error"]
        return problem(422, f"{error['field']}: {error['message']}", error["field"], limit=error.get("limit"), headers=location)
    if job.get("status") == "failed":
        return problem(500, f"the simulation failed: {job.get('message') or 'no reason given'}", headers=location)
    if job.get("status") in ("cancelled", "interrupted"):
        return problem(503, f"the simulation was {job['status']}: {job.get('message') or ''}".rstrip(": "), headers=location)
    return job_response(job, status)


@router.post(
    "",
    status_code=202,
    response_model=models.Job,
    responses={
        200: {"model": models.Job, "description": "finished: answered from stored results, or within `wait`"},
        202: {"model": models.Job, "description": "accepted: queued or running; poll the Location"},
        413: {**_PROBLEM, "description": "the request body is larger than max_body_bytes"},
        422: {**_PROBLEM, "description": "invalid input or over a work limit (the limit is named)"},
        429: {**_PROBLEM, "description": "the queue is full; retry later (Retry-After)"},
        503: {**_PROBLEM, "description": "the job store is unavailable (the reason is given); the calculator still answers"},
    },
    summary="Start a fresh simulation; returns a job id at once (or the result, if known or quick)",
)
async def submit(
    body: models.SimulationRequest,
    services: ServicesDep,
    caller: CallerDep,
    wait: Annotated[float, Query(ge=0, le=600, allow_inf_nan=False, description="time to wait for the result, in s")] = 0.0,
) -> Response:
    settings = services.settings
    try:
        normalised = job_kinds.KINDS[job_kinds.SIMULATION_KIND].validate(body.model_dump(), body.model_fields_set, settings)
    except InputError as error:
        return input_error_response(error, job_kinds.request_field(error.argument))
    try:
        job, status = await submit_job(services, caller, normalised, wait)
    except QueueFull as full:
        return queue_full_response(full)
    return job_response(job, status)


@router.get(
    "",
    response_model=models.JobList,
    responses={503: _PROBLEM},
    summary="The caller's recent simulation jobs (by API key; every job if the operator allows), without results",
)
async def list_jobs(
    services: ServicesDep,
    caller: CallerDep,
    limit: Annotated[int, Query(ge=1, le=500, description="most jobs to list (count)")] = 50,
) -> SafeJSONResponse:
    store = services.store
    everyone = services.settings.list_all_jobs
    jobs = await asyncio.to_thread(store.list, caller.key, everyone, limit)
    counts = await asyncio.to_thread(store.counts, caller.key, everyone)
    return SafeJSONResponse({"jobs": [{k: v for k, v in j.items() if k not in _HIDDEN} for j in jobs], "counts": counts})


@router.get(
    "/{job_id}",
    response_model=models.Job,
    responses={404: _PROBLEM, 503: _PROBLEM},
    summary="Status and progress of a job; the result once it is done",
)
async def get_job(job_id: JobId, services: ServicesDep) -> Response:
    job = await asyncio.to_thread(services.store.get, job_id)
    if job is None:
        return problem(404, "no simulation job with this id")
    return job_response(job, 200)


@router.delete(
    "/{job_id}",
    response_model=models.Job,
    responses={404: _PROBLEM, 409: {**_PROBLEM, "description": "the job has already finished"}, 503: _PROBLEM},
    summary="Cancel a queued or running job",
)
async def cancel_job(job_id: JobId, services: ServicesDep) -> Response:
    store = services.store
    try:
        job = await asyncio.to_thread(store.cancel, job_id)
    except NotCancellable as error:
        return problem(409, str(error))
    if job is None:
        return problem(404, "no simulation job with this id")
    services.dispatcher.wake()
    # The owner stops a running job within a poll or two; wait briefly so the answer is final.
    if job["status"] not in FINISHED and await services.notifier.wait(job_id, 5.0):
        job = await asyncio.to_thread(store.get, job_id) or job
    return job_response(job, 200)
