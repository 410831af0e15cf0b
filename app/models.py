"""Request and response models of the REST API (the OpenAPI schema at /docs comes from these).

Requests are strict (no string-to-number coercion, no unknown fields, no NaN or infinity): a wrong
type or a typo is a 422 naming the field, never a silently different question. Ranges are the
library's to check, so the service and the CLI refuse the same things with the same words.
"""

from __future__ import annotations

import inspect
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from nlpsf import defaults, detector, fidelity, roman, solver

_STRICT = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)

_SOLVE_DEFAULTS = {
    name: parameter.default
    for name, parameter in inspect.signature(solver.solve).parameters.items()
    if parameter.default is not inspect.Parameter.empty
}

#: A [ratio, weight] pair of a size-ratio distribution.
_RatioWeight = Annotated[list[float], Field(min_length=2, max_length=2)]
Metric = Literal[solver.METRICS]  # type: ignore[valid-type]
Mode = Literal[solver.MODES]  # type: ignore[valid-type]
Fidelity = Literal[solver.FIDELITIES]  # type: ignore[valid-type]
SimulationFidelity = Literal[fidelity.SIMULATION_LEVELS]  # type: ignore[valid-type]
BetaConvention = Literal[detector.BETA_CONVENTIONS]  # type: ignore[valid-type]
PupilScale = Literal[roman.PUPIL_SCALE_RULES]  # type: ignore[valid-type]
Throughput = Literal[roman.THROUGHPUTS]  # type: ignore[valid-type]
RampFit = Literal[defaults.RAMP_FITS]  # type: ignore[valid-type]


class SceneRequest(BaseModel):
    """Scene effects beyond the paper's idealised scene (``nlpsf.scene``); every field off unless given."""

    model_config = ConfigDict(**_STRICT, json_schema_extra={"examples": [{"preset": "roman"}, {"jitter": 0.014, "ipc": "roman"}]})

    preset: Literal["paper", "roman"] | None = Field(
        None, description="roman: jitter 0.014 arcsec, charge diffusion 0.1 px, GalSim's IPC kernel, flat f_nu SED"
    )
    position: list[float] | None = Field(None, min_length=2, max_length=2, description="X, Y on the SCA in pixels (1-4088)")
    sed: str | None = Field(None, description="flat (f_nu) or blackbody:TEFF")
    sed_table: list[list[float]] | None = Field(None, max_length=20_000, description="the SED as rows [wavelength nm, flux]")
    sed_units: Literal["flambda", "fnu"] = Field("flambda", description="what sed_table's flux is")
    n_wavelengths: int | None = Field(None, description="wavelengths for the SED (default: chosen for 0.1 % of the slopes)")
    jitter: float | None = Field(None, description="pointing jitter, arcsec rms per axis (Roman 0.014)")
    charge_diffusion: float | None = Field(None, description="charge diffusion, native pixels rms (GalSim's Roman 0.1)")
    ipc: str | float | list[list[float]] | None = Field(
        None, description="interpixel capacitance: roman, a nearest-neighbour alpha, or a 3x3 kernel (rows y, columns x)"
    )
    ipc_order: Literal["after", "before"] | None = Field(None, description="IPC after (default, as GalSim) or before the NL")
    nl_coefficients: list[float] | None = Field(
        None, max_length=6, description="NL beyond the quadratic: b3, b4, ... in S = Q - beta Q^2 - b3 Q^3 - ..."
    )
    bfe: float | None = Field(None, description="brighter-fatter coefficient in 1/e- (Antilogus et al. 2014, nearest neighbours)")
    background: float | None = Field(None, description="sky + dark in e- per native pixel over the exposure")


class MATableSpec(BaseModel):
    """An MA table given inline: resultants as lists of 1-based read indices."""

    model_config = _STRICT

    resultants: list[list[int]] = Field(description="resultants as lists of read indices, e.g. [[1], [2, 3], [4, 5, 6]]")
    frame_time_s: float = Field(defaults.ROMAN_FRAME_TIME_S, description="time between reads in s")
    name: str = Field("custom", max_length=64, description="a label for the conditions")


class RampFields(BaseModel):
    """Up the ramp instead of the paper's single final frame (see nlpsf.ramps)."""

    ramp: int | None = Field(None, description="N uniformly spaced reads over the exposure, one per resultant")
    ma_table: str | MATableSpec | None = Field(
        None,
        description="MultiAccum table: a shipped name (romanisim-1, romanisim-109, romanisim-110) or the table itself; "
        "without an exptime the exposure is the table's last read",
    )
    ramp_fit: RampFit = Field("ols", description="slope fit: ols, or optimal (read + Poisson noise weighting)")
    read_noise: float | None = Field(
        None, description="read noise per read in e- (optimal fit); default: the SCA's official value (CDS noise / sqrt 2)"
    )

    def ramp_arguments(self, exptime: float, sca: int = defaults.SCA) -> tuple[object, float]:
        """(ramps.Ramp or None, exposure time): the library's one rule for both (an MA table's
        exposure is its last read unless the request gives ``exptime``)."""
        from nlpsf import ramps

        table = self.ma_table.model_dump() if isinstance(self.ma_table, MATableSpec) else self.ma_table
        given = exptime if "exptime" in self.model_fields_set else None
        return ramps.build(self.ramp, table, self.ramp_fit, self.read_noise, given, allow_files=False, sca=sca)


class SolveRequest(RampFields):
    """The two-of-three calculator: give exactly two of precision, tolerance, magnitude."""

    model_config = ConfigDict(
        **_STRICT,
        json_schema_extra={"examples": [{"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}]},
    )

    band: str = Field(description=f"Roman band: {', '.join(roman.BANDS)}")
    sca: int = Field(_SOLVE_DEFAULTS["sca"], description=f"detector 1-{roman.N_SCA}")
    metric: Metric = Field(_SOLVE_DEFAULTS["metric"], description="size (dR/R), e1, e2 or e (|de|)")
    mode: Mode = Field(_SOLVE_DEFAULTS["mode"], description="bias (calibration error of beta) or scatter (per-pixel sigma_beta)")
    beta0: float = Field(_SOLVE_DEFAULTS["beta0"], description="NL coefficient beta0 in 1/e- (paper convention S = Q - beta Q^2)")
    exptime: float = Field(_SOLVE_DEFAULTS["exptime"], description="exposure time in s")
    precision: float | None = Field(None, description="calibration precision: dbeta/beta0 (bias) or sigma_beta/beta0 (scatter)")
    tolerance: float | None = Field(None, description="tolerated error of the metric (dR/R, de1, de2 or |de|)")
    magnitude: float | None = Field(None, description="AB magnitude of the brightest star used for the PSF model")
    full_well: float = Field(_SOLVE_DEFAULTS["full_well"], description="full-well depth in e-")
    fidelity: Fidelity | None = Field(
        _SOLVE_DEFAULTS["fidelity"],
        description="how the slope is obtained: table (instant, the default), linear, monte_carlo, polychromatic",
    )
    accuracy: float | None = Field(
        None,
        description="relative accuracy target: picks the cheapest fidelity meeting it, simulates only the scene effects whose "
        "measured impact exceeds it and adds the others to the uncertainty's model part",
    )
    scene: SceneRequest | None = Field(None, description="what the star goes through (default the paper's scene)")
    over_field: Literal["sca", "focal_plane"] | None = Field(
        None,
        description="answer for the worst position: over the SCA's five field points (sca) or all 18 SCAs' (focal_plane); "
        "simulates (seconds per point)",
    )
    throughput: Throughput | None = Field(
        None, description="photometry of the magnitude: null for the tables' own (roman-2024), or galsim-2021"
    )
    shear_m: float | None = Field(
        None, description="multiplicative shear-bias budget |m| (size metric); with size_ratio, in place of tolerance"
    )
    shear_c: float | None = Field(
        None, description="additive shear-bias budget |c| (e1, e2, e metrics); with size_ratio, in place of tolerance"
    )
    # No strings here: the library also reads '@FILE', which a web request must not reach.
    size_ratio: float | list[float | _RatioWeight] | None = Field(
        None,
        description="R_gal/R_psf (intrinsic galaxy over PSF, R = det(M)^(1/4)): a number, or a list of ratios or "
        "[ratio, weight] pairs; alone it reports the shear bias the tolerance implies",
    )
    stars: int = Field(
        _SOLVE_DEFAULTS["stars"],
        description="scatter mode: stars/dithers on independent pixels the PSF model averages (sigma / sqrt(stars))",
    )


class SolveResponse(BaseModel):
    """The same object as ``nlpsf solve --json`` (``Solution.to_dict()``)."""

    model_config = ConfigDict(extra="allow")

    band: str
    sca: int
    metric: str
    mode: str
    beta0: float
    exptime: float
    precision: float | None
    tolerance: float | None
    magnitude: float | None
    solved_for: str
    uncertainty: float | None
    slope: float | None
    saturation_magnitude: float | None
    stars: int
    applies_to: str
    shear: dict[str, Any] | None
    flags: list[str]
    fidelity: str
    conditions: dict[str, Any]


class FieldError(BaseModel):
    loc: list[str | int] = Field(description="where in the request: ['body', field] or ['query', name]")
    field: str | None = Field(description="the request field at fault")
    msg: str
    type: str


class Problem(BaseModel):
    """Every error: a readable message, the field at fault (if any) and, for caps, the limit's name."""

    message: str
    field: str | None = None
    limit: str | None = None
    detail: list[FieldError] = Field(default_factory=list)


class ImpactRequest(BaseModel):
    """What each scene effect changes in the slopes at one point (``nlpsf impact``)."""

    model_config = ConfigDict(
        **_STRICT, json_schema_extra={"examples": [{"band": "H158", "sca": 18, "magnitude": 18.3, "scene": {"preset": "roman"}}]}
    )

    band: str = Field(defaults.BAND, description=f"Roman band: {', '.join(roman.BANDS)}")
    sca: int = Field(defaults.SCA, description=f"detector 1-{roman.N_SCA}")
    magnitude: float = Field(defaults.MAGNITUDE, description="AB magnitude of the star")
    metric: Metric = Field("size", description="the request's metric")
    mode: Mode = Field("bias", description="bias or scatter slopes")
    beta0: float = Field(defaults.BETA0, description="beta0 in 1/e- (paper convention)")
    exptime: float = Field(defaults.EXPTIME_S, description="exposure time in s")
    realizations: int = Field(50, description="centroid realizations per run (both runs of an effect share them)")
    seed: int = Field(1, description="random seed")
    scene: SceneRequest | None = Field(None, description="the scene; effects it leaves off are measured at nominal values")


class SimulationRequest(RampFields):
    """A fresh simulation on the grid magnitudes x betas x sigma_betas (paper's defaults)."""

    model_config = ConfigDict(
        **_STRICT,
        json_schema_extra={"examples": [{"band": "H158", "magnitudes": [18.3, 20.0], "betas": [5e-7], "realizations": 20}]},
    )

    band: str = Field(defaults.BAND, description=f"Roman band: {', '.join(roman.BANDS)}")
    sca: int = Field(defaults.SCA, description=f"detector 1-{roman.N_SCA}")
    magnitudes: list[float] = Field([18.3], max_length=10_000, description="AB magnitudes")
    betas: list[float] = Field([defaults.BETA0], max_length=10_000, description="NL coefficients beta in 1/e-")
    sigma_betas: list[float] = Field(
        [0.0], max_length=10_000, description="per-pixel beta scatter; > 0 draws beta maps at a fixed centroid"
    )
    beta_convention: BetaConvention = Field("paper", description="paper: S = Q - beta Q^2; galsim: S = Q + beta Q^2")
    exptime: float = Field(defaults.EXPTIME_S, description="exposure time in s")
    full_well: float = Field(defaults.FULL_WELL_E, description="full-well depth in e-")
    fidelity: SimulationFidelity = Field("monte_carlo", description="linear response, Monte Carlo, or Monte Carlo polychromatic")
    n_wavelengths: int | None = Field(None, description="wavelengths of the polychromatic PSF (default 8)")
    realizations: int = Field(100, description="centroid realizations, or beta-map draws when sigma_beta > 0")
    seed: int = Field(1, description="random seed; the same seed gives the same numbers")
    oversampling: int = Field(3, description="fine pixels per native pixel, N")
    stamp: int = Field(96, description="stamp side in fine pixels")
    weight_cut_rho2: float = Field(
        defaults.PAPER_WEIGHT_CUT_RHO2, description="adaptive-moment weight cut rho^2 (paper 25, GalSim 32.24)"
    )
    pupil_scale: PupilScale = Field("galsim", description="pupil mask scale rule")
    scene: SceneRequest | None = Field(None, description="scene effects (position, SED, jitter, IPC, ...); default the paper's")
    throughput: Throughput = Field(
        defaults.THROUGHPUT,
        description="effective-area data: roman-2024 (official, per SCA) or galsim-2021 (GalSim's, the paper comparison)",
    )


JobState = Literal["queued", "running", "done", "failed", "cancelled", "interrupted"]


class Job(BaseModel):
    """A simulation job; ``result`` is filled once ``status`` is done."""

    id: str
    status: JobState
    progress: float = Field(description="fraction done, 0 to 1")
    message: str
    cached: bool = Field(description="answered from stored results of an identical earlier request")
    cancel_requested: bool
    queue_position: int | None
    request: dict[str, Any]
    request_hash: str
    created_at: float
    started_at: float | None
    finished_at: float | None
    updated_at: float
    error: dict[str, Any] | None
    result: dict[str, Any] | None


class JobList(BaseModel):
    jobs: list[Job]
    counts: dict[str, int]
