"""Fixtures every folder shares: the paper's prepared scene, GalSim's marker, and the one factory of the
service in process (``make_client``, and ``client`` built with it for a module's tests)."""

import importlib.util
import os
import sys
from pathlib import Path

import pytest

# OpenBLAS picks its kernels by the CPU (AVX2's "Haswell", AVX-512's "SkylakeX", ...), and they sum a
# dot product in another order: the answers stored in tests/data (test_stored_answers.py: the paper
# scene's bit for bit) were computed with the Haswell kernels, and the SkylakeX ones move the paper
# scene's answers at a field corner in the last bits (a slope by 1e-16, its uncertainty by up to
# 2e-11 relative, on 2026-12-05). The suite reads every machine's numbers with the Haswell kernels
# where the CPU runs them (an x86-64 one with AVX2; another would stop at its first AVX2 instruction):
# set before numpy loads OpenBLAS, or it counts for nothing.


def _runs_avx2() -> bool:
    try:
        return any(line.startswith("flags") and " avx2" in line for line in Path("/proc/cpuinfo").read_text().splitlines())
    except OSError:
        return False


if "numpy" in sys.modules:
    import warnings

    warnings.warn("numpy was loaded before tests/conftest.py: OpenBLAS's kernels are the CPU's own", stacklevel=1)
elif _runs_avx2():
    os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")

from nlpsf.sim import experiment  # noqa: E402  (numpy loads here: after the kernels are pinned)

HAVE_GALSIM = importlib.util.find_spec("galsim") is not None
requires_galsim = pytest.mark.skipif(not HAVE_GALSIM, reason="GalSim not installed (pip install nlpsf[reference])")

#: The in-process service's settings under every test's own: one job worker and a short queue.
SERVICE_SETTINGS = {"job_workers": 1, "max_queue": 8}


@pytest.fixture(scope="session")
def paper_config():
    """The paper's configuration with fewer realizations, to keep tests quick."""
    return experiment.SimulationConfig(realizations=20)


@pytest.fixture(scope="session")
def paper_scene(paper_config):
    return experiment.prepare(paper_config)


def _service_client(db_path: Path, overrides: dict):
    """A TestClient of the whole app (its lifespan runs on ``with``), on the job store at ``db_path``."""
    from fastapi.testclient import TestClient
    from nlpsf.web.main import create_app
    from nlpsf.web.settings import Settings

    return TestClient(create_app(Settings(**{"db_path": str(db_path), **SERVICE_SETTINGS, **overrides})))


@pytest.fixture
def make_client(tmp_path_factory):
    """``with make_client(**settings) as client:``: the service in process on a job store of its own (or
    the one at ``db_path=``, to start it again on the same store), with ``settings`` over SERVICE_SETTINGS."""

    def make(db_path: Path | str | None = None, **overrides):
        return _service_client(db_path or tmp_path_factory.mktemp("service") / "jobs.sqlite3", overrides)

    return make


@pytest.fixture(scope="module")
def client_settings() -> dict:
    """The settings of a module's shared ``client``: small limits. A module that needs others overrides
    this fixture (not ``client``)."""
    from nlpsf.web.settings import Limits

    return {"limits": Limits(max_realizations=500, max_stamp=128, max_grid=50)}


@pytest.fixture(scope="module")
def client(tmp_path_factory, client_settings):
    """The service in process, shared by one module's tests, on its own job store."""
    with _service_client(tmp_path_factory.mktemp("service") / "jobs.sqlite3", client_settings) as test_client:
        yield test_client
