"""The API under /api/v1, one router per resource, gathered here for the app (``main.create_app``):

- ``health_api``: /health, /meta;
- ``solve_api``: /solve, /solve/batch;
- ``impact_api``: /impact;
- ``tables_api``: /tables, /tables.ecsv, /tables.csv, /fits, /paper;
- ``curves_api``: /curves/slope, /curves/beta, /curves/sigma_beta;
- ``calibration_api``: /calibration/kernel, /calibration/residual, /calibration/requirement (jobs);
- ``simulations``: /simulations (jobs), mounted by the app itself.

Shared query parameters and error responses are in ``params``; what handlers need from the running
service comes as ``Annotated`` dependencies (``deps``).
"""

from __future__ import annotations

from fastapi import APIRouter

from . import calibration_api, curves_api, health_api, impact_api, solve_api, tables_api
from .errors import input_error_response
from .health_api import public_table_meta
from .params import ERRORS

router = APIRouter()
for _resource in (health_api, solve_api, impact_api, tables_api, curves_api, calibration_api):
    router.include_router(_resource.router)

__all__ = ["ERRORS", "input_error_response", "public_table_meta", "router"]
