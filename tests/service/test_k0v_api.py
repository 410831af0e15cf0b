"""The vendored K0V spectrum through the REST API: ``"sed": "k0v"`` is the library's named SED."""

from __future__ import annotations

import pytest
from nlpsf.web import models
from pydantic import ValidationError

from nlpsf.sim import scene as scenes


def test_the_api_scene_takes_the_named_k0v_and_the_library_reads_it():
    request = models.SceneRequest(sed="k0v")
    assert scenes.from_request(request.model_dump(exclude_none=True)).sed == "k0v"
    with pytest.raises(ValidationError):
        models.SceneRequest(sed="k9v")
