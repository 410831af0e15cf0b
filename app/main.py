"""The FastAPI application: ``create_app()`` builds it, ``app`` is what uvicorn serves.

API under /api/v1 (OpenAPI docs at /docs, from vendored Swagger UI), the page (``static/``) at /.

Start-up (the lifespan) runs before the worker accepts a connection: it loads the slope tables and
answers one default solve, so the first request is as fast as the rest, and opens the job store. A
job store that cannot be opened leaves the calculator running: /health says why and /simulations
answers 503 until it is back.
"""

from __future__ import annotations

import gc
import logging
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from importlib import resources
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from starlette.middleware.gzip import GZipMiddleware
from starlette.middleware.trustedhost import TrustedHostMiddleware

from nlpsf import defaults
from nlpsf._version import __version__
from nlpsf.request.resolve import SolveRequest
from nlpsf.slopes import providers, tables
from nlpsf.solve import batch

from . import api, budget, documents, errors, models, page_api, simulations
from .jobs import Dispatcher, Notifier
from .security import ApiKey, ApiMethods, BodyLimit, JsonBodies, SecurityHeaders
from .settings import Settings
from .store import Store

log = logging.getLogger("nlpsf.web")

#: How often a thread holding the interpreter lock is asked to let another run (Python's default: 5 ms).
SWITCH_INTERVAL_S = 0.001


def static_dir(settings: Settings) -> Path:
    """The page's files: the setting static_dir, else the package data ``nlpsf.web.static`` (a
    folder in a wheel or a checkout alike)."""
    return Path(settings.static_dir) if settings.static_dir else Path(str(resources.files("nlpsf.web.static")))


def _answer_one_default_solve() -> None:
    """Warm-up: a failure here is logged, not fatal, so the rest of the calculator still serves (the
    same failure then reaches the client of a default /solve as its own answer)."""
    first = {"band": defaults.BAND, "magnitude": defaults.MAGNITUDE, "tolerance": 1e-4}
    try:
        batch.answer_from_tables(SolveRequest.from_json(first))
    except Exception:
        log.exception("the warm-up default solve failed; default answers will fail the same way")


#: Routes whose answer is a pure function of the request (its query, and its body for a POST) and
#: the settings, costly enough to budget (milliseconds to half a second): kept per request and
#: admitted against the client's share when not kept (``documents.CachedAnswers``); path -> method.
CACHED_ROUTES = {
    **{f"/api/v1/{path}": "GET" for path in ("meta", "fits", "paper", "curves/slope", "curves/beta", "curves/sigma_beta")},
    **{f"/api/v1/page/{path}": "GET" for path in ("presets", "tables.csv")},
    **{f"/api/v1/page/{path}": "POST" for path in ("limits", "requirement", "slopes")},
}


#: The request model of each route that takes a JSON body: a large body is validated against it off
#: the event loop (``security.JsonBodies``) before FastAPI validates it again, cheaply, on the loop.
REQUEST_SCHEMAS = {
    "/api/v1/solve": models.SolveRequest,
    "/api/v1/solve/batch": models.BatchSolveRequest,
    "/api/v1/simulations": models.SimulationRequest,
    "/api/v1/impact": models.ImpactRequest,
    **{f"/api/v1/page/{path}": models.SolveRequest for path in ("limits", "requirement", "slopes")},
}


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # Tables first, once, before any connection is accepted (uvicorn listens after the lifespan).
        app.state.tables = tables.load_tables()
        # The field-point tables (--over-field) too, so the first such request is as fast as the rest.
        field = providers.field_tables()
        if field is not None:
            field.load_all()
        # One default answer (the Roman default at its field grid's nodes, its readout, sky and model
        # parts): what a first /solve would otherwise load lazily (~1.3 s, against ~40 ms after).
        _answer_one_default_solve()
        # What is loaded now lives as long as the process: out of the cyclic collector's sight, so a
        # full collection (0.2-0.5 s over the ~180,000 objects loaded, holding the GIL: every request
        # of this worker waits) never runs over it again.
        gc.collect()
        gc.freeze()
        # The event loop waits at most this long for the interpreter lock a worker thread holds (a
        # default solve, a large body's parsing) before it may answer another request: 1 ms, not 5.
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        store = Store(settings.db_path)
        if store.state != "ok":
            log.error("starting without simulations: %s; the calculator runs, /health says why", store.reason)
        dispatcher = Dispatcher(store, settings)
        app.state.store = store
        app.state.dispatcher = dispatcher
        app.state.notifier = Notifier(store)
        await dispatcher.start()
        try:
            yield
        finally:
            await app.state.notifier.stop()
            await dispatcher.stop()

    app = FastAPI(
        title="nlpsf",
        version=__version__,
        summary="How well must Roman detector nonlinearity be calibrated for PSF size and ellipticity?",
        description=(
            "The two-of-three calculator (calibration precision, error tolerance, star magnitude), the slope tables, "
            "curves for plotting, the paper's published data, and fresh simulations as jobs. "
            "Every number carries its conditions (band, SCA, exposure, beta0, fidelity) and its uncertainty."
        ),
        lifespan=lifespan,
        docs_url=None,  # served below from vendored Swagger UI, never a CDN
        redoc_url=None,
    )
    app.state.settings = settings
    share, burst, total = settings.inline_cpu_share, settings.inline_cpu_burst_s, settings.inline_cpu_total_share
    app.state.budget = budget.InlineBudget(share, burst, total, settings.inline_cache_mb * 1024**2)
    app.state.documents = documents.Documents(settings.documents_cache_mb * 1024**2)
    errors.install(app)
    app.include_router(api.router)
    app.include_router(simulations.router)
    app.include_router(page_api.router)
    directory = static_dir(settings)

    @app.get("/docs", include_in_schema=False)
    def docs() -> FileResponse:
        return FileResponse(directory / "docs.html", media_type="text/html")

    if directory.is_dir():
        app.mount("/", StaticFiles(directory=directory, html=True), name="page")
    _problem_schema(app)
    # Synchronous endpoints' cost measured where it is spent (their thread); pure answers kept by request.
    budget.install_metering()
    # Middleware, innermost first (each add_middleware wraps the ones before it): JSON bodies checked
    # (off the loop when large); the page's pure answers kept; answers compressed for clients that
    # accept gzip (the tables come compressed); the API's methods; the body's limits; each request
    # metered and charged to its client (outside the body's reading, so a client in debt is refused
    # before its body is read); the key; the Host check; the security headers on every response.
    app.add_middleware(JsonBodies, schemas=REQUEST_SCHEMAS)
    app.add_middleware(documents.CachedAnswers, budget=app.state.budget, documents=app.state.documents, routes=CACHED_ROUTES)
    app.add_middleware(GZipMiddleware, minimum_size=1024, compresslevel=6)
    app.add_middleware(ApiMethods)
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes, timeout_s=settings.body_timeout_s)
    app.add_middleware(budget.ClientMeter, budget=app.state.budget)
    if settings.api_keys:
        app.add_middleware(ApiKey, keys=[k.get_secret_value() for k in settings.api_keys])
    if settings.allowed_hosts != ["*"]:
        app.add_middleware(TrustedHostMiddleware, allowed_hosts=settings.allowed_hosts)
    app.add_middleware(SecurityHeaders)
    return app


#: The 429 every API path may answer (``budget.ClientMeter``), where a route documents no 429 of its own.
THROTTLED_DESCRIPTION = "your share of the service's inline CPU is used (inline_cpu_share); retry after Retry-After s"


def _problem_schema(app: FastAPI) -> None:
    """Every error response in the OpenAPI schema is the Problem model as application/problem+json
    (FastAPI documents extra responses as application/json and adds its own 422 shape)."""
    from fastapi.openapi.utils import get_openapi

    def openapi() -> dict:
        if app.openapi_schema:
            return app.openapi_schema
        schema = get_openapi(
            title=app.title, version=app.version, summary=app.summary, description=app.description, routes=app.routes
        )
        problem = {"schema": {"$ref": "#/components/schemas/Problem"}}
        for path, operations in schema.get("paths", {}).items():
            for method, operation in operations.items():
                if method in ("post", "put", "patch"):
                    # BodyLimit answers any request body over max_body_bytes before the route runs.
                    operation["responses"].setdefault("413", {"description": "the request body is larger than max_body_bytes"})
                if path.startswith("/api/"):
                    # ClientMeter charges every API request to its client: past the share, any answers 429.
                    operation["responses"].setdefault("429", {"description": THROTTLED_DESCRIPTION})
                for code, response in operation.get("responses", {}).items():
                    if code.isdigit() and int(code) >= 400:
                        response["content"] = {errors.PROBLEM_MEDIA_TYPE: problem}
                        continue
                    content = response.get("content") or {}
                    # Downloads (CSV, ECSV) are text: FastAPI also lists its default JSON, untyped.
                    if any(not media.endswith("json") for media in content):
                        content.pop("application/json", None)
                    for media, entry in content.items():
                        if not media.endswith("json") and not entry.get("schema"):
                            entry["schema"] = {"type": "string"}
        components = schema.get("components", {}).get("schemas", {})
        _publish_limits(components, app.state.settings)
        components.setdefault("Problem", models.Problem.model_json_schema(ref_template="#/components/schemas/{model}"))
        for unused in ("HTTPValidationError", "ValidationError"):
            components.pop(unused, None)
        app.openapi_schema = schema
        return schema

    app.openapi = openapi  # type: ignore[method-assign]


def _tighten(prop: dict, key: str, value: int) -> None:
    """Set ``maximum``/``maxItems`` on a property (or its non-null member) to the smaller of the two;
    a default above a lowered maximum is lowered with it (the endpoints do the same)."""
    for target in [prop, *prop.get("anyOf", [])]:
        if target.get("type") in ("integer", "number", "array") and (key != "maxItems" or target.get("type") == "array"):
            target[key] = min(target.get(key, value), value)
    if key == "maximum" and isinstance(prop.get("default"), (int, float)) and prop["default"] > value:
        prop["default"] = value


def _publish_limits(components: dict, settings: Settings) -> None:
    """The service's own caps on one request, where one field sets them, in its schema (the
    library's ranges are there already, from the models): a request the schema allows is one this
    service accepts. Caps on products of fields (grid cells, stamp pixels, work, memory) cannot be
    said in a JSON schema; they are in /meta and named in the 422 that enforces them."""
    limits = settings.limits
    simulation = components.get("SimulationRequest", {}).get("properties", {})
    for name, key, value in (
        ("realizations", "maximum", limits.max_realizations),
        ("stamp", "maximum", limits.max_stamp),
        ("n_wavelengths", "maximum", limits.max_wavelengths),
        ("magnitudes", "maxItems", limits.max_grid),
        ("betas", "maxItems", limits.max_grid),
        ("sigma_betas", "maxItems", limits.max_grid),
    ):
        if name in simulation:
            _tighten(simulation[name], key, value)
    impact = components.get("ImpactRequest", {}).get("properties", {})
    if "realizations" in impact:
        _tighten(impact["realizations"], "maximum", limits.max_realizations)
    scene = components.get("SceneRequest", {}).get("properties", {})
    if "n_wavelengths" in scene:
        _tighten(scene["n_wavelengths"], "maximum", limits.max_wavelengths)


app = create_app()
