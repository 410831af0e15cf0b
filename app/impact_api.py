"""POST /impact: what each scene effect changes in the slopes at one point (a job like any simulation)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.responses import Response

from nlpsf import defaults, roman

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
    from nlpsf import impact as impact_module

    from .job_kinds import LimitError, build_scene, check_scene_bounds

    limits = services.settings.limits
    arguments = body.model_dump()
    if "realizations" not in body.model_fields_set:
        arguments["realizations"] = max(2, min(arguments["realizations"], limits.max_realizations))
    if arguments["realizations"] > limits.max_realizations:
        raise LimitError(
            "realizations",
            "max_realizations",
            f"asks for {arguments['realizations']:,} realizations; the limit max_realizations is {limits.max_realizations:,}",
        )
    scene_request = arguments.pop("scene")
    scene = build_scene(scene_request)
    check_scene_bounds(scene, defaults.FULL_WELL_E)  # the impact report simulates at the default full well
    wavelengths = scene.wavelengths(roman.check_band(arguments["band"]))
    if wavelengths > limits.max_wavelengths:
        raise LimitError(
            "scene",
            "max_wavelengths",
            f"the scene's SED needs {wavelengths} wavelengths; the limit max_wavelengths is {limits.max_wavelengths}",
        )
    # Everything is checked at table cost here; the simulations run as a job (queue, limits, cache).
    checked = impact_module.check_request(**arguments)
    job_arguments = {**checked, "scene": scene_request, "max_wavelengths": limits.max_wavelengths}
    return await job_answer(services, caller, job_kinds.impact_job(job_arguments))
