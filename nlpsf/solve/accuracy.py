"""``accuracy``: what an answer must simulate to be within a relative accuracy A of the full scene.

The promise: the answer's slope is within A (plus its statistical error) of the slope of the full
scene -- the request's scene, by default the Roman default (``nlpsf.request.presets``) at the
request's position, readout and linearisation state -- simulated at the most exact level. Two
things may separate them, and both are budgeted against A:

- the fidelity level (:func:`level_for`): its measured relative error (``nlpsf/data/fidelity.json``,
  ``nlpsf tradeoff``). A Roman-default entry is read when the file has one (:data:`ROMAN_ENTRY`);
  otherwise the paper scene's measurement is used and the answer says so
  (``FlagCode.FIDELITY_FROM_PAPER``). A scene that integrates its SED over >= 8 wavelengths is
  band-integrated like the measured ``polychromatic`` level, so its linear level is given that
  level's measured error, not the achromatic one's.
- the effects left out (:func:`select`): each effect's impact is measured *inside the full
  scene*, as ``slope(full scene without it) / slope(full scene) - 1``, and a set of effects is left
  out only while the impact of the set *measured as a set* (all removed together) stays within what
  the fidelity error leaves of A. Effects that share a sign, or that interact (jitter and diffusion
  move a slope more with the SED on), are therefore never left out together on the strength of
  their separate impacts.

Leaving an effect out only saves CPU, and measuring its impact costs a simulation with it, so the
search runs only where it can pay: when the level A needs is the linear response (or the tables)
the full scene is simulated as it is, nothing is left out and no impact is measured
(``search="auto"``). The search runs when a more expensive level is needed (Monte Carlo), or when
asked (``search="always"``).

Impacts are measured with the linear response at one magnitude (the answer's, found by a
table-level first pass when the magnitude is solved for) on :data:`PROBE_REALIZATIONS` centroids,
the same draws for every variant; each impact carries its standard error over centroid samples
(:func:`impact_uncertainty`: the two slopes' errors over the centroids added linearly, a bound
whatever their correlation), and a set is left out only while ``|impact| + error`` (plus the
level's error) stays within the budget. The probe integrates the SED over the wavelengths the
answer will simulate: an impact is that of the scene as simulated (the same set measured with the
SED over 8 wavelengths instead of the default's 2 moves by 2.7e-4 for K213 size, a difference of the
levels, not of the centroids, which the identity ``slope_L(reduced) / slope_exact(full) =
(1 + impact_L) (slope_L(full) / slope_exact(full))`` leaves to the level's measured error).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from nlpsf import defaults
from nlpsf.flags import Flag, FlagCode, make
from nlpsf.sim import scene as scenes
from nlpsf.slopes import fidelity as levels
from nlpsf.slopes import tables

#: Centroids of the impact measurement (same draws for every variant; see the module docstring).
PROBE_REALIZATIONS = 20
#: Centroids of the answer's own linear-response simulations: their standard error stays ~1e-5 of
#: the slope or below (the answer quotes it), far under any accuracy the range allows, at a quarter
#: of the tables' 100 centroids' cost. Monte Carlo levels keep the tables' count.
ANSWER_REALIZATIONS = 25
#: Where pixels lose resultants (between a ramp's saturation limits) the slope jumps from centroid
#: to centroid as each pixel does (25 centroids gave a statistical error of 71 % of a Y106 e2
#: slope, issue 28): an answer there simulates enough centroids for its statistical error to stay
#: within this share of the accuracy, measured on a pilot of the tables' own draws.
STATISTICAL_SHARE = 0.5
#: The pilot's centroids there: the tables' and the field grid's own 100 (the same draws).
BETWEEN_LIMITS_PILOT = 100
#: The most centroids an answer simulates there, in batches of ``source.BATCH_REALIZATIONS`` (one
#: prepared scene each, so the memory stays a batch's): ~2.4 ms of CPU each on H158's HLWAS ramp,
#: about 30 s at the cap. Beyond it the statistical error is stated.
MAX_REALIZATIONS = 12_800
#: Where ``fidelity.json`` holds the Roman default's measurement (same shape as the top level:
#: ``errors[band][mode][metric][level]``, ``date``, ``reference``; ``tradeoff(default="roman")``).
ROMAN_ENTRY = ("roman",)
#: Wavelengths from which a band-integrated simulation is the measured ``polychromatic`` level.
BAND_INTEGRATED_WAVELENGTHS = levels.POLYCHROMATIC_WAVELENGTHS
#: The model part's name for the set an answer leaves out, beside the Roman default's parts.
LEFT_OUT_PART = "accuracy_left_out"
#: ``search`` choices of :func:`select`.
SEARCHES = ("auto", "always", "never")


@dataclass(frozen=True)
class FullScene:
    """The scene an ``accuracy`` answer is held to, with the simulation conditions it runs under."""

    scene: scenes.SceneModel
    #: "roman default" (the request's scene is the Roman default's, at any position), or "request".
    source: str
    ramp: object | None
    exptime: float
    pupil_scale: str
    linearise_at: str
    throughput: str | None
    #: How a calibration error acts in the corrected state (``experiment.correction.RESIDUAL_MODELS``).
    residual_nl: str | None = None

    @property
    def is_roman_default(self) -> bool:
        return self.source == "roman default"


def full_scene(request, table) -> FullScene:
    """The full scene of ``request``: its own scene when it gives one (the paper's for the "paper"
    preset, which the request holds as no scene), else the Roman default at
    the SCA centre (``roman_default.scene``) with the background over the request's exposure. The
    readout, pupil rule and linearisation state are the request's (those the solver simulates with)."""
    from nlpsf.request import presets as roman_default
    from nlpsf.roman import backgrounds

    linearise_at = getattr(request, "linearise_at", None) or "beta0"
    pupil = request.pupil_scale or str(table.settings["pupil_scale"])
    default = request.policy.quotes_default
    if request.scene is not None:
        # A request filled with the Roman default (``roman_default.fill``) holds the default's scene:
        # it is the Roman default, whose own fidelity measurement applies, at any position.
        own = default and roman_default.is_default_scene(request.scene, request.scene.background_e)
        scene, source = request.scene, "roman default" if own else "request"
    elif not request.policy.quotes_default:
        # A preset's scene the request normalises away (``SolveRequest``: "paper" is the plain path).
        scene, source = roman_default.preset_base(request.preset), "request"
    else:
        background = backgrounds.background_electrons(roman_default.BACKGROUND, request.band, request.sca, request.exptime)
        scene, source = roman_default.scene(None, background), "roman default"
    residual = getattr(request, "residual_model", None)
    return FullScene(
        scene, source, request.ramp, request.exptime, pupil, linearise_at, request.throughput or table.throughput, residual
    )


# --- the fidelity level -------------------------------------------------------------------------


@dataclass(frozen=True)
class Level:
    """A fidelity level for a scene, with its measured relative error and where that comes from."""

    name: str
    error: float
    basis: str


def _measurement(full: FullScene, band: str) -> tuple[dict, bool]:
    """(the measurement a level's error is read from, whether it is the Roman default's own)."""
    data = levels.measured()
    entry = data
    for key in ROMAN_ENTRY:
        entry = entry.get(key, {}) if isinstance(entry, dict) else {}
    if full.is_roman_default and band in entry.get("errors", {}):
        return entry, True
    return data, False


def _band_integrated(scene: scenes.SceneModel | None) -> bool:
    return scene is not None and scene.sed is not None and (scene.n_wavelengths or 0) >= BAND_INTEGRATED_WAVELENGTHS


def level_error(full: FullScene, simulated: scenes.SceneModel | None, band: str, metric: str, mode: str, level: str) -> Level:
    """The measured relative error of ``level`` on a simulation of ``simulated`` (see the module docstring)."""
    data, own = _measurement(full, band)
    errors = data["errors"][band][mode][metric]
    if own:
        value = errors.get(level)  # a level the measurement leaves out is never chosen
        basis = f"Roman default's measurement ({data.get('date', 'undated')})"
        return Level(level, math.inf if value is None else float(value), basis if value is not None else "not measured")
    if level in ("linear", "monte_carlo") and _band_integrated(simulated):
        # Band-integrated like the measured polychromatic level (which is Monte Carlo at 8 wavelengths
        # against the linear response at 16: an upper bound for the linear response at >= 8).
        basis = f"paper scene's measurement ({data['date']}), band-integrated level (the scene integrates its SED)"
        return Level(level, float(errors["polychromatic"]), basis)
    return Level(level, float(errors[level]), f"paper scene's measurement ({data['date']})")


def level_for(full: FullScene, simulated, band: str, metric: str, mode: str, budget: float) -> tuple[Level, bool]:
    """The cheapest level whose measured error is within ``budget`` (else the most accurate), and
    whether one meets it. The table level only for the paper's scene (the tables hold nothing else)."""
    candidates = levels.LEVELS if simulated is None or simulated.no_effects else levels.SIMULATION_LEVELS
    measured = [level_error(full, simulated, band, metric, mode, name) for name in candidates]
    for level in measured:
        if level.error <= budget:
            return level, True
    return min(measured, key=lambda level: level.error), False


def _with_band_integration(scene: scenes.SceneModel) -> scenes.SceneModel:
    """The scene's SED integrated over at least :data:`BAND_INTEGRATED_WAVELENGTHS` wavelengths."""
    if scene.sed is None:
        return scene
    return replace(scene, n_wavelengths=max(BAND_INTEGRATED_WAVELENGTHS, scene.n_wavelengths or 1))


# --- impacts inside the full scene --------------------------------------------------------------


def linear_config(request, full: FullScene, table, realizations: int, scene: scenes.SceneModel):
    """The linear-response simulation an accuracy answer measures with: the table's settings
    (``SimulationConfig.from_table``) at the request's band and SCA, the full scene's exposure,
    throughput and pupil rule, ``realizations`` centroids and ``scene``; with a ramp, the ramp and the
    request's full well (a final frame keeps the table's)."""
    from nlpsf.sim import experiment

    return experiment.SimulationConfig.from_table(
        table.settings,
        band=request.band,
        sca=request.sca,
        exptime_s=full.exptime,
        throughput=full.throughput,
        method="linear",
        realizations=realizations,
        pupil_scale=full.pupil_scale,
        scene=scene,
        **({} if full.ramp is None else {"ramp": full.ramp, "full_well_e": request.full_well}),
    )


class Probe:
    """Linear-response slopes of variants of the full scene at one magnitude, on the same centroids.

    ``impact(names)`` is ``slope(full without names) / slope(full) - 1`` on the request's metric and
    mode, with its standard error over centroid samples (:func:`impact_uncertainty`, a bound)."""

    def __init__(self, request, full: FullScene, table, magnitude: float, realizations: int = PROBE_REALIZATIONS):
        self.request, self.full, self.magnitude = request, full, float(magnitude)
        self.base = linear_config(request, full, table, realizations, full.scene)
        self._slopes: dict[scenes.SceneModel, tuple[float | None, float | None]] = {}
        self.runs = 0

    def slope(self, scene: scenes.SceneModel) -> tuple[float | None, float | None]:
        from nlpsf.sim import experiment

        key = replace(scene, name=None)
        if key not in self._slopes:
            config = replace(self.base, scene=key)
            result = experiment.slopes(
                config,
                [self.magnitude],
                beta0=self.request.beta0,
                linearise_at=self.full.linearise_at,
                residual_nl=self.full.residual_nl,
            )[0]
            self._slopes[key] = result.slope(self.request.mode, defaults.METRIC_COLUMNS[self.request.metric])
            self.runs += 1
        return self._slopes[key]

    def without(self, names) -> scenes.SceneModel:
        scene = self.full.scene
        for name in names:
            scene = scene.without(name)
        return scene

    def impact(self, names) -> tuple[float | None, float | None]:
        (a, da), (b, db) = self.slope(self.without(names)), self.slope(self.full.scene)
        if a is None or b is None or b == 0 or a == 0:
            return None, None
        ratio = a / b
        return ratio - 1.0, impact_uncertainty(ratio, a, da, b, db)


def impact_uncertainty(ratio: float, a: float, da: float, b: float, db: float) -> float:
    """The standard error of an impact ``ratio - 1`` (``ratio = a / b``) over centroid samples.

    Both slopes are means over the same centroids; their standard errors (``da``, ``db``) are the
    spread over those centroids / sqrt(n). The ratio's error over another sample of centroids is
    ``sqrt(Var(a_i - ratio b_i) / n) / |b|``, which needs the two slopes' covariance over the
    centroids; measured, their correlation runs from -0.5 (K213 size, a set with IPC) to +0.95
    (H158 size, the SED), so neither the quadrature sum (independent: too small where they
    anti-correlate) nor zero (fully paired) is safe. The errors added linearly,
    ``|ratio| (da/|a| + db/|b|)``, bound it whatever the correlation (Cauchy-Schwarz)."""
    return abs(ratio) * (abs(da / a) + abs(db / b))


# --- the selection ------------------------------------------------------------------------------


@dataclass
class Selection:
    """What an ``accuracy`` answer simulates, at which level, and what it leaves out."""

    fidelity: str
    scene: scenes.SceneModel | None
    model: dict
    notes: list[Flag] = field(default_factory=list)
    #: Centroids of the answer's fresh simulations (None: the tables' own).
    realizations: int | None = None


def _removable(scene: scenes.SceneModel) -> list[str]:
    on = scene.effects_on()
    return [name for name in scenes.EFFECTS if on[name]]


def select(request, magnitude: float, tables_set: tables.TableSet | None = None, search: str = "auto") -> Selection:
    """The scene and fidelity level of an ``accuracy`` answer at ``magnitude`` (see the module docstring)."""
    if search not in SEARCHES:
        raise ValueError(f"search must be one of {SEARCHES}, got {search!r}")
    accuracy = float(request.accuracy)
    band, metric, mode = request.band, request.metric, request.mode
    table = (tables_set or tables.load_tables()).get(band, request.sca)
    full = full_scene(request, table)
    own = _measurement(full, band)[1]
    if not own:
        # The paper's measurement covers a band-integrated scene at >= 8 wavelengths (level_error); the
        # Roman default's own measurement is of the levels as the default runs them.
        full = replace(full, scene=_with_band_integration(full.scene))
    notes: list[Flag] = []
    level, met = level_for(full, full.scene, band, metric, mode, accuracy)
    if not own:
        notes.append(make(FlagCode.FIDELITY_FROM_PAPER, scene=full.source, level=level.name, error=level.error))
    left: list[str] = []
    combined: tuple[float | None, float | None] = (0.0, 0.0)
    probe = None
    effects: list[dict] = []
    if search == "always" or (search == "auto" and level.name not in ("table", "linear")):
        probe = Probe(request, full, table, magnitude)
        left, combined, level, effects = _search(probe, full, band, metric, mode, accuracy, level)
    simulated = probe.without(left) if probe is not None else full.scene
    fidelity_level = level.name
    if simulated.no_effects:
        simulated = None if fidelity_level == "table" else simulated
    elif fidelity_level == "table":
        fidelity_level = "linear"
    error = level.error + (abs(combined[0]) if combined[0] is not None else 0.0)
    notes.append(
        make(
            FlagCode.ACCURACY_SCENE,
            accuracy=accuracy,
            level=fidelity_level,
            level_error=level.error,
            left_out=", ".join(left) or "nothing",
            impact=combined[0] or 0.0,
            total=error,
        )
    )
    if not met or error > accuracy:
        notes.append(make(FlagCode.FIDELITY_NONE_MEETS, accuracy=accuracy, band=band, metric=metric, mode=mode,
                          level=fidelity_level, error=level.error))  # fmt: skip
    model = _model_info(request, full, magnitude, left, combined, level, effects, probe, accuracy)
    realizations = ANSWER_REALIZATIONS if fidelity_level == "linear" else None
    if fidelity_level == "linear":
        centroids = centroids_where_pixels_saturate(request, full, table, simulated, magnitude, accuracy)
        if centroids is not None:
            realizations = centroids["used"]
            model["centroids"] = centroids
            notes.append(make(FlagCode.ACCURACY_CENTROIDS, **{k: centroids[k] for k in ACCURACY_CENTROIDS_QUOTES}))
    return Selection(fidelity_level, simulated, model, notes, realizations)


#: The values ``FlagCode.ACCURACY_CENTROIDS`` quotes from :func:`centroids_where_pixels_saturate`.
ACCURACY_CENTROIDS_QUOTES = ("magnitude", "pilot", "pilot_error", "used", "errors", "target", "verdict")


def centroids_where_pixels_saturate(request, full: FullScene, table, simulated, magnitude: float, accuracy: float) -> dict | None:
    """How many centroids an answer at ``magnitude`` needs where pixels lose resultants, or None
    where none does (no ramp, or fainter than the tables' final-frame limit, or a pilot without a
    pixel on fewer resultants). A pilot of :data:`BETWEEN_LIMITS_PILOT` centroids (the tables' draws)
    measures the slope's relative statistical error r; the answer simulates N = pilot (r / t)^2 with
    t = :data:`STATISTICAL_SHARE` x accuracy, within [pilot, :data:`MAX_REALIZATIONS`], so that its
    error is about r sqrt(pilot / N). Where even the cap leaves it above t, ``verdict`` says so."""
    from nlpsf.sim import experiment

    if full.ramp is None or simulated is None:
        return None
    background = float(getattr(full.scene, "background_e", 0.0) or 0.0)
    # The paper's star is the sharpest the tables hold: no pixel of a broader star saturates fainter.
    if magnitude > table.saturation(full.exptime, request.full_well - background) + 0.5:
        return None
    config = linear_config(request, full, table, BETWEEN_LIMITS_PILOT, simulated)
    result = experiment.slopes(
        config, [magnitude], beta0=request.beta0, linearise_at=full.linearise_at, residual_nl=full.residual_nl
    )[0]
    summary = result.extras.get("ramp") or {}
    if not (summary.get("fitted_on_fewer") or summary.get("unusable")):
        return None
    value, error = result.slope(request.mode, defaults.METRIC_COLUMNS[request.metric])
    relative = math.inf if not value else abs((error or 0.0) / value)
    target = STATISTICAL_SHARE * accuracy
    needed = BETWEEN_LIMITS_PILOT * (relative / target) ** 2 if math.isfinite(relative) else math.inf
    used = int(min(MAX_REALIZATIONS, max(BETWEEN_LIMITS_PILOT, math.ceil(needed) if math.isfinite(needed) else MAX_REALIZATIONS)))
    expected = relative * math.sqrt(BETWEEN_LIMITS_PILOT / used)
    met = expected <= target * (1 + 1e-9)
    verdict = (
        "within it"
        if met
        else f"above it: {needed:.3g} centroids would be needed, more than the {MAX_REALIZATIONS} an answer simulates"
    )
    return {
        "magnitude": float(magnitude),
        "pilot": BETWEEN_LIMITS_PILOT,
        "pilot_error": relative,
        "pixels_on_fewer_resultants": int(summary.get("fitted_on_fewer") or 0) + int(summary.get("unusable") or 0),
        "needed": needed,
        "used": used,
        "expected_error": expected,
        # What the answer reaches is measured over the count it simulates (``centroids.enough_centroids``).
        "errors": f"{expected:.2g} expected over {used}",
        "target": target,
        "met": met,
        "verdict": verdict,
        "rule": f"N = pilot (r / t)^2 within [{BETWEEN_LIMITS_PILOT}, {MAX_REALIZATIONS}], t = {STATISTICAL_SHARE:g} x accuracy",
    }


def _search(probe: Probe, full: FullScene, band, metric, mode, accuracy: float, level: Level):
    """Grow the left-out set from the smallest impact up, keeping an effect only while the set's
    impact, measured as a set, plus the level's error (for the scene then simulated) stays within A,
    and the level does not get dearer. A band-integrated level integrates the band anyway: the SED
    is no candidate there (leaving it out would save nothing)."""
    candidates = [n for n in _removable(full.scene) if not (n == "sed" and level.name == "polychromatic")]
    alone = {name: probe.impact([name]) for name in candidates}
    effects = [{"name": n, "impact_alone": v, "uncertainty": e} for n, (v, e) in alone.items()]
    order = sorted((n for n in candidates if alone[n][0] is not None), key=lambda n: abs(alone[n][0]))
    left: list[str] = []
    combined: tuple[float | None, float | None] = (0.0, 0.0)
    for name in order:
        trial = [*left, name]
        value, error = probe.impact(trial)
        if value is None:
            continue
        trial_level, met = level_for(full, probe.without(trial), band, metric, mode, accuracy)
        cheaper = levels.LEVELS.index(trial_level.name) <= levels.LEVELS.index(level.name)
        if met and cheaper and trial_level.error + abs(value) + error <= accuracy:
            left, combined, level = trial, (value, error), trial_level
    return left, combined, level, effects


def _model_info(request, full: FullScene, magnitude, left, combined, level: Level, effects, probe, accuracy) -> dict:
    """The answer's model part (``model_part.model_at`` reads it): the left-out set as one entry,
    its measured combined impact, and what was measured on the way. For the Roman default (its
    scene, or one the request modified: preset "roman") the default's own parts are added, as its
    table and grid answers carry them (:func:`_roman_parts`)."""

    alone = {e["name"]: e["impact_alone"] for e in effects}
    roman = request.policy.quotes_default
    parts = _accuracy_parts(full, left, combined, roman)
    included = [{"name": n, "impact": alone.get(n)} for n in _removable(full.scene) if n not in left]
    combine, stated_against, model_basis, extra = "sum", "slope", None, {}
    if roman:
        own = _roman_parts(request, full)
        parts = own["left_out"] + parts
        included += own["included"]
        combine, stated_against, model_basis = own["combine"], own["stated_against"], own["basis"]
        extra = {k: own[k] for k in ("magnitude_offset",) if k in own}
        extra["accuracy_parts"] = {
            "level": "the fidelity level's measured error, in uncertainty_fidelity (as a table answer's level error is)",
            LEFT_OUT_PART: "the left-out set's measured impact, a shift with a fixed sign: added linearly to the "
            "default's parts in uncertainty_model (the rule's left-out effects)",
        }
    return {
        "accuracy": accuracy,
        "magnitude_measured_at": float(magnitude),
        "full_scene": _full_scene_info(full),
        "level": {"name": level.name, "error": level.error, "basis": level.basis},
        # Simulated effects, with the impact of removing each alone where the search measured it.
        "included": included,
        "left_out": parts,
        "left_out_impact": combined[0] or 0.0,
        "left_out_impact_uncertainty": combined[1] or 0.0,
        "measured": effects,
        "probe": None
        if probe is None
        else {"realizations": probe.base.realizations, "method": "linear response, same centroids", "runs": probe.runs},
        "stated_against": stated_against,
        "combine": combine,
        "basis": (
            "impacts measured inside the full scene (each effect removed from it, and the left-out set removed "
            "together); the left-out set's impact is that of the set, not a sum"
            if probe is not None
            else "the full scene is simulated at a level whose measured error meets the accuracy: nothing left out"
        )
        + ("" if model_basis is None else f". The Roman default's own parts: {model_basis}"),
        **extra,
    }


def _accuracy_parts(full: FullScene, left, combined, roman: bool) -> list[dict]:
    """The model part's entries the accuracy search itself states: the left-out set as one entry
    (``roman``: as the Roman default's parts name it), the position's spread where none is given,
    and a pupil rule other than the official one."""
    parts = []
    if left:
        parts.append(
            {
                "name": LEFT_OUT_PART if roman else " + ".join(left),
                "members": list(left),
                "impact": combined[0],
                "uncertainty": combined[1],
                "why": "left out: its impact measured as a set (all removed together) inside the full scene",
                **({"kind": "left_out", "measured_here": True} if roman else {}),
            }
        )
    if full.is_roman_default and full.scene.position is None:
        parts.append(
            {
                "name": "position",
                "impact": None,
                "why": "no position given: the answer is for the SCA centre (the range over the SCA is not an accuracy part)",
            }
        )
    if full.pupil_scale != "official" and not roman:
        parts.append(
            {
                "name": "pupil_scale",
                "impact": None,
                "why": f"pupil-mask scale rule {full.pupil_scale!r}, not the official clear area: not measured here",
            }
        )
    return parts


def _full_scene_info(full: FullScene) -> dict:
    """What the full scene an accuracy answer simulates is, as its model part quotes it."""
    return {
        "source": full.source,
        "scene": full.scene.to_dict(),
        "description": full.scene.describe(),
        "linearise_at": full.linearise_at,
        "residual_nl": full.residual_nl,
        "pupil_scale": full.pupil_scale,
        "ramp": None if full.ramp is None else full.ramp.conditions(full.exptime),
    }


def _roman_parts(request, full: FullScene) -> dict:
    """The Roman default's parts for this answer (``model_part.roman_default_model``, the one reader
    of ``nlpsf/data/roman_model_uncertainty.json``): what the full scene itself does not know."""
    from . import model_part

    return model_part.roman_default_model(
        request.band, request.sca, request.metric, request.mode, full.scene, pupil_scale=full.pupil_scale, request=request
    )
