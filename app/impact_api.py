"""POST /impact: what each scene effect changes in the slopes at one point (a job like any simulation)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import Response

from . import job_kinds, models
from .deps import CallerDep, ServicesDep
from .params import JOB_ANSWER_RESPONSES
from .simulations import job_answer

router = APIRouter(prefix="/api/v1")


@router.post(
    "/impact",
    response_model=models.ImpactReport,
    responses=JOB_ANSWER_RESPONSES,
    summary="What each scene effect changes in the slopes at one point (linear response; a job like any simulation)",
)
async def impact(body: models.ImpactRequest, services: ServicesDep, caller: CallerDep) -> Response:
    # Everything is checked at table cost here; the simulations run as a job (queue, limits, cache).
    job = job_kinds.KINDS[job_kinds.IMPACT_KIND].validate(body.model_dump(), body.model_fields_set, services.settings)
    return await job_answer(services, caller, job)
