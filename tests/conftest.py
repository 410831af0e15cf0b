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
