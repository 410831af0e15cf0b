import importlib.util

import pytest

from nlpsf import experiment

HAVE_GALSIM = importlib.util.find_spec("galsim") is not None
requires_galsim = pytest.mark.skipif(not HAVE_GALSIM, reason="GalSim not installed (pip install nlpsf[reference])")


@pytest.fixture(scope="session")
def paper_config():
    """The paper's configuration with fewer realizations, to keep tests quick."""
    return experiment.SimulationConfig(realizations=20)


@pytest.fixture(scope="session")
def paper_scene(paper_config):
    return experiment.prepare(paper_config)


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    """The service in-process (TestClient), with small limits; one per test module."""
    from fastapi.testclient import TestClient
    from nlpsf.web.main import create_app
    from nlpsf.web.settings import Limits, Settings

    settings = Settings(
        db_path=str(tmp_path_factory.mktemp("db") / "jobs.sqlite3"),
        job_workers=1,
        max_queue=8,
        limits=Limits(max_realizations=500, max_stamp=128, max_grid=50),
    )
    with TestClient(create_app(settings)) as test_client:
        yield test_client
