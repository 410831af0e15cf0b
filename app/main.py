"""The FastAPI application: ``create_app()`` builds it, ``app`` is what uvicorn serves.

API under /api/v1 (OpenAPI docs at /docs), the page (``static/``) at /.
"""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from importlib import resources
from pathlib import Path

from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from nlpsf import __version__

from . import api, errors, simulations
from .jobs import Dispatcher
from .settings import Settings
from .store import Store


def static_dir() -> Path:
    """The page's files, installed as the package data ``nlpsf.web.static`` (a folder in a wheel
    or a checkout alike)."""
    return Path(str(resources.files("nlpsf.web.static")))


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings.from_env()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        store = Store(settings.db_path)
        dispatcher = Dispatcher(store, settings)
        app.state.store = store
        app.state.dispatcher = dispatcher
        await dispatcher.start()
        try:
            yield
        finally:
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
    )
    app.state.settings = settings
    errors.install(app)
    app.include_router(api.router)
    app.include_router(simulations.router)
    directory = static_dir()
    if directory.is_dir():
        app.mount("/", StaticFiles(directory=directory, html=True), name="page")
    return app


app = create_app()
