"""Shared parts of the API's endpoints: query parameters as ``Annotated`` types (the library's
names and ranges) and the documented error responses."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import Query

from nlpsf import roman

from . import models

ERRORS: dict[int | str, dict[str, Any]] = {422: {"model": models.Problem, "description": "invalid input; names the field"}}


Band = Annotated[models.Band, Query(description=f"Roman band (no unit): {', '.join(roman.BANDS)}")]
Sca = Annotated[int, Query(ge=1, le=roman.N_SCA, description=f"detector (SCA number, no unit) 1-{roman.N_SCA}")]
Magnitude = Annotated[float, Query(allow_inf_nan=False, description="star magnitude in AB mag")]
Exptime = Annotated[float, Query(allow_inf_nan=False, description="exposure time in s")]
Beta0 = Annotated[float, Query(allow_inf_nan=False, description="NL coefficient beta0 in 1/e- (paper convention)")]
FullWell = Annotated[float, Query(allow_inf_nan=False, description="full-well depth in e-")]
OptionalBand = Annotated[models.Band | None, Query(description="Roman band (no unit); default all")]
OptionalSca = Annotated[
    int | None, Query(ge=1, le=roman.N_SCA, description=f"detector (SCA number, no unit) 1-{roman.N_SCA}; default all")
]
MetricQuery = Annotated[models.Metric, Query(description="the PSF metric (no unit): size (dR/R), e1, e2 or e (|de|)")]
ModeQuery = Annotated[models.Mode, Query(description="bias or scatter (no unit)")]
Points = Annotated[int, Query(ge=2, le=1000, description="number of grid points (count)")]


#: Responses of an endpoint whose answer may need a simulation, which then runs as a job.
JOB_ANSWER_RESPONSES: dict[int | str, dict[str, Any]] = {
    **ERRORS,
    202: {"model": models.Job, "description": "the answer needs a simulation that is still running: poll the Location"},
    413: {"model": models.Problem, "description": "the request body is larger than max_body_bytes"},
    429: {
        "model": models.Problem,
        "description": "the simulation queue, or your share of the inline CPU, is full; retry later (Retry-After)",
    },
    500: {
        "model": models.Problem,
        "description": "the simulation the answer needed failed (the message says why; Location names the job)",
    },
    503: {
        "model": models.Problem,
        "description": "the answer needs a simulation and the job store is unavailable, or the job was cancelled or interrupted",
    },
}
