"""The pieces every kind of job is made of: what a kind is (:class:`JobKind`), and a solve's JSON
fields read as the library's typed request (POST /solve, and the calibration kinds' star). Below
``job_kinds`` (which lists the kinds) and ``calibration_jobs`` (which adds its own), so neither
imports the other back."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from nlpsf.request.resolve import SolveRequest
from nlpsf.sim import scene as scenes

Progress = Callable[[float, str], None]


@dataclass(frozen=True)
class JobKind:
    """One kind of job. ``validate(fields, given, settings)`` runs in the web process at table cost,
    before anything is queued: from the request's fields (``given``: those the client sent) to the
    job request, or InputError/LimitError naming the field. ``run(arguments, progress)`` runs in the
    job process; ``estimate(arguments)`` (s on one core, None when not priced) sets the wall-time limit."""

    name: str
    validate: Callable[[dict[str, Any], set[str], Any], dict[str, Any]]
    run: Callable[[dict[str, Any], Progress | None], dict[str, Any]]
    estimate: Callable[[dict[str, Any]], float | None]


#: Fields of POST /solve that are the service's, not the library request's.
SOLVE_SERVICE_FIELDS = ("over_field",)


def solve_body(fields: dict[str, Any], given: set[str]) -> dict[str, Any]:
    """A solve's JSON fields as the library's request reads them: the service's own fields left out
    (every published default is the library's: ``exptime`` and ``ramp_fit`` null, the scene's)."""
    return {k: v for k, v in fields.items() if k not in SOLVE_SERVICE_FIELDS}


def solve_request(body: dict[str, Any]) -> SolveRequest:
    """The library's typed request for a solve's JSON fields (:func:`solve_body`); a shipped MA
    table's name becomes the table before the library sees it (no client string reaches a file call)."""
    from .models import shipped_ma_table

    if isinstance(body.get("ma_table"), str):
        body = {**body, "ma_table": shipped_ma_table(body["ma_table"])}
    request = SolveRequest.from_json(body)
    if request.scene is not None:
        scenes.check_first_order(request.scene, request.full_well)
    return request
