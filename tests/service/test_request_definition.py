"""One request, three readers: the library's ``SolveRequest``, the API's body (``POST /solve``) and
the command line (``nlpsf solve``) name the same fields, and the defaults the API publishes and the
command line shows are the ones the library uses."""

from __future__ import annotations

import dataclasses
import inspect

import pytest
from nlpsf.web import job_parts, models

from nlpsf import SolveRequest
from nlpsf.cli import build_parser
from nlpsf.request.resolve import RAMP_REQUEST_FIELDS
from nlpsf.solve import solver

#: Library fields the API reads in another shape: the ramp from RAMP_REQUEST_FIELDS, the preset inside ``scene``.
READ_AS = {"ramp": RAMP_REQUEST_FIELDS, "preset": ("scene",)}
LIBRARY = {f.name for f in dataclasses.fields(SolveRequest) if f.init}
API = set(models.SolveRequest.model_fields)


def test_the_api_body_is_the_library_request():
    for name in LIBRARY:
        assert name in API or set(READ_AS.get(name, ())) <= API, name
    extra = API - LIBRARY - set(RAMP_REQUEST_FIELDS) - set(job_parts.SOLVE_SERVICE_FIELDS)
    assert not extra, extra


@pytest.mark.parametrize("scene", [None, "paper", {"position": [1000.0, 3000.0]}])
def test_every_published_default_is_the_one_used(client, scene):
    schema = client.get("/openapi.json").json()["components"]["schemas"]["SolveRequest"]["properties"]
    body = {"band": "H158", "precision": 0.01, "magnitude": 19.0} | ({} if scene is None else {"scene": scene})
    resolved = job_parts.solve_request(job_parts.solve_body(body, set(body)))
    published = {name: spec["default"] for name, spec in schema.items() if "default" in spec}
    assert {"sca", "metric", "mode", "beta0", "full_well", "stars"} <= set(published)
    # What depends on the scene is published as no default (null): the scene's.
    assert published.get("exptime") is None and published.get("ramp_fit") is None
    for name, default in published.items():
        if name in job_parts.SOLVE_SERVICE_FIELDS or name in body:
            continue
        given = {**body, name: default}
        assert job_parts.solve_request(job_parts.solve_body(given, set(given))) == resolved, (name, default)


def test_the_command_lines_defaults_are_the_librarys():
    parser, _ = build_parser(["solve"])
    args = parser.parse_args(["solve", "--band", "H158", "--precision", "0.01", "--magnitude", "19"])
    library = {n: p.default for n, p in inspect.signature(solver.solve).parameters.items() if p.default is not p.empty}
    shown = {name: getattr(args, name) for name in LIBRARY if hasattr(args, name)}
    assert set(shown) >= LIBRARY - {"ramp", "scene", "preset", "exptime"}  # those three are built from options
    for name, value in shown.items():
        if name in library and name not in ("band", "precision", "magnitude"):
            assert value == library[name], (name, value, library[name])
