"""The two-of-three requirement calculator (paper, Eq. ``calib`` and section 4).

For a metric (size ΔR/R, e1, e2, or the modulus |Δe| = hypot(Δe1, Δe2)) and a mode (``bias``: a
calibration error Δβ = p β0 in the mean NL coefficient; ``scatter``: a per-pixel spread
σβ = p β0), the PSF error is

    T = |c(m)| p β0,

with c(m) the slope d(metric)/dβ (bias) or σ(metric)/σβ (scatter) at magnitude m, exposure t and
β0. Given any two of (precision p, tolerance T, magnitude m) the third follows. Solving for m
returns the magnitude at which the NL error reaches the tolerance, and the brightest usable star:
the fainter of that and the saturation magnitude, with which limit binds.

Shear budgets. Instead of the tolerance, a shear-bias budget may be given: ``shear_m`` (the
multiplicative bias, size metric) or ``shear_c`` (the additive bias, e metrics) with the
galaxy-to-PSF size ratio ``size_ratio`` (a number or a distribution); ``nlpsf.shear`` turns it into
the tolerance (ΔR/R = |m| ρ²/2, Δe = 2 |c| ρ², derived there). With ``size_ratio`` alone, the answer
reports the shear bias that its tolerance implies.

Averaging (scatter mode). A per-pixel β spread is fixed in the detector, but each star of a PSF
model, and each dither of it, falls on other pixels: its NL error is an independent draw as long as
no two of them share the pixels under the moment weight (a few native pixels around each centroid).
A PSF model that averages ``stars`` such images with equal weight then has the scatter
σ(metric)/√stars, and the answer holds for that model; with stars of different brightness, all taken
at the answer's (brightest) magnitude, it is an upper bound. A bias in the mean β is common to
every star, so averaging does not reduce it and ``stars`` applies to scatter mode only.

Slopes come from the shipped tables (``fidelity="table"``, microseconds) or from fresh simulations
(``linear``, ``monte_carlo``, ``polychromatic``); ``accuracy`` picks the cheapest level whose
measured error (``nlpsf tradeoff``) meets it.

Up-the-ramp exposures (``ramp``, see ``nlpsf.ramps``): the saturation rule becomes Roman's (a star
is usable until its brightest pixel saturates in the *first* resultant, 2.5 log10(T / t_1) mag
brighter than the final-frame rule), and the slopes come from the tables where the mapping is exact
(quadratic NL, OLS fit, every pixel keeping every resultant: the final frame at beta_eff = c_2 beta0,
c_2 = 1 + 1/N for N uniform reads, so c(m) = c_2 c_table(m; c_2 beta0)) and from fresh
linear-response simulations of the ramp otherwise (optimal fit, or a star bright enough that some
of its pixels drop saturated resultants). ``conditions["ramp_slopes_from"]`` says which.

Model part. Every answer says what it leaves out of a Roman scene (``model``) and adds it to its
``uncertainty`` (``uncertainty_model``): the scene effects it does not simulate, the spread over the
SCA when no position is given, and the pupil-mask scale rule. With ``accuracy`` they are measured at
the answer's point (``nlpsf.impact``) and added in quadrature; otherwise they come from a shipped
measurement (``nlpsf/data/scene_model_uncertainty.json``: each effect's worst impact on SCA 1, 9
and 18 at two magnitudes) and are added up, since a Roman star has them all at once with signs often
alike. The pupil-scale rule and ``uncertainty_optical_model`` (the official-PSF comparison) both
measure the optical model's error, so the total counts the larger of the two, not both.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace

import numpy as np

from . import __version__, defaults, ramps, roman, shear, tables
from . import fidelity as levels
from .checks import (
    InputError,
    SimulationError,
    check_beta0,
    check_choice,
    check_exptime,
    check_full_well,
    check_integer,
    check_magnitude,
    check_number,
)
from .flags import Flag, FlagCode, make
from .flags import codes as flag_codes

METRICS = defaults.METRICS
MODES = defaults.MODES
FIDELITIES = levels.LEVELS
#: Past this Δβ Q_peak the error is no longer linear in Δβ and T = c p β0 stops describing it.
LINEAR_REGIME_LIMIT = 0.05
#: Stars (and dithers) a scatter-mode PSF model may average.
MAX_STARS = 10**9
_TABLE_METRIC_NAMES = {"size": "dR_over_R", "e1": "de1", "e2": "de2"}


@dataclass(frozen=True)
class Solution:
    """The answer, with the two given values, its uncertainty and the conditions it holds for."""

    band: str
    sca: int
    metric: str
    mode: str
    beta0: float
    exptime: float
    full_well: float
    precision: float | None
    tolerance: float | None
    magnitude: float | None
    solved_for: str
    uncertainty: float | None
    uncertainty_statistical: float | None
    uncertainty_fidelity: float | None
    slope: float | None
    slope_uncertainty: float | None
    saturation_magnitude: float
    brightest_usable_magnitude: float | None
    binding_limit: str | None
    nonlinearity_magnitude: float | None
    flags: list[str]
    fidelity: str
    conditions: dict
    #: The optical model's share (Cycle-9 Zernikes against the official post-CDR PSF statistics).
    uncertainty_optical_model: float | None = None
    elapsed_s: float = field(default=0.0, compare=False)
    #: Stars (and dithers) averaged by the PSF model the scatter-mode answer holds for.
    stars: int = 1
    applies_to: str = ""
    #: The shear budget given (or, with a size ratio alone, implied): ``Budget``-like dict.
    shear: dict | None = None
    #: Scene effects the answer leaves out (name, impact on the metric's slope, relative), the SCA
    #: spread and the pupil-scale rule, and the uncertainty they add in the solved quantity's units;
    #: measured at the point with ``accuracy``, else read from the shipped measurement
    #: (``scripts/model_uncertainty.py``); None only where the answer has no uncertainty.
    uncertainty_model: float | None = None
    model: dict | None = None
    #: The single-final-frame rule's saturation magnitude (equal to ``saturation_magnitude`` without a ramp).
    final_frame_saturation_magnitude: float | None = None

    def to_dict(self) -> dict:
        return {
            "band": self.band,
            "sca": self.sca,
            "metric": self.metric,
            "mode": self.mode,
            "beta0": self.beta0,
            "exptime": self.exptime,
            "full_well": self.full_well,
            "precision": _json_number(self.precision),
            "tolerance": _json_number(self.tolerance),
            "magnitude": _json_number(self.magnitude),
            "solved_for": self.solved_for,
            "uncertainty": _json_number(self.uncertainty),
            "uncertainty_statistical": _json_number(self.uncertainty_statistical),
            "uncertainty_fidelity": _json_number(self.uncertainty_fidelity),
            "uncertainty_optical_model": _json_number(self.uncertainty_optical_model),
            "uncertainty_model": _json_number(self.uncertainty_model),
            "model": self.model,
            "slope": _json_number(self.slope),
            "slope_uncertainty": _json_number(self.slope_uncertainty),
            "saturation_magnitude": _json_number(self.saturation_magnitude),
            "final_frame_saturation_magnitude": _json_number(self.final_frame_saturation_magnitude),
            "brightest_usable_magnitude": _json_number(self.brightest_usable_magnitude),
            "binding_limit": self.binding_limit,
            "nonlinearity_magnitude": _json_number(self.nonlinearity_magnitude),
            "flags": [str(f) for f in self.flags],
            "flag_codes": flag_codes(self.flags),
            "fidelity": self.fidelity,
            "stars": self.stars,
            "applies_to": self.applies_to,
            "shear": self.shear,
            "conditions": self.conditions,
            "elapsed_s": self.elapsed_s,
        }


def _json_number(value: float | None) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)


class _Slopes:
    """c(m) at the request's conditions, from the tables or from fresh simulations."""

    def __init__(
        self,
        band: str,
        sca: int,
        metric: str,
        mode: str,
        beta0: float,
        exptime: float,
        fidelity: str,
        tableset,
        ramp: ramps.Ramp | None = None,
        full_well: float = defaults.FULL_WELL_E,
        throughput: str | None = None,
        scene=None,
        pupil_scale: str | None = None,
    ):
        self.band, self.sca, self.metric, self.mode = band, sca, metric, mode
        self.pupil_scale = pupil_scale  # of the fresh simulations (None: the tables' own)
        self.beta0, self.exptime, self.fidelity = beta0, exptime, fidelity
        self.ramp, self.full_well = ramp, full_well
        self.scene_model = scene  # nlpsf.scene.SceneModel of the simulated levels (None: the paper's)
        self.table = tableset.get(band, sca)
        #: Magnitudes the table was relabelled by for another throughput's photometry (0: none).
        self.relabel_shift = 0.0
        if throughput is not None:
            self.table, self.relabel_shift = tables.with_throughput(self.table, throughput)
        self._cache: dict[float, tuple[float, float]] = {}
        self._scene = None  # experiment.Scene of the fresh simulations, prepared once per request
        #: beta_eff / beta0 where the ramp maps exactly onto the tables (OLS), else None.
        self.ramp_factor = ramp.quadratic_factor(exptime) if ramp is not None and ramp.fit == "ols" else None
        #: How the ramp's slopes were obtained in this request ("table", "simulation").
        self.ramp_bases: set[str] = set()

    @property
    def table_beta0(self) -> float:
        """The beta0 the tables are read at: beta_eff for a ramp that maps exactly."""
        return self.beta0 * (self.ramp_factor or 1.0)

    def range(self) -> tuple[float, float]:
        return self.table.grid_range(self.exptime, self.table_beta0)

    def exact_from(self) -> float:
        """Faintest-side limit of the exact ramp mapping: brighter than this, the brightest pixel's
        last resultant passes the full well and drops out of its fit."""
        last = self.ramp.table.duration_s / self.exptime
        return self.table.saturation(self.exptime, self.full_well) - 2.5 * math.log10(1.0 / last)

    def from_table(self, magnitude: float) -> tuple[float, float, int]:
        value, error, region = self.table.slope(self.metric, self.mode, magnitude, self.exptime, self.table_beta0)
        scale = self.ramp_factor or 1.0  # d/d beta = c_2 d/d beta_eff
        return float(value[0]) * scale, float(error[0]) * scale, int(region[0])

    def at(self, magnitude: float) -> tuple[float, float, int]:
        """(slope, uncertainty, region): region -1 brighter than the grid, 0 in it, +1 fainter."""
        if self.ramp is not None:
            return self._ramp_at(magnitude)
        value, error, region = self.from_table(magnitude)
        if self.fidelity == "table" or region < 0:
            return value, error, region
        return (*self._simulated(magnitude), region)

    def _ramp_at(self, magnitude: float) -> tuple[float, float, int]:
        exact = self.fidelity == "table" and self.ramp_factor is not None and magnitude >= self.exact_from()
        if exact:
            self.ramp_bases.add("table")
            return self.from_table(magnitude)
        self.ramp_bases.add("simulation")
        hi = self.table.grid_range(self.exptime, self.beta0)[1]
        return (*self._simulated(magnitude), 1 if magnitude > hi else 0)

    def _simulated(self, magnitude: float) -> tuple[float, float]:
        key = round(magnitude, 9)
        if key not in self._cache:
            self._cache[key] = self._simulate(magnitude)
        return self._cache[key]

    def _simulate(self, magnitude: float) -> tuple[float, float]:
        from . import experiment  # the simulator: only fresh-simulation levels need it

        # A ramp that the tables do not map exactly is simulated with the linear response.
        level = levels.simulation_settings("linear" if self.fidelity == "table" else self.fidelity)
        settings = self.table.settings
        config = experiment.SimulationConfig(
            band=self.band,
            sca=self.sca,
            realizations=int(settings["realizations"]),
            seed=int(settings["seed"]),
            oversampling=int(settings["oversampling"]),
            stamp=int(settings["stamp"]),
            exptime_s=self.exptime,
            weight_cut_rho2=float(settings["weight_cut_rho2"]),
            pupil_scale=self.pupil_scale or str(settings["pupil_scale"]),
            throughput=self.table.throughput,
            method=level.method,
            n_wavelengths=level.n_wavelengths,
            **({} if self.ramp is None else {"ramp": self.ramp, "full_well_e": self.full_well}),
            **({} if self.scene_model is None else {"scene": self.scene_model}),
        )
        if self._scene is None or self._scene.config != config:
            self._scene = experiment.prepare(config)  # magnitude-independent: once per request
        result = experiment.slopes(config, [magnitude], beta0=self.beta0, scene=self._scene)[0]
        names = ("de1", "de2") if self.metric == "e" else (_TABLE_METRIC_NAMES[self.metric],)
        value, error = result.slope(self.mode, names)
        if value is None:
            raise SimulationError(f"the simulation at m={magnitude:g} failed: {'; '.join(result.flags)}")
        return value, error


def choose_fidelity(level: str | None, accuracy: float | None, band: str, metric: str, mode: str) -> tuple[str, list[str]]:
    """The fidelity level a solve uses (``accuracy`` picks the cheapest meeting it), and a note on why."""
    if accuracy is None:
        return levels.check_level(level or "table"), []
    accuracy = check_number(accuracy, "accuracy", *defaults.ACCURACY_RANGE)
    chosen, note = levels.cheapest_meeting(accuracy, band, metric, mode)
    return chosen, [note]


def solve(
    band: str,
    sca: int = 18,
    metric: str = "size",
    mode: str = "bias",
    beta0: float = defaults.BETA0,
    exptime: float = defaults.EXPTIME_S,
    precision: float | None = None,
    tolerance: float | None = None,
    magnitude: float | None = None,
    full_well: float = defaults.FULL_WELL_E,
    fidelity: str | None = None,
    accuracy: float | None = None,
    shear_m: float | None = None,
    shear_c: float | None = None,
    size_ratio: float | list | str | shear.SizeRatio | None = None,
    stars: int = 1,
    tables_set: tables.TableSet | None = None,
    ramp: ramps.Ramp | None = None,
    throughput: str | None = None,
    scene=None,
    pupil_scale: str | None = None,
) -> Solution:
    """Give exactly two of ``precision`` (Δβ/β0, or σβ/β0 in scatter mode), ``tolerance`` (the PSF
    error allowed) and ``magnitude`` (AB); get the third. See the module docstring.

    ``shear_m`` (size metric) or ``shear_c`` (e metrics), with ``size_ratio`` = R_gal/R_psf (a
    number, (ratio, weight) pairs, or a string ``nlpsf.shear.check_size_ratio`` reads), stands in
    for ``tolerance``. ``stars`` (scatter mode): the PSF model averages that many independent
    star images (σ / √stars).

    ``ramp``: an up-the-ramp exposure (``ramps.Ramp``; e.g. ``ramps.Ramp.uniform(N, exptime)``)
    instead of the paper's single final frame. ``exptime`` stays what is given: for an MA table whose
    exposure is its last read, ``ramps.build(ma_table=...)`` returns both (as the CLI and the service do).

    ``throughput`` (``defaults.THROUGHPUTS``) is the photometry that turns the magnitude into
    electrons; None is the tables' own. Another one reads the tables relabelled
    (``tables.with_throughput``), and fresh simulations use it directly.

    ``scene`` (``nlpsf.scene.SceneModel``) is what the star goes through; with ``accuracy`` the
    answer models only the effects whose measured impact at the point exceeds it (see
    :func:`_select_scene`) and its uncertainty gains a ``model`` part for those left out.

    ``pupil_scale`` (``roman.PUPIL_SCALE_RULES``) is the pupil-mask scale rule of fresh
    simulations; None is the tables' own (galsim). Another rule is not in the tables, so a table
    solve is then simulated (fidelity linear).
    """
    start = time.perf_counter()
    band = roman.check_band(band)
    sca = roman.check_sca(sca)
    tables.check_metric_mode(metric, mode)
    beta0 = check_beta0(beta0)
    exptime = check_exptime(exptime)
    full_well = check_full_well(full_well)
    stars = check_integer(stars, "stars", 1, MAX_STARS)
    if stars > 1 and mode != "scatter":
        raise InputError(
            "stars",
            "averaging over stars applies to scatter mode only: a bias in the mean beta is common to every star, "
            "so a PSF model averaging n stars has the same bias error as one",
        )
    budget, ratio = None, None
    if shear_m is not None or shear_c is not None:
        if tolerance is not None:
            raise InputError(
                "tolerance", "give the tolerance or a shear budget (shear_m / shear_c), not both: the budget sets the tolerance"
            )
        budget = shear.budget_for(metric, shear_m, shear_c, size_ratio)
        ratio = budget.size_ratio
        tolerance = check_number(
            budget.tolerance, f"shear_{budget.kind}", *defaults.TOLERANCE_RANGE
        )  # e.g. a tiny budget on tiny galaxies
    elif size_ratio is not None:
        ratio = shear.check_size_ratio(size_ratio)
    if ramp is not None:
        if not isinstance(ramp, ramps.Ramp):
            raise InputError("ramp", f"must be a ramps.Ramp, got {type(ramp).__name__}")
        ramp.check_exposure(exptime)
    given = {k: v for k, v in (("precision", precision), ("tolerance", tolerance), ("magnitude", magnitude)) if v is not None}
    if len(given) != 2:
        missing = ", ".join(k for k in ("precision", "tolerance", "magnitude") if k not in given) or "none"
        field_at_fault = "precision" if "precision" not in given else ("tolerance" if "tolerance" not in given else "magnitude")
        if budget is not None and (field_at_fault == "tolerance" or len(given) == 3):
            field_at_fault = f"shear_{budget.kind}"
        raise InputError(
            field_at_fault,
            f"give exactly two of precision, tolerance (or a shear budget), magnitude (got {len(given)}; missing: {missing})",
        )
    if precision is not None:
        precision = check_number(precision, "precision", *defaults.PRECISION_RANGE)
    if tolerance is not None:
        tolerance = check_number(tolerance, "tolerance", *defaults.TOLERANCE_RANGE)
    if magnitude is not None:
        magnitude = check_magnitude(magnitude)
    chosen, flags = choose_fidelity(fidelity, accuracy, band, metric, mode)
    if throughput is not None:
        roman.check_throughput(throughput)
    if pupil_scale is not None:
        check_choice(pupil_scale, "pupil_scale", roman.PUPIL_SCALE_RULES)
    model_info, simulated_scene = None, None
    if scene is not None and not isinstance(scene, _scene_type()):
        raise InputError("scene", "must be a scene description (nlpsf.scene.SceneModel)")
    if scene is not None and ramp is not None:
        raise InputError("scene", "a scene and a ramp cannot be combined yet; give one of them")
    if accuracy is not None:
        point = magnitude
        if point is None:
            # The effects are measured where the answer will be: a first, table-level pass finds it.
            first = solve(
                band,
                sca,
                metric,
                mode,
                beta0,
                exptime,
                precision,
                tolerance,
                None,
                full_well,
                "table",
                None,
                shear_m=shear_m,
                shear_c=shear_c,
                size_ratio=size_ratio,
                stars=stars,
                tables_set=tables_set,
                throughput=throughput,
            )
            point = first.magnitude if first.magnitude is not None else defaults.MAGNITUDE
        simulated_scene, model_info = _select_scene(scene, band, sca, float(point), metric, mode, beta0, exptime, float(accuracy))
    elif scene is not None and not scene.is_paper:
        simulated_scene = scene
    if tables_set is None and simulated_scene is not None:
        # A star at a corner field point: its own shipped table holds it.
        tables_set = _corner_tables(simulated_scene, sca)
    scene_needs_simulation = (
        simulated_scene is not None
        and not simulated_scene.is_paper
        and not _tables_hold(simulated_scene, tables_set or tables.load_tables(), band, sca)
    )
    if chosen == "table" and scene_needs_simulation:
        flags.append(make(FlagCode.SCENE_SIMULATED))
        chosen = "linear"
    table_rule = str((tables_set or tables.load_tables()).get(band, sca).settings["pupil_scale"])
    if pupil_scale is not None and pupil_scale != table_rule and chosen == "table":
        flags.append(make(FlagCode.PUPIL_SCALE_SIMULATED, table_rule=table_rule, rule=pupil_scale))
        chosen = "linear"
    if model_info is None:
        # No accuracy asked for: what the answer leaves out comes from the shipped measurement.
        model_info = _shipped_model(band, sca, metric, mode, simulated_scene, chosen)
    if simulated_scene is not None and simulated_scene.breaks_beta_q_scaling():
        breaking = simulated_scene.breaks_beta_q_scaling()
        verb = "adds" if len(breaking) == 1 else "add"
        flags.append(make(FlagCode.BETA_Q_RULE_BROKEN, effects=", ".join(breaking), verb=verb, names=list(breaking)))
    slopes = _Slopes(
        band,
        sca,
        metric,
        mode,
        beta0,
        exptime,
        chosen,
        tables_set or tables.load_tables(),
        ramp,
        full_well,
        throughput=throughput,
        scene=simulated_scene,
        pupil_scale=pupil_scale,
    )
    table = slopes.table
    if "relabelled_from" in table.settings:
        size_error, e_error = tables.RELABEL_ERROR[band]
        flags.append(
            make(
                FlagCode.THROUGHPUT_RELABELLED,
                source=table.settings["relabelled_from"],
                throughput=throughput,
                shift=-slopes.relabel_shift,
                percent=100 * (size_error if metric == "size" else e_error),
            )
        )
    background = 0.0 if simulated_scene is None else simulated_scene.background_e
    if background >= full_well:
        raise InputError("background", f"a background of {background:g} e- fills the full well ({full_well:g} e-) by itself")
    # A background fills part of the well: the star saturates where its peak reaches the rest.
    m_sat_final_frame = table.saturation(exptime, full_well - background)
    # The rule in use: with a ramp a star is usable until its brightest pixel saturates in the
    # first resultant, 2.5 log10(T / t_1) brighter than the single final frame's limit.
    m_sat = m_sat_final_frame if ramp is None else m_sat_final_frame - ramp.saturation_shift_mag(exptime)
    solved_for = next(k for k in ("precision", "tolerance", "magnitude") if k not in given)
    brightest, binding, m_nl = None, None, None

    # The PSF model averages `stars` independent draws of the per-pixel beta map (scatter mode).
    averaging = 1.0 / math.sqrt(stars)
    systematic, systematic_note = _fidelity_error(chosen, band, metric, mode)
    if systematic_note:
        flags.append(systematic_note)
    if solved_for == "magnitude":
        solve_for_m = _solve_magnitude if ramp is None else _solve_magnitude_ramp
        m_nl, slope, slope_err, log_derivative, extra = solve_for_m(slopes, precision * beta0 * averaging, tolerance, m_sat)
        flags += extra
        magnitude, binding = _binding(m_nl, m_sat, flags)
        if ramp is not None and magnitude < m_sat_final_frame:
            flags.append(_between_limits_flag(magnitude, m_sat, m_sat_final_frame))
        brightest = magnitude
        if binding == "nonlinearity" and log_derivative:
            statistical = (slope_err / abs(slope)) / abs(log_derivative)
            fidelity_part = None if systematic is None else systematic / abs(log_derivative)
            model_part = _optical_model_relative(slopes, m_nl) / abs(log_derivative)
            model_info = _model_at(model_info, slopes, m_nl)
            effects_part, pupil_part = (model_info[k] / abs(log_derivative) for k in _MODEL_PARTS)
        else:
            # Saturation sets the answer: it does not depend on the slope. Report the NL error there.
            statistical, fidelity_part, model_part, effects_part, pupil_part = 0.0, 0.0, 0.0, 0.0, 0.0
            model_info = _model_at(model_info, slopes, m_sat)
            slope, slope_err, _ = slopes.at(m_sat)
            error = abs(slope) * precision * beta0 * averaging
            flags.append(make(FlagCode.ERROR_AT_SATURATION, metric=metric, mode=mode, error=error, tolerance=tolerance))
    else:
        if ramp is not None:
            flags += _ramp_magnitude_flags(magnitude, m_sat, m_sat_final_frame)  # refuses before simulating
        slope, slope_err, region = slopes.at(magnitude)
        if ramp is None:
            flags += _magnitude_flags(slopes, magnitude, region, m_sat, beta0)
        c, c_err = abs(slope) * averaging, slope_err * averaging
        model = _optical_model_relative(slopes, magnitude) if region >= 0 else None
        model_info = _model_at(model_info, slopes, magnitude) if region >= 0 else None
        effects, pupil = (None, None) if model_info is None else (model_info[k] for k in _MODEL_PARTS)
        if solved_for == "tolerance":
            tolerance = c * precision * beta0
            statistical = c_err * precision * beta0
            fidelity_part = None if systematic is None else tolerance * systematic
            model_part = None if model is None else tolerance * model
            effects_part, pupil_part = (None, None) if effects is None else (tolerance * effects, tolerance * pupil)
        elif c <= max(c_err, 1e-300):
            flags.append(make(FlagCode.SLOPE_CONSISTENT_WITH_ZERO, metric=metric, magnitude=magnitude, slope=slope, error=c_err))
            precision, statistical, fidelity_part, model_part, effects_part, pupil_part = math.inf, None, None, None, None, None
        else:
            precision = tolerance / (c * beta0)
            statistical = precision * c_err / c
            fidelity_part = None if systematic is None else precision * systematic
            model_part = None if model is None else precision * model
            effects_part, pupil_part = (None, None) if effects is None else (precision * effects, precision * pupil)
    # The official-PSF comparison (optical_model) and the pupil-scale rule both measure how far the
    # optical model may be from Roman's: the larger of the two counts, not both (no double counting).
    optical = max(model_part or 0.0, pupil_part or 0.0)
    uncertainty = None if statistical is None else math.hypot(statistical, fidelity_part or 0.0, effects_part or 0.0, optical)
    scene_part = None if effects_part is None else math.hypot(effects_part, pupil_part or 0.0)
    flags += _validity_flags(slopes, magnitude, precision, beta0, full_well)
    conditions = tables._conditions(table, exptime, beta0, full_well)
    relation = "T = |c(m)| * precision * beta0" + (" / sqrt(stars)" if mode == "scatter" else "")
    applies_to = _applies_to(mode, stars)
    conditions.update(fidelity=chosen, code_version=__version__, relation=relation, stars=stars, applies_to=applies_to)
    if ramp is None:
        conditions["saturation_rule"] = "final frame: the brightest pixel's charge at the end of the exposure hits the full well"
    else:
        conditions["saturation_rule"] = (
            "ramp: the brightest pixel's first resultant reaches the full well (later saturated resultants are dropped)"
        )
        conditions["ramp"] = ramp.conditions(exptime)
        # Fainter than this the tables answer exactly at beta_eff (OLS); brighter, pixels drop resultants.
        conditions["ramp_table_exact_from_magnitude"] = slopes.exact_from() if slopes.ramp_factor is not None else None
        conditions["ramp_slopes_from"] = _ramp_basis(slopes)
    shear_answer = None
    if ratio is not None and tolerance is not None and math.isfinite(tolerance):
        shear_answer = _shear_answer(metric, budget, ratio, tolerance, statistical if solved_for == "tolerance" else None)
        if metric != "size":
            flags.append(make(FlagCode.SHEAR_CROSS_TERM))
    if slopes.pupil_scale is not None and chosen != "table":
        conditions["pupil_scale"] = slopes.pupil_scale
    if chosen != "table":
        conditions["realizations"] = int(table.settings["realizations"])
        # What the optics evaluated (a scene's SED integrates the band even at linear fidelity).
        simulated = slopes._scene  # the prepared simulation, None where none ran
        conditions["n_wavelengths"] = (
            int(simulated.psf.wavelengths_nm.size) if simulated is not None else levels.simulation_settings(chosen).n_wavelengths
        )
    if simulated_scene is not None:
        conditions["scene"] = simulated_scene.to_dict()
        conditions["scene_description"] = simulated_scene.describe()
    return Solution(
        band=band,
        sca=sca,
        metric=metric,
        mode=mode,
        beta0=beta0,
        exptime=exptime,
        full_well=full_well,
        precision=precision,
        tolerance=tolerance,
        magnitude=magnitude,
        solved_for=solved_for,
        uncertainty=uncertainty,
        uncertainty_statistical=statistical,
        uncertainty_fidelity=fidelity_part,
        uncertainty_optical_model=model_part,
        slope=slope,
        slope_uncertainty=slope_err,
        saturation_magnitude=m_sat,
        final_frame_saturation_magnitude=m_sat_final_frame,
        brightest_usable_magnitude=brightest,
        binding_limit=binding,
        nonlinearity_magnitude=m_nl,
        flags=flags,
        fidelity=chosen,
        conditions=conditions,
        elapsed_s=time.perf_counter() - start,
        stars=stars,
        applies_to=applies_to,
        shear=shear_answer,
        uncertainty_model=scene_part,
        model=model_info,
    )


def _scene_type():
    from .scene import SceneModel

    return SceneModel


def _select_scene(scene, band, sca, magnitude, metric, mode, beta0, exptime, accuracy):
    """Model only what the scene requires: (scene to simulate, the model part's report).

    The impact of every effect is measured at the point (``nlpsf.impact``, linear response). An
    effect is simulated when |impact| on the request's metric exceeds ``accuracy`` -- at the scene's
    value, or at its nominal Roman value when the scene leaves it off (no scene: a Roman star). The
    others are left out and their impacts added in quadrature to the answer's relative model
    uncertainty, together with two model choices the answer cannot make for the user: where on
    the SCA the star is when no position is given (centre vs corner) and the pupil-mask scale rule
    (``galsim`` vs ``header``, measured here).
    """

    from . import experiment, impact
    from . import scene as scenes

    scene = scene if scene is not None else scenes.SceneModel()
    report = impact.impact(band, sca, magnitude, scene=scene, metric=metric, mode=mode, beta0=beta0, exptime=exptime)
    include, leave = impact.left_out(report, accuracy)
    simulated = scenes.SceneModel()
    names = []
    for effect in include:
        name = effect["name"]
        if name == "position" and not scene.effects_on()["position"]:
            leave.append(effect)  # no position given: the spread over the SCA is uncertainty, not a guess
            continue
        source = scene if scene.effects_on()[name] else scene.with_nominal(name)
        simulated = _with_effect(simulated, source, name)
        if name == "sed" and simulated.n_wavelengths is None:
            # Integrate the band finely enough for the accuracy asked for (scene.binning_error).
            n, _ = scenes.choose_wavelengths(band, simulated.spectrum(), accuracy)
            simulated = replace(simulated, n_wavelengths=n)
        names.append(name)
    parts = []
    for effect in leave:
        value = effect["impact"][metric]
        parts.append(
            {
                "name": effect["name"],
                "impact": value,
                "why": (
                    "spread over the SCA: no position given (centre vs corner)"
                    if effect["name"] == "position" and not effect["on"]
                    else ("below the accuracy" if value is not None else effect["note"])
                ),
            }
        )
    # The pupil-mask scale rule (nlpsf/data/SOURCES.md): the same point with the other rule.
    runs = {}
    for rule in ("galsim", "header"):
        config = experiment.SimulationConfig(
            band=band, sca=sca, realizations=50, exptime_s=exptime, method="linear", pupil_scale=rule, scene=simulated
        )
        runs[rule] = impact._slope_values(experiment.slopes(config, [magnitude], beta0=beta0)[0], mode)[metric][0]
    pupil = None if not runs["galsim"] or runs["header"] is None else runs["header"] / runs["galsim"] - 1
    parts.append({"name": "pupil_scale", "impact": pupil, "why": "pupil-mask scale rule: galsim (used) vs header"})
    info = {
        "accuracy": accuracy,
        "magnitude_measured_at": magnitude,
        "included": [{"name": e["name"], "impact": e["impact"][metric]} for e in include if e["name"] in names],
        "left_out": parts,
        "stated_against": "slope",
        "combine": "quadrature",
        "basis": "impact of each effect on the slope at this point (nlpsf impact, linear response), added in quadrature",
    }
    return simulated, info


#: The model part's two relative pieces (see :func:`_model_at`).
_MODEL_PARTS = ("effects_relative", "pupil_scale_relative")
_COMBINATION = (
    "uncertainty_model = hypot(effects left out, pupil-scale rule); the total adds the effects left out in "
    "quadrature with the statistical and fidelity parts and with the larger of the pupil-scale rule and "
    "uncertainty_optical_model, which both measure the optical model's distance from Roman's (not both)"
)
#: How the effects left out add up: measured at the point (each below the accuracy asked for) in
#: quadrature; from the shipped worst cases as a plain sum, because every Roman star has them all at
#: once with signs fixed by the optics, often alike (scripts/model_uncertainty.py).
_COMBINE = {"quadrature": lambda values: math.sqrt(math.fsum(v * v for v in values)), "sum": math.fsum}


def _shipped_model(band: str, sca: int, metric: str, mode: str, scene, fidelity: str) -> dict:
    """The model part of an answer without ``accuracy``: what it leaves out, from the shipped
    measurement (``scene.shipped_model_uncertainty``). Effects the scene (or the polychromatic
    level's flat-f_nu band integration) simulates are not left out; the position's spread over the
    SCA is left out unless a position is given. An SCA the measurement covers reads its own values,
    any other the worst over those it covers."""
    from . import scene as scenes

    shipped = scenes.shipped_model_uncertainty()
    conditions = shipped["conditions"]
    entry = shipped["per_band"][band][mode][metric]
    own = entry.get("per_sca", {}).get(str(sca))
    measured_scas = ", ".join(map(str, conditions["scas"]))
    where = f"SCA {sca}" if own else f"the worst over SCA {measured_scas} (SCA {sca} is not measured)"
    entry = own or entry
    measured_at = conditions["measured_at"]
    on = dict.fromkeys(scenes.EFFECTS, False) if scene is None else scene.effects_on()
    if fidelity != "table" and levels.simulation_settings(fidelity).n_wavelengths > 1:
        on["sed"] = True  # a band-integrated PSF simulates the (flat f_nu) SED
    parts = []
    for name in scenes.EFFECTS:
        if on[name]:
            continue
        value = entry["effects"].get(name)
        if name == "position":
            why = "spread over the SCA: no position given (the worst corner against the centre the tables hold)"
        elif value is None:
            why = f"not measured: {measured_at[name]}"
        else:
            why = f"not simulated; measured at {measured_at[name]}"
        parts.append({"name": name, "impact": value, "why": why})
    parts.append({"name": "pupil_scale", "impact": entry["pupil_scale"], "why": "pupil-mask scale rule: galsim (used) vs header"})
    return {
        "included": [{"name": name, "impact": None} for name in scenes.EFFECTS if on[name]],
        "left_out": parts,
        "stated_against": "modulus" if metric in ("e1", "e2") else "slope",
        "combine": "sum",
        "basis": (
            f"shipped measurement ({conditions['script']}, {conditions['measured_utc']}): each effect's worst |impact| on "
            f"the {mode} slope at its nominal Roman value on {where}, at m = {conditions['magnitudes']} "
            f"({conditions['method']}), added up (a Roman star has them all at once, with signs often alike)"
        ),
    }


def _model_at(info: dict, slopes: _Slopes, magnitude: float) -> dict:
    """The model part at the answer's magnitude: impacts relative to this metric's slope, and the
    relative uncertainty of the effects left out and of the pupil-scale rule (:data:`_MODEL_PARTS`).

    A shipped e1 / e2 impact is stated against |c_e| and scaled here by |c_e| / |c_ei|, as the
    optical model's part is."""
    scale = _component_scale(slopes, magnitude) if info["stated_against"] == "modulus" else 1.0
    left = [{**p, "impact": None if p["impact"] is None else p["impact"] * scale} for p in info["left_out"]]
    effects = _COMBINE[info["combine"]](
        [abs(p["impact"]) for p in left if p["impact"] is not None and p["name"] != "pupil_scale"]
    )
    pupil = next((abs(p["impact"]) for p in left if p["name"] == "pupil_scale" and p["impact"] is not None), 0.0)
    out = {**info, "left_out": left, "stated_against": "slope", "effects_relative": effects, "pupil_scale_relative": pupil}
    out.update(relative_uncertainty=math.hypot(effects, pupil), combination=_COMBINATION)
    if scale != 1.0:
        out["component_scale"] = scale
    return out


def _with_effect(target, source, name: str):
    """``target`` with effect ``name`` set as in ``source``."""

    fields_of = {
        "position": ("position",),
        "sed": ("sed", "sed_table", "sed_units", "n_wavelengths"),
        "jitter": ("jitter_arcsec",),
        "charge_diffusion": ("charge_diffusion_px",),
        "ipc": ("ipc", "ipc_label", "ipc_order"),
        "nl_polynomial": ("nl_coefficients",),
        "brighter_fatter": ("bfe_coefficient",),
        "background": ("background_e",),
    }
    return replace(target, **{f: getattr(source, f) for f in fields_of[name]})


def _optical_model_relative(slopes: _Slopes, magnitude: float | None) -> float:
    """Relative slope uncertainty from the optical model (``roman.optical_model_uncertainty``).

    For one ellipticity component it is stated against |c_e|, so it grows as |c_e| / |c_ei|."""
    relative = roman.optical_model_uncertainty(slopes.band, slopes.metric)
    if "relabelled_from" in slopes.table.settings:
        relative = math.hypot(relative, tables.RELABEL_ERROR[slopes.band][0 if slopes.metric == "size" else 1])
    return relative * _component_scale(slopes, magnitude)


def _component_scale(slopes: _Slopes, magnitude: float | None) -> float:
    """|c_e| / |c_ei| at ``magnitude`` for an e1 / e2 answer (1 otherwise): restates a part given
    against the modulus of the ellipticity slope against the component's own slope."""
    if slopes.metric not in ("e1", "e2") or magnitude is None:
        return 1.0
    modulus, _, _ = slopes.table.slope("e", slopes.mode, magnitude, slopes.exptime, slopes.table_beta0)
    component, _, _ = slopes.table.slope(slopes.metric, slopes.mode, magnitude, slopes.exptime, slopes.table_beta0)
    if np.isfinite(modulus[0]) and abs(component[0]) > 0:
        return float(modulus[0] / abs(component[0]))
    return 1.0


def _applies_to(mode: str, stars: int) -> str:
    if mode == "bias":
        return "every star alike: a bias in the mean beta is common to all stars, averaging does not reduce it"
    if stars == 1:
        return "one star: the scatter of a single star's metric over per-pixel beta maps"
    return (
        f"a PSF model averaging {stars} stars or dithers on independent pixels (scatter / sqrt({stars})), "
        "each as bright as the answer's magnitude"
    )


def _shear_answer(metric: str, budget, ratio, tolerance: float, tolerance_uncertainty: float | None) -> dict:
    """The shear budget given, or the bias the tolerance implies for galaxies of this size ratio."""
    if budget is not None:
        return {**budget.to_dict(), "given": budget.kind}
    kind = shear.BUDGET_FOR_METRIC[metric]
    factor = (2.0 if kind == "m" else 1.0 / shear.RESPONSIVITY) / ratio.effective**2
    implied = shear.Budget(kind, tolerance * factor, ratio, tolerance).to_dict()
    implied["given"] = "tolerance"
    implied["uncertainty"] = None if tolerance_uncertainty is None else tolerance_uncertainty * factor
    return implied


def _fidelity_error(level: str, band: str, metric: str, mode: str) -> tuple[float | None, str | None]:
    """The level's measured relative error on this slope (``nlpsf tradeoff``), or why it is unknown."""
    try:
        return levels.level_error(band, metric, mode, level), None
    except (SimulationError, KeyError):
        return None, make(FlagCode.FIDELITY_ERROR_UNKNOWN)


def _peak_electrons(slopes: _Slopes, magnitude: float) -> float:
    table = slopes.table
    flux = float(table.flux_at(magnitude - 2.5 * math.log10(slopes.exptime / table.exptime_s)))
    return flux * table.peak_fraction * int(table.settings["oversampling"]) ** 2


def _magnitude_flags(slopes: _Slopes, magnitude: float, region: int, m_sat: float, beta0: float) -> list[str]:
    lo, hi = slopes.range()
    if region < 0:
        peak = _peak_electrons(slopes, magnitude)
        if 2 * beta0 * peak >= 1:
            raise InputError(
                "magnitude",
                f"an m={magnitude:g} star is too bright for beta0={beta0:g}: the quadratic nonlinearity is not monotonic "
                f"there (2 beta0 Q_peak = {2 * beta0 * peak:.2f} >= 1), so S = Q - beta Q^2 does not describe the detector",
            )
        raise InputError(
            "magnitude",
            f"m={magnitude:g} is brighter than the tables reach at these conditions (m >= {lo:.2f}: the tables stop "
            f"{tables.BRIGHT_MARGIN_MAG} mag past saturation, in beta0 x flux); such a star saturates the detector several "
            "times over and has no meaningful NL answer",
        )
    flags = []
    if region > 0:
        flags.append(make(FlagCode.EXTRAPOLATED_FAINT, magnitude=magnitude, faintest=hi))
    if magnitude < m_sat:
        flags.append(make(FlagCode.STAR_SATURATED, magnitude=magnitude, m_sat=m_sat))
    return flags


def _validity_flags(
    slopes: _Slopes, magnitude: float | None, precision: float | None, beta0: float, full_well: float
) -> list[str]:
    if magnitude is None or not math.isfinite(magnitude):
        return []
    peak = _peak_electrons(slopes, magnitude)
    if slopes.ramp is not None:
        # The fit only sees reads up to the last unsaturated resultant (or the first one).
        peak = min(peak, max(full_well, peak * slopes.ramp.first_usable_fraction(slopes.exptime)))
    flags = []
    if 2 * beta0 * peak >= 1:
        flags.append(make(FlagCode.QUADRATIC_NOT_MONOTONIC, value=2 * beta0 * peak, magnitude=magnitude))
    if precision is not None and math.isfinite(precision) and precision * beta0 * peak > LINEAR_REGIME_LIMIT:
        flags.append(make(FlagCode.OUTSIDE_LINEAR_REGIME, value=precision * beta0 * peak, limit=LINEAR_REGIME_LIMIT))
    return flags


def _solve_magnitude(slopes: _Slopes, delta_beta: float, tolerance: float, m_sat: float):
    """Magnitude where |c(m)| delta_beta = tolerance, scanning from faint to bright so that every
    fainter star also meets the tolerance (|c| need not be monotonic when e1 or e2 changes sign).

    Returns (m, slope, slope uncertainty, d ln|c| / dm, flags); m is None when even the brightest
    tabulated star stays within the tolerance.
    """
    flags: list[str] = []
    required = tolerance / delta_beta
    lo, hi = slopes.range()
    grid = np.arange(hi, lo - 1e-9, -0.05)  # faint to bright
    shift = slopes.table.magnitude_shift(slopes.exptime, slopes.beta0)
    factor = slopes.table.beta0 / slopes.beta0
    value = slopes.table.values(slopes.metric, slopes.mode, grid - shift) * factor
    above = np.abs(value) > required
    if above[0]:
        # Even the faintest tabulated star exceeds the tolerance: go fainter along the linear
        # regime, where |c| is proportional to the flux.
        m_nl = float(hi + 2.5 * math.log10(abs(value[0]) / required))
        flags.append(make(FlagCode.EXTRAPOLATED_ANSWER, faintest=hi, magnitude=m_nl))
        if m_nl > 40:
            flags.append(make(FlagCode.FAINTER_THAN_40))
        slope, slope_err = slopes.at(m_nl)[:2]
        return m_nl, slope, slope_err, -0.4 * math.log(10), flags
    if not above.any():
        margin = tables.BRIGHT_MARGIN_MAG
        where = f"over the whole table, down to m={lo:.2f} ({margin} mag brighter than saturation, in beta0 x flux)"
        flags.append(make(FlagCode.BELOW_TOLERANCE_EVERYWHERE, where=where, down_to=lo))
        return None, None, None, None, flags
    k = int(np.argmax(above))  # first magnitude (from the faint side) where the tolerance is exceeded
    bright, faint = float(grid[k]), float(grid[k - 1])

    def excess(m: float) -> float:
        return math.log(abs(slopes.at(m)[0]) / required)

    if slopes.fidelity == "table":
        # One vectorised look-up on a 1e-4 mag sub-grid of the bracket, then linear interpolation
        # of log|c| between the two sub-grid points around the crossing: ~1e-9 mag, in one call.
        sub = np.linspace(faint, bright, 501)
        log_c = np.log(np.abs(slopes.table.values(slopes.metric, slopes.mode, sub - shift) * factor) / required)
        j = max(int(np.argmax(log_c > 0)), 1)
        m_nl = float(sub[j - 1] + (sub[j] - sub[j - 1]) * (0.0 - log_c[j - 1]) / (log_c[j] - log_c[j - 1]))
    else:
        # Fresh simulations: few evaluations, starting from the table's bracket widened a little.
        m_nl = _secant_root(excess, bright - 0.1, faint + 0.1)
    slope, slope_err, _ = slopes.at(m_nl)
    h = 0.01
    ends = np.abs(slopes.table.values(slopes.metric, slopes.mode, np.array([m_nl + h, m_nl - h]) - shift))
    log_derivative = float(np.log(ends[0] / ends[1]) / (2 * h))
    if any(np.diff(np.sign(value[np.isfinite(value)])) != 0):
        flags.append(make(FlagCode.SLOPE_CHANGES_SIGN, metric=slopes.metric, where="within the table"))
    return m_nl, slope, slope_err, log_derivative, flags


def _secant_root(function, a: float, b: float, tolerance: float = 1e-4, iterations: int = 12) -> float:
    fa, fb = function(a), function(b)
    if fa * fb > 0:
        from scipy.optimize import brentq

        return brentq(function, a - 1.0, b + 1.0, xtol=tolerance)
    c = b
    for _ in range(iterations):
        c = b - fb * (b - a) / (fb - fa)
        fc = function(c)
        if abs(fc) < 1e-6 or abs(c - b) < tolerance:
            return c
        if fa * fc < 0:
            b, fb = c, fc
        else:
            a, fa = c, fc
    return c


def _ramp_basis(slopes: _Slopes) -> str:
    parts = []
    if "table" in slopes.ramp_bases:
        parts.append(
            f"tables at beta_eff = {slopes.ramp_factor:.6g} beta0 "
            "(exact: quadratic NL, OLS fit, every pixel keeps every resultant)"
        )
    if "simulation" in slopes.ramp_bases:
        level = "linear-response" if slopes.fidelity in ("table", "linear") else slopes.fidelity.replace("_", " ")
        why = (
            "the optimally weighted fit has no exact table mapping"
            if slopes.ramp.fit == "optimal"
            else f"brighter than m={slopes.exact_from():.2f} pixels drop saturated resultants"
            if slopes.fidelity == "table"
            else f"fidelity {slopes.fidelity} asked for"
        )
        parts.append(f"fresh {level} simulations of the ramp ({why}; {int(slopes.table.settings['realizations'])} realizations)")
    return "; ".join(parts) or "none needed"


def _between_limits_flag(magnitude: float, m_sat: float, m_sat_final_frame: float) -> Flag:
    return make(FlagCode.BETWEEN_SATURATION_LIMITS, magnitude=magnitude, m_sat_final=m_sat_final_frame, m_sat=m_sat)


def _ramp_magnitude_flags(magnitude: float, m_sat: float, m_sat_final_frame: float) -> list[str]:
    if magnitude < m_sat - tables.BRIGHT_MARGIN_MAG:
        raise InputError(
            "magnitude",
            f"m={magnitude:g} saturates the brightest pixel in the first resultant of the ramp by more than "
            f"{tables.BRIGHT_MARGIN_MAG} mag (usable down to m={m_sat:.2f}); such a star has no meaningful NL answer",
        )
    if magnitude < m_sat:
        return [make(FlagCode.RAMP_SATURATED, magnitude=magnitude, m_sat=m_sat)]
    if magnitude < m_sat_final_frame:
        return [_between_limits_flag(magnitude, m_sat, m_sat_final_frame)]
    return []


def _solve_magnitude_ramp(slopes: _Slopes, delta_beta: float, tolerance: float, m_sat: float):
    """As :func:`_solve_magnitude` for a ramp. Fainter than where the brightest pixel starts dropping
    resultants, |c(m)| comes at once from the tables at the OLS beta_eff on a 0.05 mag grid (exact for
    an OLS fit, a bracket for the optimal one); brighter, down to the ramp's saturation magnitude,
    from the slopes themselves on a 0.25 mag grid (fresh simulations); the crossing is then refined on
    the exact slopes (secant method on log |c|)."""
    flags: list[str] = []
    required = tolerance / delta_beta
    hi = slopes.range()[1]
    exact = min(slopes.exact_from(), hi)
    c_ols = slopes.ramp.ols_quadratic_factor(slopes.exptime)
    table = slopes.table
    faint_grid = np.arange(hi, exact - 1e-9, -0.05)
    shift = table.magnitude_shift(slopes.exptime, c_ols * slopes.beta0)
    faint_values = table.values(slopes.metric, slopes.mode, faint_grid - shift) * (table.beta0 / slopes.beta0)
    bright_grid = np.arange(exact - 0.25, m_sat - 1e-9, -0.25)
    if bright_grid.size == 0 or bright_grid[-1] > m_sat + 1e-9:
        bright_grid = np.append(bright_grid, m_sat)
    if slopes.fidelity == "table" and slopes.ramp_factor is not None:
        slopes.ramp_bases.add("table")
    if np.any(np.abs(faint_values) > required):
        bright_grid = bright_grid[:0]  # the crossing is in the table part: no simulation needed to find it
    grid = np.concatenate([faint_grid, bright_grid])
    value = np.concatenate([faint_values, [slopes.at(float(m))[0] for m in bright_grid]])
    above = np.abs(value) > required
    if above[0]:
        at_hi = slopes.at(hi)[0]  # the fit in use, at the faint end of the table
        m_nl = float(hi + 2.5 * math.log10(abs(at_hi) / required))
        flags.append(make(FlagCode.EXTRAPOLATED_ANSWER, faintest=hi, magnitude=m_nl))
        slope, slope_err = slopes.at(m_nl)[:2]
        return m_nl, slope, slope_err, -0.4 * math.log(10), flags
    if not above.any():
        where = f"for every star down to the ramp's saturation limit m={m_sat:.2f}"
        flags.append(make(FlagCode.BELOW_TOLERANCE_EVERYWHERE, where=where, down_to=m_sat))
        return None, None, None, None, flags
    k = int(np.argmax(above))
    bright, faint = float(grid[k]), float(grid[k - 1])

    def excess(m: float) -> float:
        return math.log(abs(slopes.at(m)[0]) / required)

    if slopes.fidelity == "table" and slopes.ramp_factor is not None and bright >= slopes.exact_from():
        from scipy.optimize import brentq  # table look-ups are cheap: bracket to 1e-6 mag

        m_nl = brentq(excess, bright, faint, xtol=1e-6)
    else:
        m_nl = _secant_root(excess, bright, faint)
    slope, slope_err, _ = slopes.at(m_nl)
    h = 0.01
    log_derivative = (math.log(abs(slopes.at(m_nl + h)[0])) - math.log(abs(slopes.at(m_nl - h)[0]))) / (2 * h)
    if any(np.diff(np.sign(value[np.isfinite(value)])) != 0):
        flags.append(make(FlagCode.SLOPE_CHANGES_SIGN, metric=slopes.metric, where="over the scan"))
    return m_nl, slope, slope_err, log_derivative, flags


def _binding(m_nl: float | None, m_sat: float, flags: list[str]) -> tuple[float, str]:
    """The brightest usable star: the fainter of the NL limit and saturation, and which binds."""
    if m_nl is None or m_nl < m_sat:
        where = "" if m_nl is None else f" (the NL error would reach the tolerance only at m={m_nl:.2f})"
        flags.append(make(FlagCode.SATURATION_BINDS, m_sat=m_sat, where=where, nonlinearity_magnitude=m_nl))
        return m_sat, "saturation"
    return m_nl, "nonlinearity"


def _tables_hold(scene, tableset: tables.TableSet, band: str, sca: int) -> bool:
    """Whether the tables already hold the scene: it differs from the paper's by its position alone,
    and the table of (band, SCA) was built at that position (a field-point table, or the centre's)."""
    if not replace(scene, position=None).is_paper or scene.position is None:
        return False
    held = tableset.get(band, sca).position_pixels
    return all(abs(a - b) < 1e-6 for a, b in zip(held, scene.position, strict=True))


def _corner_tables(scene, sca: int) -> tables.TableSet | None:
    """The field-point tables at the scene's position, if it is one of the SCA's corner field points
    and the scene has no other effect; None otherwise (or where no field-point tables are installed)."""
    if scene.position is None or not replace(scene, position=None).is_paper:
        return None
    for point, position in enumerate(roman.field_points(sca)):
        if point and all(abs(a - b) < 1e-6 for a, b in zip(position, scene.position, strict=True)):
            corners = field_tables()
            return None if corners is None else corners.at_point(point)
    return None


def field_points(sca: int) -> list[tuple[float, float]]:
    """Where ``solve_over_field`` looks on an SCA: its centre and the four corner field points
    (``roman.field_points`` 1-4). The Zernikes are interpolated bilinearly between the corners, so
    every coefficient takes its extremes there; the centre is where the SCA-centre tables are."""
    centre = (roman.SCA_PIXELS / 2, roman.SCA_PIXELS / 2)
    return [centre, *roman.field_points(sca)[1:]]


def field_tables() -> tables.TableSet | None:
    """The shipped field-point tables, None if this installation has none."""
    path = tables.field_table_path()
    return tables.load_tables(str(path)) if path.exists() else None


def over_field_from_tables(scene=None, fidelity: str | None = None, accuracy: float | None = None, ramp=None) -> bool:
    """Whether ``solve_over_field`` answers such a request from the tables alone (milliseconds, no
    simulation): the paper's scene, the table level, no accuracy to measure, no ramp, and the
    field-point tables installed."""
    plain = (scene is None or scene.is_paper) and ramp is None and accuracy is None
    return plain and fidelity in (None, "table") and field_tables() is not None


def solve_over_field(band: str, scas="all", scene=None, progress=None, **request) -> Solution:
    """The answer for the worst position over the field: the centre and four corners of the given
    SCAs (``"all"``: the 18 of the focal plane), each with its own aberrations.

    At the table level (the default) the answer reads the SCA-centre tables and the shipped
    field-point tables (``field_slopes.ecsv.gz``), milliseconds per point. A scene with other effects,
    or a simulating fidelity, simulates every point (linear response unless another level is asked
    for; seconds per point). Worst means the most demanding answer: the smallest precision, the
    largest tolerance, or the faintest brightest-usable magnitude. The Solution returned is that
    point's, with every point's value in ``conditions["over_field"]`` and where the worst lies in a
    flag.
    """

    from . import scene as scenes

    chosen = list(range(1, roman.N_SCA + 1)) if scas == "all" else [roman.check_sca(s) for s in scas]
    base = scene if scene is not None else scenes.SceneModel()
    if base.position is not None:
        raise InputError("position", "give a position or ask for the worst over the field, not both")
    # Each corner's own table is found by ``solve`` from the position (``_corner_tables``).
    corners = field_tables() if base.is_paper and request.get("tables_set") is None else None
    if corners is None and request.get("fidelity") in (None, "table"):
        # Without field-point tables (or with a scene they do not hold) every point is simulated.
        request["fidelity"] = "linear"
    answers = []
    points = [(s, p) for s in chosen for p in field_points(s)]
    for index, (sca, position) in enumerate(points):
        if progress:
            progress(index, len(points), f"SCA {sca} at {position[0]:.0f},{position[1]:.0f}")
        answers.append((sca, position, solve(band, sca, scene=replace(base, position=position), **request)))
    if progress:
        progress(len(points), len(points), "done")
    solved = answers[0][2].solved_for

    def demand(solution: Solution) -> float:
        value = getattr(solution, solved)
        if value is None or not math.isfinite(value):
            return -math.inf
        return {"precision": -value, "tolerance": value, "magnitude": value}[solved]

    sca, position, worst = max(answers, key=lambda item: demand(item[2]))
    values = [getattr(a[2], solved) for a in answers]
    finite = [v for v in values if v is not None and math.isfinite(v)]
    conditions = dict(worst.conditions)
    conditions["over_field"] = [
        {"sca": s, "position": list(p), solved: _json_number(getattr(a, solved)), "uncertainty": _json_number(a.uncertainty)}
        for s, p, a in answers
    ]
    where = "all 18 SCAs" if scas == "all" else "SCA " + ", ".join(map(str, chosen))
    flag = make(
        FlagCode.WORST_OVER_FIELD,
        points=len(points),
        where=where,
        sca=sca,
        x=position[0],
        y=position[1],
        solved=solved,
        low=min(finite),
        high=max(finite),
    )
    return replace(worst, flags=[flag, *worst.flags], conditions=conditions)
