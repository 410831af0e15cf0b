"""Request and response models of the REST API (the OpenAPI schema at /docs comes from these).

Requests are strict (no string-to-number coercion, no unknown fields, no NaN or infinity): a wrong
type or a typo is a 422 naming the field, never a silently different question. Ranges are the
library's to check, so the service and the CLI refuse the same things with the same words.
"""

from __future__ import annotations

import inspect
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field

from nlpsf import defaults, roman
from nlpsf.request import shear
from nlpsf.request.resolve import MAX_STARS
from nlpsf.sim import detector, levels, ramps
from nlpsf.sim import scene as scenes
from nlpsf.solve import solver

_STRICT = ConfigDict(extra="forbid", strict=True, allow_inf_nan=False)


def _within(
    bounds: tuple[float, float], description: str, default: Any = None, *, open_low: bool = False, in_type: bool = False
) -> Any:
    """A field whose range is the library's (``bounds``, its one owner): enforced at the entry as a
    422 naming the field, and published in the OpenAPI schema (minimum/maximum) and its description.
    ``in_type``: the bounds are on the field's type already (``_Int``), only the description says them."""
    low, high = bounds
    opening = "(" if open_low else "["
    limits = {} if in_type else {"gt" if open_low else "ge": low, "le": high}
    return Field(default, **limits, description=f"{description}; accepted {opening}{low:g}, {high:g}]")


def _Int(bounds: tuple[int, int]) -> Any:
    """An integer in the library's range that also takes 3.0 (see ``_whole``). The bounds sit inside
    the type, before the validator, so that the schema shows them as minimum/maximum."""
    return Annotated[int, Field(ge=bounds[0], le=bounds[1]), BeforeValidator(_whole)]


#: The integer field type for the other request models (calibration_models) too.
BoundedInt = _Int


def _whole(value: Any) -> Any:
    # JSON Schema calls 1.0 an integer (a number with a zero fractional part); so does this API.
    # Strings stay refused (strict models), and so do 1.5 and floats too large to be exact.
    if isinstance(value, float) and value.is_integer() and abs(value) <= 2**53:
        return int(value)
    return value


def _Number(bounds: tuple[float, float]) -> Any:
    """One number in the library's range (for list items and union members)."""
    return Annotated[float, Field(ge=bounds[0], le=bounds[1])]


#: Seeds over JSON: the library takes up to 2^63 - 1, but a JSON number above 2^53 is not exact in
#: most clients (JavaScript's), nor in a schema checker's float arithmetic; 2^53 seeds are plenty.
JSON_SEEDS = (defaults.SEED_RANGE[0], min(defaults.SEED_RANGE[1], 2**53))

#: The MA tables the service knows, by name (case-insensitive). The API never opens a file by a name
#: it was given: anything else is one refusal, the same words for every unknown name.
SHIPPED_MA_TABLES: tuple[str, ...] = tuple(ramps.shipped_table_names())
ShippedMATable = Annotated[
    Literal[SHIPPED_MA_TABLES],  # type: ignore[valid-type]
    BeforeValidator(lambda value: value.strip().lower() if isinstance(value, str) and len(value) <= 64 else value),
]
#: ``blackbody:TEFF`` with TEFF in the library's range (1000 K to 1e6 K), ``flat``, or a vendored
#: spectrum by name (``nlpsf.roman.seds.NAMED``: ``k0v``).
SED_PATTERN = r"^(flat|k0v|blackbody:([1-9][0-9]{3,5}(\.[0-9]{0,6})?|1000000(\.0{0,6})?))$"

_SOLVE_DEFAULTS = {
    name: parameter.default
    for name, parameter in inspect.signature(solver.solve).parameters.items()
    if parameter.default is not inspect.Parameter.empty
}

#: R_gal / R_psf, and a [ratio, weight] pair of a size-ratio distribution (ranges: ``nlpsf.request.shear``).
_Ratio = Annotated[float, Field(ge=shear.SIZE_RATIO_RANGE[0], le=shear.SIZE_RATIO_RANGE[1])]


def _array_as_pair(value: Any) -> Any:
    # A JSON array is a list; strict models take a tuple only as a tuple. Strict(False) on the tuple
    # did this from pydantic 2.8 on, not in 2.7 (the declared minimum), inside a union.
    return tuple(value) if isinstance(value, list) else value


_RatioWeight = Annotated[tuple[_Ratio, Annotated[float, Field(ge=0.0, le=shear.MAX_WEIGHT)]], BeforeValidator(_array_as_pair)]
_RatioList = Annotated[list[_Ratio | _RatioWeight], Field(min_length=1, max_length=shear.MAX_SIZE_RATIOS)]


def _band_name(value: Any) -> Any:
    # Band names are case-insensitive (as in the library and the CLI); the schema lists the canonical ones.
    return value.upper() if isinstance(value, str) else value


Band = Annotated[Literal[roman.BANDS], BeforeValidator(_band_name)]  # type: ignore[valid-type]
Metric = Literal[solver.METRICS]  # type: ignore[valid-type]
Mode = Literal[solver.MODES]  # type: ignore[valid-type]
Fidelity = Literal[solver.FIDELITIES]  # type: ignore[valid-type]
SimulationFidelity = Literal[levels.SIMULATION_LEVELS]  # type: ignore[valid-type]
BetaConvention = Literal[detector.BETA_CONVENTIONS]  # type: ignore[valid-type]
PupilScale = Literal[roman.PUPIL_SCALE_RULES]  # type: ignore[valid-type]
Throughput = Literal[roman.THROUGHPUTS]  # type: ignore[valid-type]
RampFit = Literal[defaults.RAMP_FITS]  # type: ignore[valid-type]


ScenePreset = Literal["roman", "paper", "galsim-roman"]


def _preset_object(value: Any) -> Any:
    """A scene given as a preset's name ("paper") is that preset's scene object."""
    return {"preset": value} if isinstance(value, str) else value


class SceneRequest(BaseModel):
    """Scene effects beyond the paper's idealised scene (``nlpsf.sim.scene``); every field off unless given."""

    model_config = ConfigDict(**_STRICT, json_schema_extra={"examples": [{"preset": "roman"}, {"jitter": 0.014, "ipc": "roman"}]})

    preset: ScenePreset | None = Field(
        None,
        description="(no unit) the base the other fields change: roman (the Roman default, nlpsf.request.presets; the "
        "default), paper (the paper's idealised scene), galsim-roman (jitter 0.014 arcsec, charge diffusion 0.1 px, "
        "GalSim's IPC kernel, flat f_nu SED)",
    )
    position: list[_Number((1.0, float(roman.SCA_PIXELS)))] | None = Field(
        None, min_length=2, max_length=2, description=f"X, Y on the SCA in pixels (1-{roman.SCA_PIXELS})"
    )
    sed: str | None = Field(
        None,
        max_length=32,
        pattern=SED_PATTERN,
        description="(no unit) flat (f_nu), k0v (the Pickles 1998 K0V spectrum) or blackbody:TEFF (TEFF in K, 1000-1e6)",
    )
    sed_table: list[Annotated[list[Annotated[float, Field(ge=0)]], Field(min_length=2, max_length=2)]] | None = Field(
        None, min_length=2, max_length=20_000, description="the SED as rows [wavelength in nm, flux in sed_units]"
    )
    sed_units: Literal["flambda", "fnu"] = Field(
        "flambda", description="(no unit) what sed_table's flux is: flambda or fnu, any scale"
    )
    n_wavelengths: _Int((1, defaults.MAX_WAVELENGTHS)) | None = _within(
        (1, defaults.MAX_WAVELENGTHS),
        "number of wavelengths for the SED (count; default: chosen for 0.1 % of the slopes)",
        in_type=True,
    )
    jitter: float | None = _within((0.0, scenes.MAX_JITTER_ARCSEC), "pointing jitter, arcsec rms per axis (Roman 0.014)")
    charge_diffusion: float | None = _within(
        (0.0, scenes.MAX_DIFFUSION_PX), "charge diffusion, native pixels rms (GalSim's Roman 0.1)"
    )
    ipc: (
        Literal["roman", "none", "off"]
        | _Number((0.0, scenes.MAX_IPC_ALPHA))
        | Annotated[
            list[Annotated[list[Annotated[float, Field(ge=0)]], Field(min_length=3, max_length=3)]],
            Field(min_length=3, max_length=3),
        ]
        | None
    ) = Field(
        None,
        description="interpixel capacitance: roman, a nearest-neighbour alpha (dimensionless fraction), or a 3x3 kernel "
        "(dimensionless, rows y, columns x)",
    )
    ipc_order: Literal["after", "before"] | None = Field(
        None, description="(no unit) IPC after (default, as GalSim) or before the NL"
    )
    nl_coefficients: list[float] | None = Field(
        None,
        max_length=scenes.MAX_NL_ORDER - 2,
        description="NL beyond the quadratic: b3 in 1/e-^2, b4 in 1/e-^3, ... in S = Q - beta Q^2 - b3 Q^3 - ...; "
        "the response must rise (dS/dQ > 0) from 0 to the full well, else 422",
    )
    bfe: float | None = _within(
        (-scenes.MAX_BFE, scenes.MAX_BFE),
        "brighter-fatter coefficient in 1/e- (Antilogus et al. 2014, nearest neighbours); |bfe| x full_well must stay "
        "below 1 (the first-order model), else 422",
    )
    background: float | None = _within((0.0, scenes.MAX_BACKGROUND_E), "sky + dark in e- per native pixel over the exposure")


class MATableSpec(BaseModel):
    """An MA table given inline: resultants as lists of 1-based read indices."""

    model_config = _STRICT

    resultants: list[
        Annotated[list[_Int((1, defaults.MAX_RAMP_READS))], Field(min_length=1, max_length=defaults.MAX_RAMP_READS)]
    ] = Field(
        min_length=1,
        max_length=defaults.MAX_RAMP_READS,
        description="resultants as lists of 1-based read indices (dimensionless), e.g. [[1], [2, 3], [4, 5, 6]]",
    )
    frame_time_s: float = _within(
        defaults.FRAME_TIME_RANGE_S, "time between reads in s", defaults.ROMAN_FRAME_TIME_S, open_low=True
    )
    name: str = Field("custom", max_length=64, description="a label for the conditions (text, no unit)")


class RampFields(BaseModel):
    """Up the ramp instead of the paper's single final frame (see nlpsf.sim.ramps)."""

    ramp: _Int((1, defaults.MAX_RAMP_READS)) | None = _within(
        (1, defaults.MAX_RAMP_READS), "N uniformly spaced reads over the exposure, one per resultant (count)", in_type=True
    )
    ma_table: ShippedMATable | MATableSpec | None = Field(
        None,
        description=f"MultiAccum table (no unit): a shipped name ({', '.join(SHIPPED_MA_TABLES)}) or the table itself "
        "(never a file on the server); without an exptime the exposure is the table's last read",
    )
    ramp_fit: RampFit | None = Field(
        None,
        description="slope fit (no unit): ols, or optimal (read + Poisson noise weighting); null: the scene's (the "
        "Roman default: optimal, romancal's likelihood fit, on its HLWAS table unless a ramp or MA table is given; the "
        "paper's: ols)",
    )
    read_noise: float | None = _within(
        defaults.READ_NOISE_RANGE_E,
        "read noise per read in e- (optimal fit: > 0); default: the SCA's official value (CDS noise / sqrt 2)",
    )


def shipped_ma_table(name: str) -> ramps.MATable:
    """A shipped MA table by its (validated) name, read from the package's own data folder only."""
    import json

    if name not in SHIPPED_MA_TABLES:  # unreachable past the model; kept so no caller can pass a path
        raise ValueError("not a shipped MA table")
    return ramps.MATable.from_dict(json.loads((ramps.shipped_table_dir() / f"{name}.json").read_text()), name=name)


def build_ramp(reads, ma_table, fit, read_noise, exptime, sca) -> tuple[object, float]:
    """``ramps.build`` for the web layer: a name becomes the shipped table before the library sees
    it, so no string the client sent ever reaches a file-system call."""
    table = shipped_ma_table(ma_table) if isinstance(ma_table, str) else ma_table
    return ramps.build(reads, table, fit, read_noise, exptime, allow_files=False, sca=sca)


class SolveRequest(RampFields):
    """The two-of-three calculator: give exactly two of precision, tolerance, magnitude."""

    model_config = ConfigDict(
        **_STRICT,
        json_schema_extra={"examples": [{"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}]},
    )

    band: Band = Field(description=f"Roman band (no unit): {', '.join(roman.BANDS)}")
    sca: _Int((1, roman.N_SCA)) = Field(_SOLVE_DEFAULTS["sca"], description=f"detector (SCA number, no unit) 1-{roman.N_SCA}")
    metric: Metric = Field(_SOLVE_DEFAULTS["metric"], description="the PSF metric (no unit): size (dR/R), e1, e2 or e (|de|)")
    mode: Mode = Field(
        _SOLVE_DEFAULTS["mode"], description="(no unit) bias: calibration error of beta; scatter: per-pixel sigma_beta"
    )
    beta0: float = _within(
        defaults.BETA0_RANGE, "NL coefficient beta0 in 1/e- (paper convention S = Q - beta Q^2)", _SOLVE_DEFAULTS["beta0"]
    )
    exptime: float | None = _within(
        defaults.EXPTIME_RANGE_S,
        "exposure time in s; null: the scene's (the Roman default's HLWAS table's last read, 139.149 s; the "
        "paper's 168.1 s; an MA table's last read)",
    )
    precision: float | None = _within(
        defaults.PRECISION_RANGE,
        "calibration precision, dimensionless fraction: dbeta/beta0 (bias) or sigma_beta/beta0 (scatter)",
    )
    tolerance: float | None = _within(
        defaults.TOLERANCE_RANGE, "tolerated error of the metric, dimensionless (dR/R, de1, de2 or |de|)"
    )
    magnitude: float | None = _within(
        defaults.MAGNITUDE_RANGE, "magnitude of the brightest star used for the PSF model, in AB mag in the band"
    )
    full_well: float = _within(defaults.FULL_WELL_RANGE_E, "full-well depth in e-", _SOLVE_DEFAULTS["full_well"])
    fidelity: Fidelity | None = Field(
        _SOLVE_DEFAULTS["fidelity"],
        description="how the slope is obtained (no unit): table (instant, the default), linear, monte_carlo, polychromatic",
    )
    accuracy: float | None = Field(
        None,
        ge=defaults.ACCURACY_RANGE[0],
        le=defaults.ACCURACY_RANGE[1],
        description=f"accepted [{defaults.ACCURACY_RANGE[0]:g}, {defaults.ACCURACY_RANGE[1]:g}]; "
        "relative accuracy target (dimensionless fraction): picks the cheapest fidelity meeting it, "
        "simulates only the scene effects whose measured impact exceeds it and adds the others to the uncertainty's model part",
    )
    scene: ScenePreset | SceneRequest | None = Field(
        None,
        description="what the star goes through: a preset's name or its fields (units per field); default the Roman "
        "default (nlpsf.request.presets: its scene at the position, the HLWAS readout, official pupil scale, linearised at "
        "corrected; without a position, the most demanding of the SCA's field-grid nodes); 'paper': the paper's "
        "idealised scene and the shipped tables",
    )
    linearise_at: Literal["beta0", "corrected"] | None = Field(
        None,
        description="(no unit) the detector state the slope is taken at: null for the scene's (roman: corrected; paper: beta0)",
    )
    residual_nl: Literal["per_resultant_correction", "per_read_beta"] | None = Field(
        None,
        description="(no unit) how a calibration error acts in the corrected state: null for the default "
        "(per_resultant_correction: the linearity correction on every resultant of the measured signal, as romancal "
        "applies it); per_read_beta: the earlier model, a residual beta on every read before IPC",
    )
    over_field: Literal["sca", "focal_plane"] | None = Field(
        None,
        description="(no unit) answer for the worst position: over the SCA's centre and four corner field points (sca) "
        "or all 18 SCAs' 90 points (focal_plane); from the shipped field-point tables at table fidelity (milliseconds), "
        "simulated (seconds per point, a job) with a scene, a simulating level or an accuracy",
    )
    throughput: Throughput | None = Field(
        None, description="photometry of the magnitude (no unit): null for the tables' own (roman-2024), or galsim-2021"
    )
    pupil_scale: PupilScale | None = Field(
        None,
        description="pupil mask scale rule of fresh simulations (no unit): null for the tables' own (galsim); "
        "header or official simulates the slopes (a job)",
    )
    shear_m: float | None = Field(
        None,
        ge=shear.BUDGET_RANGE[0],
        le=shear.BUDGET_RANGE[1],
        description="multiplicative shear-bias budget |m|, dimensionless (size metric); with size_ratio, in place of tolerance",
    )
    shear_c: float | None = Field(
        None,
        ge=shear.BUDGET_RANGE[0],
        le=shear.BUDGET_RANGE[1],
        description="additive shear-bias budget |c|, dimensionless (e1, e2, e metrics); with size_ratio, in place of tolerance",
    )
    # No strings here: the library also reads '@FILE', which a web request must not reach.
    size_ratio: _Ratio | _RatioList | None = Field(
        None,
        description="R_gal/R_psf, dimensionless (intrinsic galaxy over PSF, R = det(M)^(1/4)): a number, or a list of ratios or "
        "[ratio, weight] pairs; alone it reports the shear bias the tolerance implies",
    )
    stars: _Int((1, MAX_STARS)) = Field(
        _SOLVE_DEFAULTS["stars"],
        description="scatter mode: number of stars/dithers on independent pixels the PSF model averages (sigma / sqrt(stars))",
    )


def desc(description: str, default: Any = ...) -> Any:
    """A field with its description (``...``: required)."""
    return Field(default, description=description)


class SolveResponse(BaseModel):
    """The same object as ``nlpsf solve --json`` (``Solution.to_dict()``)."""

    model_config = ConfigDict(extra="allow")

    band: str = desc("Roman band (no unit)")
    sca: int = desc("detector (SCA number, no unit)")
    metric: str = desc("the PSF metric (no unit): size, e1, e2 or e")
    mode: str = desc("bias or scatter (no unit)")
    beta0: float = desc("NL coefficient beta0 in 1/e- (paper convention)")
    exptime: float = desc("exposure time in s")
    full_well: float | None = desc("full-well depth in e-", None)
    precision: float | None = desc("calibration precision, dimensionless fraction of beta0")
    tolerance: float | None = desc("tolerated error of the metric, dimensionless")
    magnitude: float | None = desc("star magnitude in AB mag")
    solved_for: str = desc("which of precision, tolerance, magnitude was solved for (no unit)")
    uncertainty: float | None = desc("1-sigma uncertainty of the solved quantity, in its unit")
    uncertainty_statistical: float | None = desc("statistical part of the uncertainty, in the solved quantity's unit", None)
    uncertainty_fidelity: float | None = desc("fidelity (method) part of the uncertainty, in the solved quantity's unit", None)
    uncertainty_optical_model: float | None = desc("optical-model part of the uncertainty, in the solved quantity's unit", None)
    uncertainty_model: float | None = desc(
        "scene-model part of the uncertainty (effects left out and the pupil-scale rule), in the solved quantity's unit", None
    )
    model: dict[str, Any] | None = desc(
        "the scene effects the answer includes and leaves out, each with its relative impact on the slope and why", None
    )
    slope: float | None = desc("slope c(m) = d(metric)/d(beta) or sigma(metric)/sigma_beta, in e- (metric per 1/e-)")
    slope_uncertainty: float | None = desc("1-sigma uncertainty of the slope in e-", None)
    saturation_magnitude: float | None = desc("magnitude (AB mag) brighter than which the brightest pixel saturates")
    final_frame_saturation_magnitude: float | None = desc("saturation magnitude (AB mag) of a single final frame", None)
    brightest_usable_magnitude: float | None = desc("brightest usable star in AB mag (magnitude solves)", None)
    binding_limit: str | None = desc("which limit sets the brightest usable star: nonlinearity or saturation (no unit)", None)
    nonlinearity_magnitude: float | None = desc("magnitude (AB mag) at which the NL error reaches the tolerance", None)
    stars: int = desc("number of stars/dithers averaged (count)")
    applies_to: str = desc("what the tolerance applies to (text)")
    shear: dict[str, Any] | None = desc("shear-bias budget and the tolerance it implies (dimensionless values)")
    flags: list[str] = desc("warnings about the answer's validity (text)")
    flag_codes: list[str] = desc(
        "the code of each flag, in the same order (flag_codes[i] is flags[i]'s; the catalogue: GET /api/v1/meta → flag_codes)"
    )
    fidelity: str = desc("the fidelity level used (no unit)")
    conservative: dict[str, Any] | None = desc(
        "the answer that holds if the slope is at the top of its uncertainty: the solved quantity (its unit), "
        "relative_slope_bound (dimensionless) and its coverage (text)",
        None,
    )
    ranges: dict[str, Any] | None = desc(
        "what varies from star to star (e.g. the SED): each range's ends, the slope's relative change there "
        "(dimensionless) and the solved quantity there (its unit); not an uncertainty",
        None,
    )
    conditions: dict[str, Any] = desc("the conditions of the answer: band, SCA, exposure (s), beta0 (1/e-), settings")


class FieldError(BaseModel):
    loc: list[str | int] = Field(description="where in the request: ['body', field] or ['query', name]")
    field: str | None = Field(description="the request field at fault (no unit)")
    msg: str = Field(description="what is wrong (text)")
    type: str = Field(description="the kind of error (no unit)")


class Problem(BaseModel):
    """Every error, as RFC 9457 problem details (media type application/problem+json), with extensions:
    the field at fault (if any), the limit's name (for caps) and every bad field found."""

    type: str = Field("about:blank", description="URI reference naming the kind of problem (RFC 9457; text, no unit)")
    title: str = Field("", description="short summary of the kind of problem (the HTTP status phrase, text)")
    status: int = Field(0, description="the HTTP status code (no unit)")
    detail: str = Field("", description="a readable explanation of this occurrence (text)")
    message: str = Field(description="the same text as detail (kept for older clients)")
    field: str | None = Field(None, description="the request field at fault (no unit)")
    limit: str | None = Field(None, description="the name of the service limit the request hit (no unit)")
    errors: list[FieldError] = Field(default_factory=list, description="one entry per bad field found")
    send_to: str | None = Field(
        None,
        description="where the request is answered instead (a path of this API), for a batch entry refused because it "
        "needs a simulation (type /problems/needs-simulation)",
    )


class BatchSolveRequest(BaseModel):
    """Many solves in one call; each is answered or refused on its own."""

    model_config = ConfigDict(extra="forbid", strict=True)

    requests: list[dict[str, Any]] = Field(
        min_length=1,
        max_length=1000,
        description="solve requests, each a SolveRequest object, answered where the shipped tables or the Roman default's "
        "field grid hold it (the same answer as POST /solve); one that needs a simulation is refused in its own entry "
        "(type /problems/needs-simulation, send_to POST /solve)",
    )


class BatchItem(BaseModel):
    index: int = Field(description="position of the request in the batch (0-based, no unit)")
    ok: bool = Field(description="true when the request was answered")
    solution: SolveResponse | None = Field(None, description="the answer, as POST /solve gives it")
    error: Problem | None = Field(None, description="why this request was refused")


class BatchSolveResponse(BaseModel):
    results: list[BatchItem] = Field(description="one entry per request, in the order given")
    answered: int = Field(description="number of requests answered (count)")
    failed: int = Field(description="number of requests refused (count)")


class ImpactRequest(BaseModel):
    """What each scene effect changes in the slopes at one point (``nlpsf impact``)."""

    model_config = ConfigDict(
        **_STRICT, json_schema_extra={"examples": [{"band": "H158", "sca": 18, "magnitude": 18.3, "scene": {"preset": "roman"}}]}
    )

    band: Band = Field(defaults.BAND, description=f"Roman band (no unit): {', '.join(roman.BANDS)}")
    sca: _Int((1, roman.N_SCA)) = Field(defaults.SCA, description=f"detector (SCA number, no unit) 1-{roman.N_SCA}")
    magnitude: float = _within(defaults.MAGNITUDE_RANGE, "magnitude of the star in AB mag", defaults.MAGNITUDE)
    metric: Metric = Field("size", description="the request's metric (no unit)")
    mode: Mode = Field("bias", description="bias or scatter slopes (no unit)")
    beta0: float = _within(defaults.BETA0_RANGE, "beta0 in 1/e- (paper convention)", defaults.BETA0)
    exptime: float = _within(defaults.EXPTIME_RANGE_S, "exposure time in s", defaults.EXPTIME_S)
    realizations: _Int((2, 10_000)) = _within(
        (2, 10_000), "number of centroid realizations per run (count; both runs of an effect share them)", 50, in_type=True
    )
    seed: _Int(JSON_SEEDS) = _within(JSON_SEEDS, "random seed (integer, no unit)", 1, in_type=True)
    scene: SceneRequest | None = Field(None, description="the scene; effects it leaves off are measured at nominal values")
    pupil_scale: PupilScale | None = Field(
        None, description="pupil mask scale rule of every run (no unit): null for the simulation's default (galsim)"
    )


class ImpactEffect(BaseModel):
    model_config = ConfigDict(extra="allow")

    name: str = desc("the scene effect (no unit)")
    on: bool = desc("whether the request's scene has the effect on")
    impact: dict[str, float | None] = desc("relative change of the slope per metric (dimensionless; 0.05 = +5 %)")
    uncertainty: dict[str, float | None] = desc("1-sigma uncertainty of each relative change (dimensionless)")
    cost_s: float | None = desc("time of the run with the effect, in s")
    value: Any = desc("the effect's value as measured, in the unit of its scene field", None)
    note: str | None = desc("how the effect was measured (text)", None)


class ImpactReport(BaseModel):
    model_config = ConfigDict(extra="allow")

    effects: list[ImpactEffect] = desc("one entry per scene effect")
    conditions: dict[str, Any] = desc("conditions: band, SCA, magnitude (AB mag), beta0 (1/e-), exposure (s), scene, slopes (e-)")


class SimulationRequest(RampFields):
    """A fresh simulation on the grid magnitudes x betas x sigma_betas (paper's defaults)."""

    model_config = ConfigDict(
        **_STRICT,
        json_schema_extra={"examples": [{"band": "H158", "magnitudes": [18.3, 20.0], "betas": [5e-7], "realizations": 20}]},
    )

    band: Band = Field(defaults.BAND, description=f"Roman band (no unit): {', '.join(roman.BANDS)}")
    sca: _Int((1, roman.N_SCA)) = Field(defaults.SCA, description=f"detector (SCA number, no unit) 1-{roman.N_SCA}")
    magnitudes: list[_Number(defaults.MAGNITUDE_RANGE)] = Field(
        [18.3], min_length=1, max_length=10_000, description="star magnitudes in AB mag in the band"
    )
    betas: list[_Number((-defaults.MAX_ABS_BETA, defaults.MAX_ABS_BETA))] = Field(
        [defaults.BETA0], min_length=1, max_length=10_000, description="NL coefficients beta in 1/e-"
    )
    sigma_betas: list[_Number((0.0, defaults.MAX_ABS_BETA))] = Field(
        [0.0],
        min_length=1,
        max_length=10_000,
        description="per-pixel beta scatter sigma_beta in 1/e-; > 0 draws beta maps at a fixed centroid",
    )
    beta_convention: BetaConvention = Field(
        "paper", description="sign convention (no unit); paper: S = Q - beta Q^2; galsim: S = Q + beta Q^2"
    )
    exptime: float | None = _within(
        defaults.EXPTIME_RANGE_S,
        "exposure time in s; null: the scene's readout's (the Roman default's HLWAS table's last read, "
        "139.149 s; the paper's 168.1 s final frame; an MA table's last read)",
    )
    full_well: float = _within(defaults.FULL_WELL_RANGE_E, "full-well depth in e-", defaults.FULL_WELL_E)
    fidelity: SimulationFidelity = Field(
        "monte_carlo", description="(no unit) linear response, Monte Carlo, or Monte Carlo polychromatic"
    )
    n_wavelengths: _Int((1, defaults.MAX_WAVELENGTHS)) | None = _within(
        (1, defaults.MAX_WAVELENGTHS), "number of wavelengths of the polychromatic PSF (count, default 8)", in_type=True
    )
    realizations: _Int((1, defaults.MAX_REALIZATIONS)) = _within(
        (1, defaults.MAX_REALIZATIONS),
        "number of centroid realizations, or beta-map draws when sigma_beta > 0 (count)",
        100,
        in_type=True,
    )
    seed: _Int(JSON_SEEDS) = _within(
        JSON_SEEDS, "random seed (integer, no unit); the same seed gives the same numbers", 1, in_type=True
    )
    oversampling: _Int(defaults.OVERSAMPLING_RANGE) = _within(
        defaults.OVERSAMPLING_RANGE, "fine pixels per native pixel along a side, N (count)", 3, in_type=True
    )
    stamp: _Int(defaults.STAMP_RANGE) = _within(defaults.STAMP_RANGE, "stamp side in fine pixels (count)", 96, in_type=True)
    weight_cut_rho2: float = _within(
        defaults.WEIGHT_CUT_RHO2_RANGE,
        "adaptive-moment weight cut rho^2, dimensionless (paper 25, GalSim 32.24)",
        defaults.PAPER_WEIGHT_CUT_RHO2,
    )
    pupil_scale: PupilScale | None = Field(
        None, description="pupil mask scale rule (no unit); null: the scene's (roman: official; paper: galsim)"
    )
    # A preset's name is its fields' shorthand: {"preset": name}, so errors keep naming scene.FIELD.
    scene: Annotated[SceneRequest | None, BeforeValidator(_preset_object)] = Field(
        None,
        description="what the star goes through: a preset's name or its fields (units per field); default the Roman "
        "default, as the CLI's simulate (nlpsf.request.presets: its scene at the position, its sky, the HLWAS readout "
        "with the likelihood fit and its exposure unless a ramp, MA table or exptime is given, official pupil scale); "
        "'paper': the paper's idealised scene on its 168.1 s final frame",
    )
    throughput: Throughput = Field(
        defaults.THROUGHPUT,
        description="effective-area data (no unit): roman-2024 (official, per SCA) or galsim-2021 (GalSim's, paper comparison)",
    )


JobState = Literal["queued", "running", "done", "failed", "cancelled", "interrupted"]


class Job(BaseModel):
    """A simulation job; ``result`` is filled once ``status`` is done."""

    id: str = desc("the job's id, its capability (hex token)")
    status: JobState = desc("queued, running, done, failed, cancelled or interrupted (no unit)")
    progress: float = desc("fraction done, dimensionless 0 to 1")
    message: str = desc("what the job is doing (text)")
    cached: bool = desc("answered from stored results of an identical earlier request")
    cancel_requested: bool = desc("a cancel was asked for")
    queue_position: int | None = desc("place in the queue (count; null when not queued)")
    request: dict[str, Any] = desc("the normalised request, in the units of SimulationRequest")
    request_hash: str = desc("hash of the normalised request (hex)")
    created_at: float = desc("Unix time in s")
    started_at: float | None = desc("Unix time in s")
    finished_at: float | None = desc("Unix time in s")
    updated_at: float = desc("Unix time in s")
    error: dict[str, Any] | None = desc("why the job failed: field and message (text)")
    result: dict[str, Any] | None = desc(
        "the result: metrics (dimensionless), fluxes in e-, magnitudes in AB mag, with conditions"
    )


class JobList(BaseModel):
    jobs: list[Job] = desc("the caller's recent jobs, without results")
    counts: dict[str, int] = desc("number of jobs per status (count)")
