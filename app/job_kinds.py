"""The kinds of job, one registry: what each kind is, how it is validated (in the web process,
before anything is queued), how it runs (in the job process) and how long it is expected to take.

- ``simulation``: a fresh simulation on a grid of magnitudes x betas x sigma_betas (POST /simulations);
- ``solve``: a two-of-three solve that needs simulated slopes (POST /solve);
- ``impact``: an impact report, every scene effect simulated with and without (POST /impact);
- ``kernel``, ``residual``, ``requirement``: the calibration capability (POST /calibration/*,
  ``calibration_jobs``).

A job request is a JSON object: a simulation's normalised request, or ``{"kind": K, K: arguments}``
for the others; :data:`KINDS` maps each kind to its entry. All physics is in the library; this
module maps field names, applies the service's work limits and reports progress.
"""

from __future__ import annotations

import hashlib
import json
import time
from typing import Any

from nlpsf import roman
from nlpsf._version import __version__
from nlpsf.checks import InputError
from nlpsf.request.resolve import RAMP_REQUEST_FIELDS, SolveRequest
from nlpsf.serialise import json_safe
from nlpsf.sim import detector, experiment, levels
from nlpsf.sim import scene as scenes

from . import calibration_jobs
from .job_parts import JobKind, Progress, solve_body, solve_request
from .settings import JOB_BYTES_PER_STAMP_PIXEL, Limits

#: Library argument names -> request field names, so a 422 names what the user typed.
FIELD_FOR_ARGUMENT = {
    "magnitude": "magnitudes",
    "beta": "betas",
    "sigma_beta": "sigma_betas",
    "exptime": "exptime",
    "full_well": "full_well",
    "weight_cut_rho2": "weight_cut_rho2",
    "ma_table.resultants": "ma_table",
    "ma_table.frame_time_s": "ma_table",
}

#: Request fields of an up-the-ramp exposure; absent from a final-frame request's normalised form
#: (so its hash, the result cache's key, is what it was before ramps existed).
RAMP_FIELDS = RAMP_REQUEST_FIELDS


class LimitError(InputError):
    """A request asks for more work than the service allows; ``limit`` names the setting."""

    def __init__(self, argument: str, limit: str, message: str):
        super().__init__(argument, message)
        self.limit = limit


def request_field(argument: str, request: dict[str, Any] | None = None) -> str:
    """The request field a library argument names: a simulation's own names (``magnitudes``, ...); the other
    kinds' requests use the library's names (``request``: the job request, None for a simulation's)."""
    if request is not None and request.get("kind", SIMULATION_KIND) != SIMULATION_KIND:
        return argument
    return FIELD_FOR_ARGUMENT.get(argument, argument)


def build_scene(fields: dict[str, Any] | None, sky_of: tuple | None = None) -> scenes.SceneModel:
    """The library's scene for a request's ``scene`` object (``SolveRequest``'s reading of it; errors
    name ``scene.FIELD``). ``sky_of``: (band, sca, exptime, ramp) of a simulation, whose preset's own
    sky over that exposure is then the base, so that the sky ``fill_simulation`` filled in is no
    change and the scene keeps its preset's name (a sky the client gave otherwise is one)."""
    from nlpsf.request.resolve import scene_from_json

    return scene_from_json(fields, sky_of=sky_of)


def request_arguments(request: SolveRequest) -> dict[str, Any]:
    """``request``'s fields as keyword arguments (for ``solver.solve_over_field``, which takes them)."""
    from dataclasses import fields

    return {f.name: getattr(request, f.name) for f in fields(request) if f.init}


def build_config(request: dict[str, Any]) -> experiment.SimulationConfig:
    """The library's configuration for a (pydantic-validated) request; raises InputError."""
    from .models import build_ramp

    level = levels.simulation_settings(request["fidelity"], request.get("n_wavelengths"))
    ramp, exptime = build_ramp(
        request.get("ramp"),
        request.get("ma_table"),
        request.get("ramp_fit") or "ols",
        request.get("read_noise"),
        request.get("exptime"),
        request["sca"],
    )
    # SimulationConfig refuses a scene beyond first order (scene.check_first_order).
    scene = build_scene(request.get("scene"), (request["band"], request["sca"], exptime, ramp))
    return experiment.SimulationConfig(
        band=request["band"],
        sca=request["sca"],
        realizations=request["realizations"],
        seed=request["seed"],
        oversampling=request["oversampling"],
        stamp=request["stamp"],
        exptime_s=exptime,
        full_well_e=request["full_well"],
        n_wavelengths=level.n_wavelengths,
        weight_cut_rho2=request["weight_cut_rho2"],
        pupil_scale=request["pupil_scale"],
        method=level.method,
        scene=scene,
        throughput=request.get("throughput", roman.DEFAULT_THROUGHPUT),
        ramp=ramp,
    )


#: Request fields whose default a deployment's limit may lower: (field, limit). An omitted field
#: means "the default, or the limit if that is smaller" (the schema publishes the same), so a
#: request the schema allows is never refused for a value the client did not send.
CAPPED_DEFAULTS = (("realizations", "max_realizations"), ("stamp", "max_stamp"))


def capped_defaults(payload: dict[str, Any], given: set[str], limits: Limits) -> dict[str, Any]:
    """``payload`` with each omitted capped field at min(default, limit); a polychromatic level's
    default wavelength count likewise."""
    out = dict(payload)
    for name, limit in CAPPED_DEFAULTS:
        if name not in given and name in out:
            out[name] = min(out[name], getattr(limits, limit))
    if out.get("fidelity") == "polychromatic" and out.get("n_wavelengths") is None:
        default = levels.simulation_settings("polychromatic").n_wavelengths
        out["n_wavelengths"] = min(default, limits.max_wavelengths) if default > limits.max_wavelengths else None
    return out


def work_of(config: experiment.SimulationConfig, cells: int) -> int:
    return config.realizations * config.stamp**2 * (config.optics.n_wavelengths + cells)


def validate(request: dict[str, Any], limits: Limits, memory_mb: int | None = None) -> dict[str, Any]:
    """Check a request against the library and the service's limits.

    Returns the normalised request (band upper-cased, values as the library will use them), whose
    hash identifies the result. Raises InputError (or LimitError) naming the field.
    """
    # The service's caps first, so that a request over them names the limit a user can ask about.
    counts = [
        ("realizations", "max_realizations", request["realizations"], limits.max_realizations, "realizations"),
        ("stamp", "max_stamp", request["stamp"], limits.max_stamp, "stamp side (fine pixels)"),
        ("n_wavelengths", "max_wavelengths", request.get("n_wavelengths") or 1, limits.max_wavelengths, "wavelengths"),
        (
            "magnitudes",
            "max_grid",
            len(request["magnitudes"]) * len(request["betas"]) * len(request["sigma_betas"]),
            limits.max_grid,
            "grid cells (magnitudes x betas x sigma_betas)",
        ),
    ]
    _check_limits(counts)
    config = build_config(request)
    magnitudes = experiment.check_magnitudes(request["magnitudes"])
    betas = [float(b) for b in request["betas"]]
    for beta in betas:
        detector.to_paper_beta(beta, request["beta_convention"])
    if not betas:
        raise InputError("betas", "give at least one value")
    sigma_betas = [experiment.check_sigma_beta(s) for s in request["sigma_betas"]]
    if not sigma_betas:
        raise InputError("sigma_betas", "give at least one value (0 for no per-pixel scatter)")
    cells = len(magnitudes) * len(betas) * len(sigma_betas)
    _check_limits(
        [
            ("n_wavelengths", "max_wavelengths", config.optics.n_wavelengths, limits.max_wavelengths, "wavelengths"),
            (
                "realizations",
                "max_stamp_pixels",
                config.realizations * config.stamp**2,
                limits.max_stamp_pixels,
                "stamp pixels held in memory (realizations x stamp^2)",
            ),
            (
                "realizations",
                "max_work",
                work_of(config, cells),
                limits.max_work,
                "work units (realizations x stamp^2 x (wavelengths + grid cells))",
            ),
        ]
    )
    if memory_mb is not None:
        need = config.realizations * config.stamp**2 * JOB_BYTES_PER_STAMP_PIXEL
        if need > memory_mb * 1024**2:
            raise LimitError(
                "realizations",
                "job_memory_mb",
                f"needs about {need / 1024**2:,.0f} MB ({JOB_BYTES_PER_STAMP_PIXEL} bytes per stamp pixel, measured); "
                f"the limit job_memory_mb is {memory_mb:,} MB",
            )
    normalised = dict(request)
    if config.ramp is None:
        for name in RAMP_FIELDS:
            normalised.pop(name, None)
    normalised.update(
        exptime=config.exptime_s,
        band=config.band,
        n_wavelengths=config.n_wavelengths,
        magnitudes=magnitudes,
        betas=betas,
        sigma_betas=sigma_betas,
    )
    if normalised.get("scene") is None:
        normalised.pop("scene", None)  # the paper's scene: same hash as before scenes existed
    return normalised


def _check_limits(checks: list[tuple[str, str, int, int, str]]) -> None:
    for field, limit, value, cap, what in checks:
        if value > cap:
            raise LimitError(field, limit, f"asks for {value:,} {what}; the limit {limit} is {cap:,}")


def request_hash(normalised: dict[str, Any]) -> str:
    """Content hash of what determines the result: the request, the code and the optical data."""
    key = {"request": normalised, "code_version": __version__, "data_version": roman.DATA_VERSION}
    return hashlib.sha256(json.dumps(key, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def estimate_seconds(normalised: dict[str, Any]) -> float:
    """Rough duration on one core, for the page's expectations only (not a promise)."""
    config = build_config(normalised)
    cells = len(normalised["magnitudes"]) * len(normalised["betas"]) * len(normalised["sigma_betas"])
    return 1e-7 * work_of(config, cells)


#: A job that is a solve at a simulating fidelity (POST /solve), not a simulation grid.
SOLVE_KIND = "solve"
#: A job that is an impact report (POST /impact): every effect simulated with and without.
IMPACT_KIND = "impact"
#: A simulation grid (POST /simulations): its request is the normalised request itself, without "kind".
SIMULATION_KIND = "simulation"


def solve_job(arguments: dict[str, Any]) -> dict[str, Any]:
    """The job request of a solve that needs a simulation: ``{"request": JSON fields, "over_field": ...}``."""
    return {"kind": SOLVE_KIND, "solve": arguments}


def impact_job(arguments: dict[str, Any]) -> dict[str, Any]:
    """The job request of an impact report (``arguments`` as ``impact.impact`` takes them, the
    scene as the request's JSON ``scene`` object)."""
    return {"kind": IMPACT_KIND, "impact": arguments}


def _steps(progress: Progress | None):
    return None if progress is None else (lambda done, total, message: progress(done / max(total, 1), message))


def _run_impact(arguments: dict[str, Any], progress: Progress | None) -> dict[str, Any]:
    from nlpsf.solve import impact

    arguments = dict(arguments)
    scene = build_scene(arguments.pop("scene"))
    return json_safe(impact.impact(scene=scene, progress=_steps(progress), **arguments))


def _run_solve(arguments: dict[str, Any], progress: Progress | None) -> dict[str, Any]:
    from nlpsf.solve import solver

    if progress:
        progress(0.0, "simulating the slopes this solve needs")
    request = solve_request(arguments["request"])
    over_field = arguments.get("over_field")
    if over_field is not None:
        rest = request_arguments(request)
        band, sca = rest.pop("band"), rest.pop("sca")
        scas = "all" if over_field == "focal_plane" else [sca]
        # The request was filled for its own SCA (the default's sky, read noise): the others get theirs.
        solution = solver.solve_over_field(band, scas, progress=_steps(progress), filled_for=sca, **rest).to_dict()
    else:
        # The SCA range's nodes are its steps (the Roman default without a position); else one step.
        solution = solver.answer(request, progress=_steps(progress)).to_dict()
    if progress:
        progress(1.0, "done")
    return json_safe(solution)


def _run_simulation(normalised: dict[str, Any], progress: Progress | None) -> dict[str, Any]:
    start = time.perf_counter()
    config = build_config(normalised)
    magnitudes, betas, sigma_betas = normalised["magnitudes"], normalised["betas"], normalised["sigma_betas"]
    pairs = len(magnitudes) * len(betas)
    # Rendering and fitting every centroid costs about as much as half the (magnitude, beta) cells.
    prepare_weight = max(3.0, 0.5 * pairs * len(sigma_betas))
    total = prepare_weight + pairs * len(sigma_betas)

    def prepare_stage():
        if progress is None:
            return None
        return lambda done, steps, message: progress(min(prepare_weight * done / steps / total, 1.0), message)

    def stage(offset: float):
        if progress is None:
            return None
        return lambda done, _steps, message: progress(min((offset + done) / total, 1.0), message)

    scene = experiment.prepare(config, progress=prepare_stage())
    results = []
    for index, sigma_beta in enumerate(sigma_betas):
        results += experiment.simulate(
            config,
            magnitudes,
            betas,
            sigma_beta=sigma_beta,
            beta_convention=normalised["beta_convention"],
            scene=scene,
            progress=stage(prepare_weight + index * pairs),
        )
    if progress:
        progress(1.0, "done")
    rows = [json_safe(_result_row(r)) for r in results]
    return {
        "source": f"fresh simulation ({config.fidelity}, {config.realizations} realizations, seed {config.seed})",
        "fidelity": normalised["fidelity"],
        "conditions": json_safe(config.conditions()),
        "grid": {"magnitudes": magnitudes, "betas": betas, "sigma_betas": sigma_betas, "order": "sigma_beta, magnitude, beta"},
        "results": rows,
        "elapsed_s": time.perf_counter() - start,
    }


#: The metrics of a simulation result row, each with mean, std, stderr (and std_error, added here).
RESULT_METRICS = ("dR_over_R", "de1", "de2")


def _result_row(result) -> dict[str, Any]:
    """A simulation result as JSON, each metric with ``std_error``, the standard error of its
    ``std`` (``Statistic.std_error``): the error bar of a scatter (sigma_beta > 0) point."""
    row = result.to_dict()
    for name in RESULT_METRICS:
        row[name] = {**row[name], "std_error": getattr(result, name).std_error}
    return row


def _validate_simulation(fields: dict[str, Any], given: set[str], settings: Any) -> dict[str, Any]:
    from nlpsf.request import presets

    from .models import build_ramp

    payload = presets.fill_simulation(capped_defaults(fields, given, settings.limits), given, build_ramp)
    return validate(payload, settings.limits, settings.job_memory_mb)


def _validate_solve(fields: dict[str, Any], given: set[str], settings: Any) -> dict[str, Any]:
    """A solve that needs simulated slopes: everything checked at table cost (the library's request,
    the table solve of the same question, the fidelity choice), then the job's arguments: the
    request's JSON fields, which the job process reads into the same typed request."""
    from nlpsf.solve import solver

    body = solve_body(fields, given)
    request = solve_request(body)
    checked = solver.answer(request.table_pass())
    solver.choose_fidelity(request.fidelity, request.accuracy, checked.band, checked.metric, checked.mode)
    return solve_job({"request": {**body, "band": request.band}, "over_field": fields["over_field"]})


def _validate_impact(fields: dict[str, Any], given: set[str], settings: Any) -> dict[str, Any]:
    from nlpsf import defaults
    from nlpsf.solve import impact as impact_module

    limits = settings.limits
    arguments = dict(fields)
    if "realizations" not in given:
        arguments["realizations"] = max(2, min(arguments["realizations"], limits.max_realizations))
    if arguments["realizations"] > limits.max_realizations:
        raise LimitError(
            "realizations",
            "max_realizations",
            f"asks for {arguments['realizations']:,} realizations; the limit max_realizations is {limits.max_realizations:,}",
        )
    scene_request = arguments.pop("scene")
    scene = build_scene(scene_request)
    scenes.check_first_order(scene, defaults.FULL_WELL_E)  # the impact report simulates at the default full well
    wavelengths = scene.wavelengths(roman.check_band(arguments["band"]))
    if wavelengths > limits.max_wavelengths:
        raise LimitError(
            "scene",
            "max_wavelengths",
            f"the scene's SED needs {wavelengths} wavelengths; the limit max_wavelengths is {limits.max_wavelengths}",
        )
    rule = arguments.pop("pupil_scale", None)
    checked = impact_module.check_request(**arguments)
    # The rule enters the job only when given, so a request without one keeps its stored hash.
    extra = {} if rule is None else {"pupil_scale": rule}
    return impact_job({**checked, "scene": scene_request, "max_wavelengths": limits.max_wavelengths, **extra})


#: Every kind of job. A new kind is one entry here and the endpoint that submits it.
KINDS: dict[str, JobKind] = {
    SIMULATION_KIND: JobKind(SIMULATION_KIND, _validate_simulation, _run_simulation, estimate_seconds),
    SOLVE_KIND: JobKind(SOLVE_KIND, _validate_solve, _run_solve, lambda _arguments: None),
    IMPACT_KIND: JobKind(IMPACT_KIND, _validate_impact, _run_impact, lambda _arguments: None),
}


#: The calibration capability's kinds (kernel, residual, requirement).
KINDS.update(calibration_jobs.kinds())


def _entry(request: dict[str, Any]) -> tuple[JobKind, dict[str, Any]]:
    """The kind of a job request and its arguments."""
    name = request.get("kind", SIMULATION_KIND)
    kind = KINDS[name]
    return kind, (request if name == SIMULATION_KIND else request[name])


def run(request: dict[str, Any], progress: Progress | None = None) -> dict[str, Any]:
    """Run a validated job request with the library; ``progress(fraction, message)`` along the way."""
    kind, arguments = _entry(request)
    return kind.run(arguments, progress)


def estimate(request: dict[str, Any]) -> float | None:
    """A job request's expected duration on one core, s (None when not priced)."""
    kind, arguments = _entry(request)
    return kind.estimate(arguments)
