"""A solve request: every input of ``nlpsf.solve.solver``, validated once, frozen.

:class:`SolveRequest` is what the CLI, the API, the batch and the page's endpoint build (through
:meth:`SolveRequest.from_mapping`, which names the field at fault in its ``InputError``); the
solver trusts it. It checks the inputs in the order the solver always has, so the first error a
bad request meets is the same whichever entry point it came through.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from functools import lru_cache
from typing import Any

from nlpsf import defaults, roman
from nlpsf.checks import (
    InputError,
    check_beta0,
    check_choice,
    check_exptime,
    check_full_well,
    check_integer,
    check_magnitude,
    check_number,
)
from nlpsf.frozen import replaced
from nlpsf.sim import levels, ramps

from . import shear

#: Stars (and dithers) a scatter-mode PSF model may average.
MAX_STARS = 10**9
#: The fields of a request (API body, batch row) that describe its ramp (``ramps.build`` reads them).
RAMP_REQUEST_FIELDS: tuple[str, ...] = (
    "ramp", "ma_table", "ramp_fit", "read_noise", "ramp_saturation", "ramp_single_resultant",
)  # fmt: skip
#: The ramp's rules among them, as ``ramps.build``'s arguments (absent: its defaults, romancal's).
RAMP_RULE_FIELDS: dict[str, str] = {"ramp_saturation": "saturation", "ramp_single_resultant": "single_resultant"}
#: The three quantities of the relation, of which a request gives exactly two.
TRIPLE: tuple[str, ...] = ("precision", "tolerance", "magnitude")


def _scene_type():
    from nlpsf.sim.scene import SceneModel  # the scene module is heavy; only a scene request needs it

    return SceneModel


@dataclass(frozen=True)
class SolveRequest:
    """Two of (precision, tolerance, magnitude) and the conditions; see ``nlpsf.solve.solver.solve``."""

    band: str
    sca: int = defaults.SCA
    metric: str = "size"
    mode: str = "bias"
    beta0: float = defaults.BETA0
    #: None: the preset's (roman: the HLWAS table's last read, 139.1 s; paper: 168.1 s).
    exptime: float | None = None
    precision: float | None = None
    tolerance: float | None = None
    magnitude: float | None = None
    full_well: float = defaults.FULL_WELL_E
    fidelity: str | None = None
    accuracy: float | None = None
    shear_m: float | None = None
    shear_c: float | None = None
    size_ratio: Any = None
    stars: int = 1
    ramp: ramps.Ramp | None = None
    throughput: str | None = None
    #: The scene: None (the Roman default), a preset's name (``roman_default.PRESETS``: "roman",
    #: "paper", "galsim-roman") or a ``scene.SceneModel`` (its effects as given).
    scene: Any = None
    pupil_scale: str | None = None
    #: Where the slope is taken (``experiment.LINEARISE_STATES``); None: the preset's (roman
    #: "corrected", paper "beta0").
    linearise_at: str | None = None
    #: The preset whose readout, exposure, pupil rule and state fill what the request leaves unset
    #: (``roman_default.fill``); None: the scene's name when it names one, else "roman".
    preset: str | None = None
    #: How the calibration error acts in the corrected state (``experiment.correction.RESIDUAL_MODELS``):
    #: None, the default model ("per_resultant_correction"; a field-grid answer says which model its grid
    #: holds); "per_read_beta", the earlier model. Only with ``linearise_at`` "corrected".
    residual_nl: str | None = None
    #: The shear budget (``shear_m`` / ``shear_c`` with ``size_ratio``) and the size ratio, checked.
    budget: shear.Budget | None = field(default=None, init=False, compare=False, repr=False)
    ratio: shear.SizeRatio | None = field(default=None, init=False, compare=False, repr=False)
    budget_tolerance: float | None = field(default=None, init=False, compare=False, repr=False)

    def __post_init__(self) -> None:
        self._set("band", roman.check_band(self.band))
        self._set("sca", roman.check_sca(self.sca))
        self._fill_preset()
        check_choice(self.metric, "metric", defaults.METRICS)
        check_choice(self.mode, "mode", defaults.MODES)
        self._set("beta0", check_beta0(self.beta0))
        self._set("exptime", check_exptime(self.exptime))
        self._set("full_well", check_full_well(self.full_well))
        self._set("stars", check_integer(self.stars, "stars", 1, MAX_STARS))
        if self.stars > 1 and self.mode != "scatter":
            raise InputError(
                "stars",
                "averaging over stars applies to scatter mode only: a bias in the mean beta is common to every star, "
                "so a PSF model averaging n stars has the same bias error as one",
            )
        self._check_budget()
        if self.ramp is not None:
            if not isinstance(self.ramp, ramps.Ramp):
                raise InputError("ramp", f"must be a ramps.Ramp, got {type(self.ramp).__name__}")
            self.ramp.check_exposure(self.exptime)
            self.ramp.check_saturates(self.full_well, self.beta0)
        self._check_triple()
        if self.accuracy is None:
            levels.check_level(self.fidelity or "table")
        else:
            self._set("accuracy", check_number(self.accuracy, "accuracy", *defaults.ACCURACY_RANGE))
        if self.throughput is not None:
            roman.check_throughput(self.throughput)
        if self.pupil_scale is not None:
            check_choice(self.pupil_scale, "pupil_scale", roman.PUPIL_SCALE_RULES)
        if self.scene is not None and self.ramp is not None:
            ramps.check_scene(self.scene)  # the one rule of what a ramp combines with (brighter-fatter: not yet)

    def _set(self, name: str, value) -> None:
        object.__setattr__(self, name, value)

    def _fill_preset(self) -> None:
        """The scene choice, validated once: the preset's readout, exposure, pupil rule, state and
        (for the Roman default) scene and background wherever the request leaves them unset."""
        from . import presets as roman_default

        scene, preset = self.scene, self.preset
        if isinstance(scene, str):
            scene = roman_default.check_preset(scene)
            if preset is not None and roman_default.check_preset(preset) != scene:
                raise InputError("scene", f"scene {scene!r} and preset {preset!r} disagree; give one")
            preset, scene = scene, None
        elif preset is None:
            name = getattr(scene, "name", None)
            preset = name if name in roman_default.PRESETS else roman_default.NAME
        preset = roman_default.check_preset(preset)
        if scene is not None and not isinstance(scene, _scene_type()):
            raise InputError("scene", "must be a preset's name or a scene description (nlpsf.sim.scene.SceneModel)")
        if self.linearise_at is not None:
            from nlpsf.sim.experiment.config import LINEARISE_STATES  # only when one is given: the simulator is heavy

            check_choice(self.linearise_at, "linearise_at", LINEARISE_STATES)
        if self.ramp is not None and not isinstance(self.ramp, ramps.Ramp):
            raise InputError("ramp", f"must be a ramps.Ramp, got {type(self.ramp).__name__}")
        if self.exptime is not None:
            self._set("exptime", check_exptime(self.exptime))
        filled = roman_default.fill(preset, self.band, self.sca, self.exptime, self.ramp, self.pupil_scale, self.linearise_at)
        if preset == roman_default.NAME and (scene is None or (scene.name == roman_default.NAME and not scene.background_e)):
            # The default's scene (or its preset, at a position, with what the caller changed) with the sky
            # over this exposure: a change the caller made to the default's scene is kept, as the CLI keeps it.
            scene = (
                roman_default.scene(None, filled.background_e)
                if scene is None
                else replace(scene, background_e=filled.background_e)
            )
        elif scene is None and preset == "galsim-roman":
            scene = roman_default.preset_scene(preset)
        elif preset == "paper" and scene is not None and scene.no_effects:
            scene = None  # the paper's scene is the solver's plain path (today's answers, bit for bit)
        self._set("preset", preset)
        self._set("scene", scene)
        self._set("exptime", filled.exptime)
        self._set("ramp", filled.ramp)
        self._set("pupil_scale", filled.pupil_scale)
        self._set("linearise_at", filled.linearise_at)
        if self.residual_nl is not None:
            from nlpsf.sim.experiment.correction import RESIDUAL_MODELS

            check_choice(self.residual_nl, "residual_nl", RESIDUAL_MODELS)
            if self.linearise_at != "corrected":
                raise InputError(
                    "residual_nl",
                    f"the residual model applies to the corrected state; this request is linearised at {self.linearise_at}",
                )

    @property
    def residual_model(self) -> str | None:
        """The residual model fresh simulations use: the one given, else the default's in the corrected
        state (None at beta0)."""
        if self.linearise_at != "corrected":
            return None
        if self.residual_nl is not None:
            return self.residual_nl
        from . import presets as roman_default

        return roman_default.RESIDUAL_NL

    def _check_budget(self) -> None:
        if self.shear_m is not None or self.shear_c is not None:
            if self.tolerance is not None:
                raise InputError(
                    "tolerance",
                    "give the tolerance or a shear budget (shear_m / shear_c), not both: the budget sets the tolerance",
                )
            budget = shear.budget_for(self.metric, self.shear_m, self.shear_c, self.size_ratio)
            # e.g. a tiny budget on tiny galaxies
            self._set("budget_tolerance", check_number(budget.tolerance, f"shear_{budget.kind}", *defaults.TOLERANCE_RANGE))
            self._set("budget", budget)
            self._set("ratio", budget.size_ratio)
        elif self.size_ratio is not None:
            self._set("ratio", shear.check_size_ratio(self.size_ratio))

    def _check_triple(self) -> None:
        values = {"precision": self.precision, "tolerance": self.target_tolerance, "magnitude": self.magnitude}
        given = [k for k in TRIPLE if values[k] is not None]
        if len(given) != 2:
            missing = ", ".join(k for k in TRIPLE if k not in given) or "none"
            at_fault = next((k for k in TRIPLE if k not in given), "magnitude")
            if self.budget is not None and (at_fault == "tolerance" or len(given) == 3):
                at_fault = f"shear_{self.budget.kind}"
            raise InputError(
                at_fault,
                f"give exactly two of precision, tolerance (or a shear budget), magnitude (got {len(given)}; missing: {missing})",
            )
        if self.precision is not None:
            self._set("precision", check_number(self.precision, "precision", *defaults.PRECISION_RANGE))
        if self.tolerance is not None:
            self._set("tolerance", check_number(self.tolerance, "tolerance", *defaults.TOLERANCE_RANGE))
        if self.magnitude is not None:
            self._set("magnitude", check_magnitude(self.magnitude))

    @property
    def policy(self):
        """What the request's preset means for its answer (``presets.Policy``)."""
        from . import presets

        return presets.POLICIES[self.preset]

    @property
    def target_tolerance(self) -> float | None:
        """The tolerance given, or the one the shear budget sets."""
        return self.budget_tolerance if self.budget is not None else self.tolerance

    @property
    def solved_for(self) -> str:
        values = {"precision": self.precision, "tolerance": self.target_tolerance, "magnitude": self.magnitude}
        return next(k for k in TRIPLE if values[k] is None)

    def conditions_key(self) -> tuple:
        """Every field but the relation's numbers and the shear budget, which no plan reads, and the
        scene's name (scenes compare without it; the answer states it): requests with equal keys have
        the same plan wherever the magnitude's place is not asked (``solver.plan(...,
        fresh_between_limits=False)``). Raises TypeError where a field is unhashable."""
        key = (*[getattr(self, name) for name in _CONDITION_FIELDS], getattr(self.scene, "name", None))
        hash(key)
        return key

    def with_changes(self, **changes) -> SolveRequest:
        """Another request, validated again (``dataclasses.replace``)."""
        return replace(self, **changes)

    def at_position(self, position) -> SolveRequest:
        """This request for the same star at another ``position`` of its SCA (pixels): its scene
        moved there, nothing else read again (the position is checked by the scene)."""
        try:
            scene = _scene_at(self.scene, tuple(position))
        except TypeError:  # a scene holding something unhashable: moved afresh
            scene = replace(self.scene, position=position)
        return replaced(self, scene=scene)

    def table_pass(self) -> SolveRequest:
        """This request on the paper's tables (no ramp, scene, other pupil rule or state): the cheap
        first pass that finds where a magnitude answer lies."""
        return replace(
            self, fidelity="table", accuracy=None, ramp=None, scene="paper", preset="paper", pupil_scale=None,
            linearise_at=None, residual_nl=None,
        )  # fmt: skip

    @classmethod
    def from_mapping(cls, data: Mapping[str, Any]) -> SolveRequest:
        """The request from a mapping of ``solver.solve``'s keyword arguments (the CLI's options,
        an API body, a batch row); an unknown key is an ``InputError`` naming it."""
        known = {f.name for f in fields(cls) if f.init}
        for key in data:
            if key not in known:
                raise InputError(str(key), f"unknown field; a solve request takes {', '.join(sorted(known))}")
        if "band" not in data:
            raise InputError("band", "missing")
        return cls(**dict(data))

    @classmethod
    def from_json(cls, data: Mapping[str, Any], allow_files: bool = False) -> SolveRequest:
        """The request from a JSON-shaped body (the API's, the page's, a batch row's): the fields of
        :meth:`from_mapping` with the ramp as :data:`RAMP_REQUEST_FIELDS` (``ramps.build``: an MA
        table's exposure is its last read unless ``exptime`` is given) and the scene as its JSON
        object (``scene.from_request``; errors name ``scene.FIELD``). Files only with ``allow_files``."""
        from . import presets as roman_default

        data = dict(data)
        scene = data.pop("scene", None)
        preset = _preset_of(scene, data.get("preset"))
        data["preset"] = preset
        ramp_fields = {k: data.pop(k, None) for k in RAMP_REQUEST_FIELDS}
        given_exptime = data.get("exptime")
        sca = data.get("sca", defaults.SCA)
        changes_readout = any(ramp_fields[k] is not None for k in ("ramp_fit", "read_noise", *RAMP_RULE_FIELDS))
        if preset == roman_default.NAME and ramp_fields["ramp"] is None and ramp_fields["ma_table"] is None and changes_readout:
            # A fit, read noise or rule alone changes the default's own readout (its MA table), as a simulation's does.
            ramp_fields["ma_table"] = roman_default.MA_TABLE
        if ramp_fields["ramp"] is not None or ramp_fields["ma_table"] is not None or preset != roman_default.NAME:
            # A ramp given replaces the preset's readout; the Roman default's fit is romancal's likelihood fit.
            default_fit = roman_default.RAMP_FIT if preset == roman_default.NAME else "ols"
            ramp, exptime = ramps.build(
                ramp_fields["ramp"],
                ramp_fields["ma_table"],
                ramp_fields["ramp_fit"] or default_fit,
                ramp_fields["read_noise"],
                given_exptime,
                allow_files=allow_files,
                sca=sca,
                **{rule: ramp_fields[name] for name, rule in RAMP_RULE_FIELDS.items() if ramp_fields[name] is not None},
            )
            data["exptime"], data["ramp"] = exptime, ramp
        if isinstance(scene, Mapping) and scene:
            sky_of = None
            if roman_default.policy(preset).sky:
                # The caller's changes change the default's scene with its sky over this request's
                # exposure: a background left out is that sky, one given (0 too) is the caller's.
                # The band and SCA are checked where the request is made (below); the sky, kept by them,
                # checks values it has not met (one of another type is refused here, before it is looked up).
                if "band" not in data:
                    raise InputError("band", "missing")
                band = data["band"] if type(data["band"]) is str else roman.check_band(data["band"])
                sky_of = (band, sca if type(sca) is int else roman.check_sca(sca), data.get("exptime"), data.get("ramp"))
            data["scene"] = scene_from_json(scene, preset, sky_of)
        elif isinstance(scene, Mapping) or scene is None or isinstance(scene, str):
            data["scene"] = None if isinstance(scene, Mapping) else scene
        else:
            data["scene"] = scene
        return cls.from_mapping(data)


#: The request's conditions (:meth:`SolveRequest.conditions_key`): a field added to the request is one
#: unless it is named here.
_CONDITION_FIELDS: tuple[str, ...] = tuple(
    f.name for f in fields(SolveRequest) if f.compare and f.name not in (*TRIPLE, "shear_m", "shear_c", "size_ratio")
)


def _scene_at(scene, position: tuple) -> Any:
    """``scene`` moved to ``position`` (checked there), kept: an SCA range moves one scene to each of
    its nodes. Kept by the scene's name too: scenes compare without it (a named preset and the same
    values given by hand are equal), and the moved scene states it."""
    return _named_scene_at(scene, getattr(scene, "name", None), position)


@lru_cache(maxsize=4096)
def _named_scene_at(scene, name: str | None, position: tuple) -> Any:
    return scene.at(position) if isinstance(scene, _scene_type()) else replace(scene, position=position)


def _preset_of(scene, preset: str | None) -> str:
    """The preset a JSON request builds on: the scene's name or its ``preset`` key, else the default."""
    from . import presets as roman_default

    named = scene if isinstance(scene, str) else scene.get("preset") if isinstance(scene, Mapping) else None
    if named is not None and preset is not None and roman_default.check_preset(named) != roman_default.check_preset(preset):
        raise InputError("scene", f"scene preset {named!r} and preset {preset!r} disagree; give one")
    return roman_default.check_preset(named or preset or roman_default.NAME)


def scene_from_json(fields_: Mapping[str, Any] | None, preset: str | None = None, sky_of: tuple | None = None):
    """The scene a request's JSON ``scene`` object describes, the one reading of it (a solve's, a
    simulation's, an impact report's): its fields over its preset's scene effects -- ``preset``, else
    the object's own ``preset`` key; neither, the scene model's defaults; errors name ``scene.FIELD``.
    ``sky_of``: (band, sca, exptime, ramp), whose sky (a preset that has one: ``presets.sky_base``) is
    in the base, so that a background left out is that sky and one given (0 too) the caller's."""
    from nlpsf.sim import scene as scenes

    from . import presets as roman_default

    data = dict(fields_ or {})
    named = data.pop("preset", None) if preset is None else preset
    data.pop("preset", None)
    if named is None:
        base = None
    else:
        base = roman_default.preset_base(named) if sky_of is None else roman_default.sky_base(named, *sky_of)
    try:
        return scenes.from_request(data, base=base)
    except InputError as error:
        raise InputError(f"scene.{error.argument}" if error.argument != "scene" else "scene", error.reason) from None
