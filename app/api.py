"""The read-only endpoints: health, metadata, the calculator, tables, curves and the paper's data."""

from __future__ import annotations

import csv
import io
import math
from pathlib import PurePath
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool

from nlpsf import __version__, defaults, detector, fidelity, roman, solver, tables
from nlpsf.checks import InputError

from . import liveness, models, simulation
from .errors import SafeJSONResponse, input_error_response, json_safe, problem
from .store import QueueFull

router = APIRouter(prefix="/api/v1")

ERRORS: dict[int | str, dict[str, Any]] = {422: {"model": models.Problem, "description": "invalid input; names the field"}}

Band = Annotated[models.Band, Query(description=f"Roman band (no unit): {', '.join(roman.BANDS)}")]
Sca = Annotated[int, Query(ge=1, le=roman.N_SCA, description=f"detector (SCA number, no unit) 1-{roman.N_SCA}")]
Magnitude = Annotated[float, Query(allow_inf_nan=False, description="star magnitude in AB mag")]
Exptime = Annotated[float, Query(allow_inf_nan=False, description="exposure time in s")]
Beta0 = Annotated[float, Query(allow_inf_nan=False, description="NL coefficient beta0 in 1/e- (paper convention)")]
FullWell = Annotated[float, Query(allow_inf_nan=False, description="full-well depth in e-")]
OptionalBand = Annotated[models.Band | None, Query(description="Roman band (no unit); default all")]
OptionalSca = Annotated[
    int | None, Query(ge=1, le=roman.N_SCA, description=f"detector (SCA number, no unit) 1-{roman.N_SCA}; default all")
]
MetricQuery = Annotated[models.Metric, Query(description="the PSF metric (no unit): size (dR/R), e1, e2 or e (|de|)")]
ModeQuery = Annotated[models.Mode, Query(description="bias or scatter (no unit)")]
Points = Annotated[int, Query(ge=2, le=1000, description="number of grid points (count)")]


@router.get(
    "/health",
    response_model=models.Health,
    summary="Liveness: 200 when the service answers; 'degraded' (with the reason) when simulations cannot run",
)
async def health(request: Request) -> dict[str, Any]:
    # No I/O here: the job store's state is kept by the dispatcher's heartbeat (every 1 s, with an integrity check).
    store = getattr(request.app.state, "store", None)
    job_store = store.status() if store is not None else {"state": "starting", "reason": None, "since": None}
    workers = liveness.report()  # None when no supervisor runs this process
    stalled = bool(workers and workers["stalled"])
    return {
        "status": "ok" if job_store["state"] == "ok" and not stalled else "degraded",
        "version": __version__,
        "calculator": "ok",
        "job_store": job_store,
        "http_workers": workers,
    }


def public_table_meta(meta: dict[str, Any]) -> dict[str, Any]:
    """The tables' metadata without the server's file system: a source path becomes its file name."""
    out = json_safe(meta)
    if "source" in out:
        out["source"] = PurePath(str(out["source"])).name
    return out


def _ma_table_summary(name: str) -> dict:
    table = models.shipped_ma_table(name)
    return {
        "name": name,
        "resultants": table.n_resultants,
        "reads": table.n_reads,
        "frame_time_s": table.frame_time_s,
        "last_read_s": table.duration_s,
        "first_resultant_end_s": table.resultants[0][-1] * table.frame_time_s,
        "source": table.source,
    }


@router.get("/meta", response_model=models.Meta, summary="Bands, SCAs, metrics, defaults, limits, data and code versions")
def meta(request: Request) -> SafeJSONResponse:
    settings = request.app.state.settings
    table_set = tables.load_tables()
    solve_defaults = models.SolveRequest.model_fields
    return SafeJSONResponse(
        {
            "service": "nlpsf",
            "api_version": "v1",
            "code_version": __version__,
            "data_version": roman.DATA_VERSION,
            "throughputs": {name: roman.THROUGHPUT_VERSIONS[name] for name in roman.THROUGHPUTS},
            "default_throughput": roman.DEFAULT_THROUGHPUT,
            "tables": public_table_meta(table_set.meta),
            "bands": list(roman.BANDS),
            "paper_bands": list(roman.PAPER_BANDS),
            "table_bands": table_set.bands,
            "scas": list(range(1, roman.N_SCA + 1)),
            "metrics": list(solver.METRICS),
            "modes": list(solver.MODES),
            "fidelities": list(solver.FIDELITIES),
            "simulation_fidelities": list(fidelity.SIMULATION_LEVELS),
            "beta_conventions": list(detector.BETA_CONVENTIONS),
            "ramp_fits": list(defaults.RAMP_FITS),
            "ma_tables": [_ma_table_summary(name) for name in models.SHIPPED_MA_TABLES],
            "defaults": {
                "solve": {k: f.default for k, f in solve_defaults.items() if not f.is_required()},
                "simulation": models.SimulationRequest().model_dump(),
            },
            "limits": {
                **settings.limits.to_dict(),
                "max_queue": settings.max_queue,
                "job_workers": settings.job_workers,
                "max_wait_s": settings.max_wait_s,
                "solve_wait_s": settings.solve_wait_s,
                "job_memory_mb": settings.job_memory_mb,
                "max_body_bytes": settings.max_body_bytes,
            },
        }
    )


#: Responses of an endpoint whose answer may need a simulation, which then runs as a job.
JOB_ANSWER_RESPONSES: dict[int | str, dict[str, Any]] = {
    **ERRORS,
    202: {"model": models.Job, "description": "the answer needs a simulation that is still running: poll the Location"},
    413: {"model": models.Problem, "description": "the request body is larger than max_body_bytes"},
    429: {"model": models.Problem, "description": "the simulation queue is full; retry later (Retry-After)"},
    500: {
        "model": models.Problem,
        "description": "the simulation the answer needed failed (the message says why; Location names the job)",
    },
    503: {
        "model": models.Problem,
        "description": "the answer needs a simulation and the job store is unavailable, or the job was cancelled or interrupted",
    },
}


@router.post(
    "/solve",
    response_model=models.SolveResponse,
    responses=JOB_ANSWER_RESPONSES,
    summary="Two of (precision, tolerance, magnitude) -> the third, with its uncertainty",
)
async def solve(body: models.SolveRequest, request: Request) -> Response:
    # A table solve takes microseconds and runs on the event loop (a thread hop would cost more).
    ramp_keys = ("ramp", "ma_table", "ramp_fit", "read_noise")
    scene_keys = ("scene", "over_field")
    raw = body.model_dump()
    arguments = {k: v for k, v in raw.items() if k not in ramp_keys and k not in scene_keys}
    ramp, arguments["exptime"] = body.ramp_arguments(body.exptime, body.sca)  # validates the ramp
    from .simulation import build_scene, check_scene_bounds

    scene = build_scene(raw["scene"]) if raw["scene"] is not None else None  # validates the scene
    if scene is not None:
        check_scene_bounds(scene, body.full_well)
    if scene is not None and ramp is not None:
        raise InputError("scene", "a scene and a ramp cannot be combined yet; give one of them")
    plain = ramp is None and scene is None and body.over_field is None
    if plain and body.fidelity in (None, "table") and body.accuracy is None:
        return SafeJSONResponse(solver.solve(**arguments).to_dict())
    if body.over_field is not None and solver.over_field_from_tables(scene, body.fidelity, body.accuracy, ramp):
        # The worst field point from the shipped field-point tables: up to 90 table solves, a few
        # tens of milliseconds, so off the event loop but not a job.
        scas = "all" if body.over_field == "focal_plane" else [body.sca]
        rest = {k: v for k, v in arguments.items() if k not in ("band", "sca")}
        answer = await run_in_threadpool(solver.solve_over_field, body.band, scas, **rest)
        return SafeJSONResponse(answer.to_dict())
    # Validate everything else at table cost; what remains -- a simulating level, an accuracy (its
    # effects are measured by simulation even when the table level meets it), a ramp, a scene, or an
    # over-field answer the field-point tables do not hold -- is a job like any other simulation
    # (queue, limits, idle priority), never work inside this HTTP worker.
    checked = solver.solve(**{**arguments, "fidelity": "table", "accuracy": None})
    solver.choose_fidelity(body.fidelity, body.accuracy, checked.band, checked.metric, checked.mode)
    job_arguments = {**arguments, "band": checked.band, "scene_request": raw["scene"], "over_field": raw["over_field"]}
    if ramp is not None:
        # The worker rebuilds the ramp from the request's own (JSON) fields.
        job_arguments["exptime"] = body.exptime
        job_arguments["ramp_request"] = {
            **{k: raw[k] for k in ramp_keys},
            "exptime_given": "exptime" in body.model_fields_set,
        }
    return await _job_answer(request, simulation.solve_job(job_arguments))


@router.post(
    "/impact",
    response_model=models.ImpactReport,
    responses=JOB_ANSWER_RESPONSES,
    summary="What each scene effect changes in the slopes at one point (linear response; a job like any simulation)",
)
async def impact(body: models.ImpactRequest, request: Request) -> Response:
    from nlpsf import impact as impact_module

    from .simulation import LimitError, build_scene, check_scene_bounds

    limits = request.app.state.settings.limits
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
    return await _job_answer(request, simulation.impact_job(job_arguments))


async def _job_answer(request: Request, job_request: dict[str, Any]) -> Response:
    """Submit a job and answer with its result when it finishes within ``solve_wait_s`` (200), with
    its input error (422), its failure (500) or its cancellation (503), or with the job to poll (202)."""
    from .simulations import job_response, queue_full_response, submit_job

    try:
        job, status = await submit_job(request, job_request, request.app.state.settings.solve_wait_s)
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
        if ramp is not None or request.fidelity not in (None, "table") or request.accuracy is not None:
            # A batch answers at table cost; a simulating solve is a job (POST /solve), one at a time.
            raise InputError("fidelity", "a batch solves from the tables only: send ramps and simulating levels to POST /solve")
        return {"index": index, "ok": True, "solution": json_safe(solver.solve(**arguments).to_dict())}
    except InputError as error:
        return {"index": index, "ok": False, "error": input_error_body(error)}
    except SimulationError as error:
        # Not the request's fault (e.g. missing shipped data): a server error for this item.
        return {"index": index, "ok": False, "error": problem_body(500, str(error))}


@router.get(
    "/tables",
    response_model=models.TableJSON,
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
    response_model=models.Fits,
    responses=ERRORS,
    summary="Power-law fits slope = A 10^(B (m - 20)) per band and SCA (the paper's Table 2 form)",
)
def fits(band: OptionalBand = None, sca: OptionalSca = None) -> SafeJSONResponse:
    bands = [band] if band else None
    scas = [sca] if sca else None
    return SafeJSONResponse({"fits": json_safe(tables.powerlaw_fits(bands, scas))})


@router.get(
    "/paper",
    response_model=models.PaperData,
    summary="The paper's published figure data (Figs. 2, 3, 5, Table 2; Cycle-5 optics)",
)
def paper() -> SafeJSONResponse:
    return SafeJSONResponse(json_safe(tables.paper_data()))


@router.get(
    "/curves/slope",
    response_model=models.SlopeCurves,
    responses=ERRORS,
    summary="Slope vs magnitude for every band (the paper's Figs. 3 and 5)",
)
def slope_curves(
    metric: MetricQuery = "size",
    mode: ModeQuery = "bias",
    sca: Sca = 18,
    exptime: Exptime = defaults.EXPTIME_S,
    beta0: Beta0 = defaults.BETA0,
    full_well: FullWell = defaults.FULL_WELL_E,
    bands: Annotated[list[models.Band] | None, Query(description="bands to include (no unit; default: all with tables)")] = None,
) -> SafeJSONResponse:
    chosen = bands or tables.load_tables().bands
    curves = [tables.curve(b, sca, metric, mode, exptime=exptime, beta0=beta0, full_well=full_well) for b in chosen]
    for curve in curves:
        # The table level's measured error beside the statistical one (the calculator quotes both).
        curve["fidelity_relative_uncertainty"], _ = solver._fidelity_error("table", curve["band"], metric, mode)
    return SafeJSONResponse(
        {
            "source": "table: the shipped slope tables, interpolated in magnitude and scaled to these conditions",
            "metric": metric,
            "mode": mode,
            "curves": json_safe(curves),
        }
    )


def _linear_curve(
    band: str, sca: int, metric: str, mode: str, magnitude: float, exptime: float, beta0: float, full_well: float, xs: list[float]
) -> dict[str, Any]:
    # The solver at precision 1 returns tolerance = |c(m)| beta0 and the signed slope c(m): the curve is
    # the line c(m) x through 0 (signed, since Delta e1 and Delta e2 can be negative).
    solution = solver.solve(
        band,
        sca=sca,
        metric=metric,
        mode=mode,
        beta0=beta0,
        exptime=exptime,
        precision=1.0,
        magnitude=magnitude,
        full_well=full_well,
    ).to_dict()
    # The statistical part per point, the fidelity part as one relative number (the page shows both).
    at_beta0 = solution["tolerance"]
    statistical, systematic = solution["uncertainty_statistical"], solution["uncertainty_fidelity"]
    relative = abs((statistical or 0.0) / at_beta0) if at_beta0 else 0.0
    slope = solution["slope"] or 0.0
    values = [slope * x for x in xs]
    return {
        "values": values,
        "uncertainty": [abs(v) * relative for v in values],
        "fidelity_relative_uncertainty": abs(systematic / at_beta0) if at_beta0 and systematic is not None else None,
        "slope": solution["slope"],
        "flags": solution["flags"],
        "saturation_magnitude": solution["saturation_magnitude"],
        "conditions": solution["conditions"],
    }


def _grid(top: float, points: int) -> list[float]:
    return [top * k / (points - 1) for k in range(points)]


@router.get(
    "/curves/beta",
    response_model=models.BetaCurve,
    responses=ERRORS,
    summary="Metric vs beta at one magnitude (the paper's Fig. 2)",
)
def beta_curve(
    band: Band = "H158",
    sca: Sca = 18,
    metric: MetricQuery = "size",
    magnitude: Magnitude = 18.3,
    exptime: Exptime = defaults.EXPTIME_S,
    beta0: Beta0 = defaults.BETA0,
    full_well: FullWell = defaults.FULL_WELL_E,
    beta_max: Annotated[
        float, Query(allow_inf_nan=False, gt=0, le=detector.MAX_ABS_BETA, description="largest beta in 1/e-")
    ] = 1.25e-6,
    points: Points = 26,
) -> SafeJSONResponse:
    betas = _grid(beta_max, points)
    curve = _linear_curve(band, sca, metric, "bias", magnitude, exptime, beta0, full_well, betas)
    return SafeJSONResponse(
        json_safe(
            {
                "source": "table, first order: metric = c(m) beta with c(m) the table's bias slope at beta0; "
                "POST /api/v1/simulations with several betas gives the full (nonlinear) response",
                "band": band.upper(),
                "sca": sca,
                "metric": metric,
                "magnitude": magnitude,
                "beta": betas,
                **curve,
            }
        )
    )


@router.get(
    "/curves/sigma_beta",
    response_model=models.SigmaBetaCurve,
    responses=ERRORS,
    summary="Scatter of the metric vs sigma_beta at one magnitude",
)
def sigma_beta_curve(
    band: Band = "H158",
    sca: Sca = 18,
    metric: MetricQuery = "size",
    magnitude: Magnitude = 18.3,
    exptime: Exptime = defaults.EXPTIME_S,
    beta0: Beta0 = defaults.BETA0,
    full_well: FullWell = defaults.FULL_WELL_E,
    sigma_beta_max: Annotated[
        float, Query(allow_inf_nan=False, gt=0, le=detector.MAX_ABS_BETA, description="largest sigma_beta in 1/e-")
    ] = 1e-7,
    points: Points = 26,
) -> SafeJSONResponse:
    sigmas = _grid(sigma_beta_max, points)
    curve = _linear_curve(band, sca, metric, "scatter", magnitude, exptime, beta0, full_well, sigmas)
    return SafeJSONResponse(
        json_safe(
            {
                "source": "table, first order: sigma(metric) = c_sigma(m) sigma_beta with c_sigma(m) the table's scatter slope; "
                "POST /api/v1/simulations with sigma_betas gives Monte Carlo values",
                "band": band.upper(),
                "sca": sca,
                "metric": metric,
                "magnitude": magnitude,
                "sigma_beta": sigmas,
                **curve,
            }
        )
    )


__all__ = ["input_error_response", "router"]
