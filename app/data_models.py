"""The service's read-only answers: health, the library's catalogue (/meta), the shipped tables and
their fits, the slope and metric curves and the paper's data. The requests and the answers of the
calculator, the impact report and the jobs are in ``models``.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from .models import desc


class JobStoreStatus(BaseModel):
    state: str = Field(description="ok, starting or unavailable (no unit)")
    reason: str | None = Field(None, description="why simulations cannot run (text)")
    since: float | None = Field(None, description="Unix time in s of the last state change")


class Health(BaseModel):
    model_config = ConfigDict(extra="allow")

    status: Literal["ok", "degraded"] = Field(description="ok, or degraded when simulations cannot run")
    version: str = Field(description="code version (no unit)")
    calculator: str = Field(description="state of the calculator (no unit)")
    job_store: JobStoreStatus = Field(description="state of the simulation job store")
    http_workers: dict[str, Any] | None = Field(
        None,
        description="the HTTP workers under the supervisor: workers, responding, starting (counts: a starting worker has "
        "not beaten yet), stalled (each worker's index and silence in s), heartbeat_timeout_s; null when no supervisor "
        "runs the service",
    )


class FlagCatalogueEntry(BaseModel):
    code: str = desc("the flag's code, stable across versions and languages (no unit)")
    template: str = desc("the message's template; {name} is one of quotes (text)")
    quotes: list[str] = desc("the values the message quotes (no unit)")
    meaning: str = desc("what the flag means, in one sentence (text)")


class SceneEffectEntry(BaseModel):
    name: str = desc("the effect (no unit), as the impact report names it")
    fields: list[str] = desc("the library's scene fields that set it (nlpsf.sim.scene.SceneModel; no unit)")
    nominal: dict[str, Any] = desc("the Roman value tried when a scene leaves it off, in the fields' units (null: none)")
    source: str = desc("where the nominal value comes from (text)")
    kind: Literal["optical", "detector"] = desc("optical: acts on the PSF before the pixels; detector: in the pixels")
    breaks_beta_q: bool = desc("adds a flux dependence of its own (the tables' beta x flux rescaling then does not hold)")
    combines_with: str = desc("what it can be simulated together with (text)")
    in_roman_preset: bool = desc("part of the scene preset 'roman' at its nominal value")


class Meta(BaseModel):
    model_config = ConfigDict(extra="allow")

    service: str = desc("service name (no unit)")
    api_version: str = desc("API version (no unit)")
    code_version: str = desc("code version (no unit)")
    data_version: str = desc("optical data version (no unit)")
    tables: dict[str, Any] = desc("metadata of the shipped slope tables (settings, fingerprint, units)")
    bands: list[str] = desc("Roman bands (no unit)")
    table_bands: list[str] = desc("bands with shipped tables (no unit)")
    scas: list[int] = desc("detector numbers (no unit)")
    metrics: list[str] = desc("PSF metrics (no unit)")
    modes: list[str] = desc("modes (no unit)")
    fidelities: list[str] = desc("solve fidelity levels (no unit)")
    simulation_fidelities: list[str] = desc("simulation fidelity levels (no unit)")
    defaults: dict[str, Any] = desc("request defaults, in the units of the request fields")
    limits: dict[str, Any] = desc("service limits (counts, s, MB, bytes as named)")
    flag_codes: list[FlagCatalogueEntry] = desc("every flag code an answer or a simulation result may carry (nlpsf.flags)")
    scene_effects: list[SceneEffectEntry] = desc("the scene effects, in the order they act (nlpsf.sim.scene.REGISTRY)")


class TableJSON(BaseModel):
    meta: dict[str, Any] = desc("metadata of the tables (settings, fingerprint; units under 'units')")
    rows: list[dict[str, Any]] = desc(
        "one row per (band, SCA, magnitude): magnitude in AB mag, flux_electrons in e-, peak_electrons in e- per fine "
        "pixel x N^2, slopes bias_* / scatter_* and their _err / _interp in e- (metric per 1/e- of beta or sigma_beta)"
    )


class Fits(BaseModel):
    fits: list[dict[str, Any]] | dict[str, Any] = desc(
        "power-law fits slope = A 10^(B (m - 20)): A in e- (metric per 1/e-), B in 1/mag, per band, SCA and mode"
    )


class SlopeCurve(BaseModel):
    model_config = ConfigDict(extra="allow")

    band: str = desc("Roman band (no unit)")
    sca: int = desc("detector (no unit)")
    magnitude: list[float] = desc("magnitudes in AB mag")
    slope: list[float | None] = desc("slope c(m) in e- (metric per 1/e- of beta or sigma_beta), signed")
    uncertainty: list[float | None] = desc("statistical 1-sigma uncertainty of the slope in e-")
    fidelity_relative_uncertainty: float | None = desc("the table level's measured relative error (dimensionless)", None)
    saturation_magnitude: float | None = desc("saturation magnitude in AB mag")
    conditions: dict[str, Any] = desc("conditions: exposure in s, beta0 in 1/e-, full well in e-, settings")


class SlopeCurves(BaseModel):
    source: str = desc("where the numbers come from (text)")
    metric: str = desc("the PSF metric (no unit)")
    mode: str = desc("bias or scatter (no unit)")
    curves: list[SlopeCurve] = desc("one curve per band")


class LinearCurve(BaseModel):
    model_config = ConfigDict(extra="allow")

    source: str = desc("where the numbers come from (text)")
    band: str = desc("Roman band (no unit)")
    sca: int = desc("detector (no unit)")
    metric: str = desc("the PSF metric (no unit)")
    magnitude: float = desc("star magnitude in AB mag")
    values: list[float | None] = desc("the metric (dimensionless) at each beta or sigma_beta")
    uncertainty: list[float | None] = desc("statistical 1-sigma uncertainty of each value (dimensionless)")
    fidelity_relative_uncertainty: float | None = desc("the table level's measured relative error (dimensionless)", None)
    slope: float | None = desc("slope in e- (metric per 1/e-)")
    flags: list[str] = desc("validity warnings (text)")
    flag_codes: list[str] = desc("the code of each flag, in the same order (catalogue: GET /api/v1/meta → flag_codes)")
    saturation_magnitude: float | None = desc("saturation magnitude in AB mag")
    conditions: dict[str, Any] = desc("conditions: exposure in s, beta0 in 1/e-, full well in e-, settings")


class BetaCurve(LinearCurve):
    beta: list[float] = desc("NL coefficients beta in 1/e-")


class SigmaBetaCurve(LinearCurve):
    sigma_beta: list[float] = desc("per-pixel beta scatter sigma_beta in 1/e-")


class PaperData(BaseModel):
    model_config = ConfigDict(extra="allow")

    magnitudes: list[float] = desc("the paper's magnitudes in AB mag")
