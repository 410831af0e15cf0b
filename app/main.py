"""The FastAPI application: ``create_app()`` builds it, ``app`` is what uvicorn serves.

API under /api/v1 (OpenAPI docs at /docs, from vendored Swagger UI), the page (``static/``) at /.

Start-up (the lifespan) runs before the worker accepts a connection: it loads the slope tables, so
the first request is as fast as the rest, and opens the job store. A job store that cannot be
opened leaves the calculator running: /health says why and /simulations answers 503 until it is back.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from importlib import resources
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles
from starlette.middleware.trustedhost import TrustedHostMiddleware

from nlpsf import __version__, tables

from . import api, errors, simulations
from .jobs import Dispatcher, Notifier
from .security import ApiKey, BodyLimit, SecurityHeaders
from .settings import Settings
from .store import Store

log = logging.getLogger("nlpsf.web")


def static_dir(settings: Settings) -> Path:
    """The page's files: the setting static_dir, else the package data ``nlpsf.web.static`` (a
    folder in a wheel or a checkout alike)."""
    return Path(settings.static_dir) if settings.static_dir else Path(str(resources.files("nlpsf.web.static")))


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        # Tables first, once, before any connection is accepted (uvicorn listens after the lifespan).
        app.state.tables = tables.load_tables()
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
    errors.install(app)
    app.include_router(api.router)
    app.include_router(simulations.router)
    directory = static_dir(settings)

    @app.get("/docs", include_in_schema=False)
    def docs() -> FileResponse:
        return FileResponse(directory / "docs.html", media_type="text/html")

    if directory.is_dir():
        app.mount("/", StaticFiles(directory=directory, html=True), name="page")
    # Outermost last: every response, refusals included, gets the security headers.
    if settings.api_keys:
        app.add_middleware(ApiKey, keys=[k.get_secret_value() for k in settings.api_keys])
    app.add_middleware(BodyLimit, max_bytes=settings.max_body_bytes)
    if settings.allowed_hosts != ["*"]:
        app.add_middleware(TrustedHostMiddleware, allowed_hosts=settings.allowed_hosts)
    app.add_middleware(SecurityHeaders)
    return app


app = create_app()
