"""The calibration capability (docs/calibration.md): a residual nonlinearity in the calibrator's terms.

- POST /calibration/kernel: the response kernel K(Q) of a star (the columns of ``nlpsf kernel``'s ECSV);
- GET /calibration/kernel/{job_id}.ecsv: a finished kernel as that ECSV;
- POST /calibration/residual: what an inline residual (a curve, a polynomial, a shape with its scale, or two
  calibrations' per-pixel polynomials around the star) does to the star's size and ellipticity;
- POST /calibration/requirement: for a residual shape, two of scale, tolerance, magnitude give the third; or
  the envelope eps(Q) over a magnitude range.

The star is given as POST /solve takes it. Each answer is a simulation (about a second for one star), so
each runs as a job like any simulation (``calibration_jobs``): validated completely here first, answered
when it finishes within ``solve_wait_s`` (200), else 202 with the job to poll (its Location). No physics here.
"""

from __future__ import annotations

import asyncio
import io
from typing import Any

from fastapi import APIRouter
from fastapi.responses import Response

from nlpsf.checks import InputError

from . import calibration_models as cm
from . import job_kinds
from .calibration_jobs import KERNEL_KIND, REQUIREMENT_KIND, RESIDUAL_KIND
from .deps import CallerDep, ServicesDep
from .errors import problem
from .params import JOB_ANSWER_RESPONSES
from .simulations import JobId, job_answer

router = APIRouter(prefix="/api/v1/calibration", tags=["calibration"])

_ANSWERS: dict[int | str, dict[str, Any]] = {
    **JOB_ANSWER_RESPONSES,
    200: {"description": "the answer (the Location header names its job: GET /api/v1/simulations/{id})"},
}


async def _answer(kind: str, body, services, caller) -> Response:
    # Validated at table cost (the star as POST /solve reads it, the residual), then a job like any simulation.
    job = job_kinds.KINDS[kind].validate(body.model_dump(), body.model_fields_set, services.settings)
    return await job_answer(services, caller, job)


@router.post(
    "/kernel",
    response_model=cm.KernelResponse,
    responses=_ANSWERS,
    summary="The response kernel K(Q) of a star: how its size and ellipticity respond to a calibration residual at each "
    "charge level (a job)",
)
async def kernel(body: cm.KernelRequest, services: ServicesDep, caller: CallerDep) -> Response:
    return await _answer(KERNEL_KIND, body, services, caller)


@router.get(
    "/kernel/{job_id}.ecsv",
    responses={
        200: {"content": {"text/x-ecsv": {}}, "description": "ECSV (astropy): charge_e and per metric K and its error"},
        404: {"model": cm.models.Problem, "description": "no kernel job with this id"},
        409: {"model": cm.models.Problem, "description": "the kernel is not finished (or failed)"},
        503: {"model": cm.models.Problem},
    },
    summary="A finished kernel as ECSV, the same columns as `nlpsf kernel --output`",
)
async def kernel_ecsv(job_id: JobId, services: ServicesDep) -> Response:
    from nlpsf.calibration.kernel import kernel_table

    job = await asyncio.to_thread(services.store.get, job_id)
    if job is None or (job.get("request") or {}).get("kind") != KERNEL_KIND:
        return problem(404, "no kernel job with this id")
    if job.get("status") != "done" or job.get("result") is None:
        return problem(409, f"the kernel is {job.get('status')}, not done: poll GET /api/v1/simulations/{job_id}")
    result = job["result"]
    try:
        table = kernel_table(result["columns"], result["meta"])
    except (InputError, KeyError):
        return problem(409, "the job's result is not a kernel")
    out = io.StringIO()
    table.write(out, format="ascii.ecsv")
    meta = result["meta"]
    conditions = meta.get("conditions") or {}
    magnitude = meta.get("magnitude")
    where = f"{conditions.get('band', 'band')}-sca{conditions.get('sca', '')}"
    name = f"nlpsf-kernel-{where}-m{magnitude:g}.ecsv" if isinstance(magnitude, (int, float)) else f"nlpsf-kernel-{where}.ecsv"
    return Response(out.getvalue(), media_type="text/x-ecsv", headers={"Content-Disposition": f'attachment; filename="{name}"'})


@router.post(
    "/residual",
    response_model=cm.ResidualResponse,
    responses=_ANSWERS,
    summary="What a calibration residual, given inline, does to a star's size and ellipticity (a job)",
)
async def residual(body: cm.ResidualRequest, services: ServicesDep, caller: CallerDep) -> Response:
    return await _answer(RESIDUAL_KIND, body, services, caller)


@router.post(
    "/requirement",
    response_model=cm.RequirementResponse,
    responses=_ANSWERS,
    summary="For a residual shape: two of scale, tolerance, magnitude give the third, or the envelope eps(Q) (a job)",
)
async def requirement(body: cm.RequirementRequest, services: ServicesDep, caller: CallerDep) -> Response:
    return await _answer(REQUIREMENT_KIND, body, services, caller)
