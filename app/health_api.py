"""The service itself: /health (liveness, the job store, the HTTP workers) and /meta (bands,
defaults, limits, versions)."""

from __future__ import annotations

from pathlib import PurePath
from typing import Any

from fastapi import APIRouter

from nlpsf import defaults, flags, roman
from nlpsf._version import __version__
from nlpsf.request import presets as roman_default
from nlpsf.serialise import json_safe
from nlpsf.sim import detector, levels
from nlpsf.sim import scene as scenes
from nlpsf.slopes import tables
from nlpsf.solve import solver

from . import data_models, liveness, models
from .deps import ServicesDep, SettingsDep
from .errors import SafeJSONResponse

router = APIRouter(prefix="/api/v1")


@router.get(
    "/health",
    response_model=data_models.Health,
    summary="Liveness: 200 when the service answers; 'degraded' (with the reason) when simulations cannot run",
)
async def health(services: ServicesDep) -> dict[str, Any]:
    # No I/O here: the job store's state is kept by the dispatcher's heartbeat (every 1 s, with an integrity check).
    store = services.store
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


def scene_effects() -> list[dict[str, Any]]:
    """The scene-effect registry (``nlpsf.sim.scene.REGISTRY``) as JSON, in the order the effects act."""
    return [
        {
            "name": e.name,
            "fields": list(e.fields),
            "nominal": json_safe(e.nominal),
            "source": e.source,
            "kind": e.kind,
            "breaks_beta_q": e.breaks_beta_q,
            "combines_with": e.combines_with,
            "in_roman_preset": e.in_roman_preset,
        }
        for e in scenes.REGISTRY.values()
    ]


@router.get("/meta", response_model=data_models.Meta, summary="Bands, SCAs, metrics, defaults, limits, data and code versions")
def meta(settings: SettingsDep) -> SafeJSONResponse:
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
            "simulation_fidelities": list(levels.SIMULATION_LEVELS),
            "beta_conventions": list(detector.BETA_CONVENTIONS),
            "ramp_fits": list(defaults.RAMP_FITS),
            "ma_tables": [_ma_table_summary(name) for name in models.SHIPPED_MA_TABLES],
            "flag_codes": flags.catalogue(),
            "scene_effects": scene_effects(),
            "defaults": {
                "solve": {k: f.default for k, f in solve_defaults.items() if not f.is_required()},
                "simulation": models.SimulationRequest().model_dump(),
                # What a solve leaves unset is filled per scene (nlpsf.request.presets.fill): its exposure.
                "scene_exptime": {"roman": roman_default.exptime_s(), "paper": defaults.EXPTIME_S},
            },
            "limits": {
                **settings.limits.to_dict(),
                "max_queue": settings.max_queue,
                "job_workers": settings.job_workers,
                "max_wait_s": settings.max_wait_s,
                "solve_wait_s": settings.solve_wait_s,
                "job_memory_mb": settings.job_memory_mb,
                "max_body_bytes": settings.max_body_bytes,
                "max_queue_per_client": settings.queue_per_client,
                "job_stall_s": settings.job_stall_s,
                "job_time_factor": settings.job_time_factor,
                "header_timeout_s": settings.header_timeout_s,
                "body_timeout_s": settings.body_timeout_s,
                "keep_alive_s": settings.keep_alive_s,
                "max_connections": settings.max_connections,
                "heartbeat_timeout_s": settings.heartbeat_timeout_s,
            },
        }
    )
