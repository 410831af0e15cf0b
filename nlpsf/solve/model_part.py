"""The model part of an answer: what a solve leaves out of a Roman scene, and what that adds to
its uncertainty.

With ``accuracy`` the full scene is simulated, or a set of effects whose combined impact is
measured within the accuracy is left out (``nlpsf.solve.accuracy.select``, which builds the model
part); otherwise what is left out is read from the shipped measurement (:func:`shipped_model`).
:func:`model_at` states the parts relative to the answer's slope. ``slopes`` arguments are the
solver's c(m) at the request (``band``, ``metric``, ``mode``, ``table``, ``exptime``, ``table_beta0``).
"""

from __future__ import annotations

import math
import threading
from dataclasses import replace
from enum import StrEnum

import numpy as np

from nlpsf import roman
from nlpsf.slopes import fidelity as levels
from nlpsf.slopes import tables

from . import roman_uncertainty as roman_parts


class Rule(StrEnum):
    """How an answer's model parts add up: its model part's ``combine`` (the value answers carry)."""

    #: Measured at the point, each below the accuracy asked for (:data:`COMBINE`).
    QUADRATURE = "quadrature"
    #: The shipped worst cases of the paper scene's measurement, added up (:data:`COMBINE`).
    SUM = "sum"
    #: The Roman default's parts, read at the magnitude and combined by ``roman_uncertainty.combine``.
    ROMAN_PARTS = "roman"


#: The model part's two relative pieces (see :func:`model_at`).
MODEL_PARTS = ("effects_relative", "pupil_scale_relative")
COMBINATION = (
    "uncertainty_model = hypot(effects left out, pupil-scale rule); the total adds the effects left out in "
    "quadrature with the statistical and fidelity parts and with the larger of the pupil-scale rule and "
    "uncertainty_optical_model, which both measure the optical model's distance from Roman's (not both)"
)
#: How the effects left out add up: measured at the point (each below the accuracy asked for) in
#: quadrature; from the shipped worst cases as a plain sum, because every Roman star has them all at
#: once with signs fixed by the optics, often alike (scripts/model_uncertainty.py).
COMBINE = {"quadrature": lambda values: math.sqrt(math.fsum(v * v for v in values)), "sum": math.fsum}


def shipped_model(
    band: str,
    sca: int,
    metric: str,
    mode: str,
    scene,
    fidelity: str,
    *,
    default: str = "paper",
    pupil_scale: str | None = None,
    request=None,
) -> dict:
    """The model part of an answer without ``accuracy``, from a shipped measurement.

    ``default``: the measurement the request's preset reads (``presets.Policy.measured_as``,
    :data:`SHIPPED`): "roman", the Roman default's parts (:func:`roman_default_model`,
    ``nlpsf/data/roman_model_uncertainty.json``); "paper" (the paper scene, unchanged): what the
    paper's scene leaves out (:func:`paper_scene_model`). ``pupil_scale``: the rule the answer uses
    (None: the library's default), which the pupil part's label names. ``request`` (the Roman
    default's only): where it differs from the conditions its parts were measured at."""
    reader = SHIPPED.get(default)
    if reader is None:
        raise ValueError(f"default must be one of {', '.join(map(repr, SHIPPED))}, got {default!r}")
    return reader(band, sca, metric, mode, scene, fidelity, pupil_scale=pupil_scale, request=request)


def paper_scene_model(
    band: str, sca: int, metric: str, mode: str, scene, fidelity: str, *, pupil_scale=None, request=None
) -> dict:
    """What the paper's scene leaves out (``scene.shipped_model_uncertainty``). Effects the scene (or
    the polychromatic level's flat-f_nu band integration) simulates are not left out; the position's
    spread over the SCA is left out unless a position is given. An SCA the measurement covers reads
    its own values, any other the worst over those it covers. ``request`` is not read."""
    from nlpsf import defaults
    from nlpsf.sim import scene as scenes

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
    used = pupil_scale or defaults.PUPIL_SCALE
    why = (
        "pupil-mask scale rule: galsim (used) vs header"
        if used == "galsim"
        else f"pupil-mask scale rule: {used} used; the part measured is header vs galsim (scripts/model_uncertainty.py)"
    )
    parts.append({"name": "pupil_scale", "impact": entry["pupil_scale"], "why": why})
    return {
        "included": [{"name": name, "impact": None} for name in scenes.EFFECTS if on[name]],
        "left_out": parts,
        "stated_against": "modulus" if metric in ("e1", "e2") else "slope",
        "combine": Rule.SUM,
        "basis": (
            f"shipped measurement ({conditions['script']}, {conditions['measured_utc']}): each effect's worst |impact| on "
            f"the {mode} slope at its nominal Roman value on {where}, at m = {conditions['magnitudes']} "
            f"({conditions['method']}), added up (a Roman star has them all at once, with signs often alike)"
        ),
    }


def model_at(info: dict, slopes, magnitude: float) -> dict:
    """The model part at the answer's magnitude: impacts relative to this metric's slope, and the
    relative uncertainty of the effects left out and of the pupil-scale rule (:data:`MODEL_PARTS`).

    A shipped e1 / e2 impact is stated against |c_e| and scaled here by |c_e| / |c_ei|, as the
    optical model's part is. The Roman default's parts (:attr:`Rule.ROMAN_PARTS`) are read at the
    magnitude (``roman_uncertainty.at_magnitude``) and combined by its rule; the optical model's
    vintage and the pupil rule are among them, so ``effects_relative`` holds the whole model part,
    ``pupil_scale_relative`` is 0 and ``optical_model_included`` tells the caller not to add
    ``optical_model_relative`` again."""
    if info["combine"] == Rule.ROMAN_PARTS:
        # The default's e1 / e2 parts are restated with the answer's own slopes (the grid's or the
        # simulation's), not the paper tables': their ratio |c_e| / |c_ei| differs by up to x3.5.
        own = None
        if info["stated_against"] == "modulus" and hasattr(slopes, "modulus_over_component"):
            own = slopes.modulus_over_component(magnitude)
        scale = own if own is not None else component_scale(slopes, magnitude) if info["stated_against"] == "modulus" else 1.0
        out = _roman_model_at(info, magnitude, scale)
        if info["stated_against"] == "modulus":
            out["component_scale_from"] = "the answer's own slopes" if own is not None else "the tables"
        return out
    scale = component_scale(slopes, magnitude) if info["stated_against"] == "modulus" else 1.0
    left = [{**p, "impact": None if p["impact"] is None else p["impact"] * scale} for p in info["left_out"]]
    effects = COMBINE[info["combine"]]([abs(p["impact"]) for p in left if p["impact"] is not None and p["name"] != "pupil_scale"])
    pupil = next((abs(p["impact"]) for p in left if p["name"] == "pupil_scale" and p["impact"] is not None), 0.0)
    out = {**info, "left_out": left, "stated_against": "slope", "effects_relative": effects, "pupil_scale_relative": pupil}
    out.update(relative_uncertainty=math.hypot(effects, pupil), combination=COMBINATION)
    if scale != 1.0:
        out["component_scale"] = scale
    return out


def with_effect(target, source, name: str):
    """``target`` with effect ``name`` set as in ``source`` (the fields of ``scene.REGISTRY[name]``)."""
    from nlpsf.sim.scene import REGISTRY

    return replace(target, **{f: getattr(source, f) for f in REGISTRY[name].fields})


def optical_model_relative(slopes, magnitude: float | None, model_info: dict | None = None) -> float:
    """Relative slope uncertainty from the optical model (``roman.optical_model_uncertainty``).

    For one ellipticity component it is stated against |c_e|, so it grows as |c_e| / |c_ei|.
    Zero when ``model_info`` (:func:`model_at`'s) already holds the optical model's part (the Roman
    default's vintage part)."""
    if model_info is not None and model_info.get("optical_model_included"):
        return 0.0
    relative = roman.optical_model_uncertainty(slopes.band, slopes.metric)
    if "relabelled_from" in slopes.table.settings:
        relative = math.hypot(relative, tables.RELABEL_ERROR[slopes.band][0 if slopes.metric == "size" else 1])
    return relative * component_scale(slopes, magnitude)


def component_scale(slopes, magnitude: float | None) -> float:
    """|c_e| / |c_ei| at ``magnitude`` for an e1 / e2 answer (1 otherwise): restates a part given
    against the modulus of the ellipticity slope against the component's own slope."""
    if slopes.metric not in ("e1", "e2") or magnitude is None:
        return 1.0
    modulus, _, _ = slopes.table.slope("e", slopes.mode, magnitude, slopes.exptime, slopes.table_beta0)
    component, _, _ = slopes.table.slope(slopes.metric, slopes.mode, magnitude, slopes.exptime, slopes.table_beta0)
    if np.isfinite(modulus[0]) and abs(component[0]) > 0:
        return float(modulus[0] / abs(component[0]))
    return 1.0


#: Scene fields a request may set that decide a Roman-default part or range: when the request's
#: value differs from the default's, the star is the user's and that spread is not the default's.
_CHOSEN_BY_REQUEST = {
    "sed": "sed",
    "jitter": "jitter_arcsec",
    "charge_diffusion": "charge_diffusion_px",
}
#: What a part the request sets no longer means (it is dropped, with this reason).
_SET_BY_REQUEST_WHY = {
    "sed": "the default's SED range (3500-10000 K blackbodies against its K0V) is not the range of the SED the request gives",
    "jitter": "the default's jitter uncertainty (6 +- 0.86 mas) is not the uncertainty of the jitter the request gives",
    "charge_diffusion": (
        "the default's diffusion uncertainty (0.332 +- 0.011 px) is not the uncertainty of the diffusion the request gives"
    ),
}


def roman_default_model(band: str, sca: int, metric: str, mode: str, scene, pupil_scale: str | None = None, request=None) -> dict:
    """:func:`_roman_default_model`, built once for each set of what decides it and kept: each call
    gets its own dicts and lists of parts, whose rows (``by_magnitude``, ``ends``) are shared and
    read-only (the parts' look-ups, ``roman_uncertainty.at_magnitude``, keep their sorted rows by them)."""
    from nlpsf.request import presets as roman_default

    defaults_scene = roman_default.base_scene()
    chosen = tuple(
        scene is not None and getattr(scene, field) != getattr(defaults_scene, field) for field in _CHOSEN_BY_REQUEST.values()
    )
    simulated = scene is not None and (scene.bfe_coefficient != 0, any(c != 0 for c in scene.nl_coefficients))
    differences = None if request is None else roman_measurement_differences(request)
    measured = None if differences is None else (tuple(differences[0]), differences[1])
    key = (band, sca, metric, mode, pupil_scale, chosen, simulated, measured)
    with _ROMAN_MODELS_LOCK:
        built = _ROMAN_MODELS.get(key)
    if built is None:
        built = _roman_default_model(band, sca, metric, mode, scene, pupil_scale, differences)
        with _ROMAN_MODELS_LOCK:
            if len(_ROMAN_MODELS) >= 4096:
                _ROMAN_MODELS.clear()
            _ROMAN_MODELS[key] = built
    return own_copy(built)


def own_copy(info: dict) -> dict:
    """A model part of an answer, its own dicts and lists of parts (a kept one is shared by the answers
    that read it; its parts' rows, ``by_magnitude`` and ``ends``, stay shared and read-only)."""
    out = dict(info)
    for name in ("included", "left_out"):
        if name in out:
            out[name] = [dict(part) for part in out[name]]
    if "ranges" in out:
        out["ranges"] = {name: dict(shipped) for name, shipped in out["ranges"].items()}
    return out


#: The Roman default's model parts by what decides them (:func:`roman_default_model`).
_ROMAN_MODELS: dict[tuple, dict] = {}
_ROMAN_MODELS_LOCK = threading.Lock()


def _roman_default_model(
    band: str, sca: int, metric: str, mode: str, scene, pupil_scale: str | None, differences: tuple[list[str], float] | None
) -> dict:
    """The Roman default's model part: its parts (``nlpsf.solve.roman_uncertainty``) for this band, SCA,
    mode and metric, each by name with its value over the measured magnitudes, and the star-to-star
    ranges (the SED's) beside them.

    A part the request fixes (its own jitter or diffusion) or simulates (brighter-fatter, an NL
    polynomial) is dropped, with the reason in ``included``; a request's own SED drops the SED range.
    ``pupil_scale``: the rule the answer uses; the optics part is the jointly fitted optics' distance
    from the official rule's PSF, so another rule moves that distance by its own log scale (read
    from the shipped pupil scales). ``request`` (a ``SolveRequest``): where its readout, exposure,
    beta0, full well or state differ from those the parts were measured at
    (``differences``: :func:`roman_measurement_differences` of it), the basis says so and the parts are read at the
    magnitude of equal charge in the measured exposure."""
    from nlpsf.request import presets as roman_default

    defaults_scene = roman_default.base_scene()
    entry, where = roman_parts.entry(band, sca, mode, metric)
    data = roman_parts.shipped()
    conditions = data["conditions"]
    parts, included = [], []

    def chosen(name: str) -> bool:
        field = _CHOSEN_BY_REQUEST.get(name)
        return scene is not None and field is not None and getattr(scene, field) != getattr(defaults_scene, field)

    for part in roman_parts.PARTS:
        shipped = entry["parts"][part.name]
        simulated = scene is not None and (
            (part.name == "brighter_fatter" and scene.bfe_coefficient != 0)
            or (part.name == "nl_shape" and any(c != 0 for c in scene.nl_coefficients))
        )
        if chosen(part.name) or simulated:
            why = f"set by the request: {_SET_BY_REQUEST_WHY[part.name]}" if chosen(part.name) else "simulated"
            included.append({"name": part.name, "impact": None, "why": why})
            continue
        row = {
            "name": part.name,
            "kind": part.kind,
            "impact": shipped["value"],
            "by_magnitude": [[r[0], r[1]] for r in shipped["by_magnitude"]],
            "why": shipped.get("why", part.measured_as),
            "source": part.source,
        }
        if part.name == "optics" and pupil_scale not in (None, roman_default.PUPIL_SCALE):
            row.update(_optics_for_rule(band, sca, entry, pupil_scale))
        parts.append(row)
    ranges = {}
    for name in roman_parts.RANGES:
        if chosen(name):
            included.append({"name": name, "impact": None, "why": f"set by the request: {_SET_BY_REQUEST_WHY[name]}"})
            continue
        shipped = entry["ranges"][name]
        ranges[name] = {"ends": list(shipped["ends"]), "by_magnitude": [list(r) for r in shipped["by_magnitude"]]}
    differences, offset = ([], 0.0) if differences is None else differences
    basis = (
        f"shipped measurement of the Roman default's parts ({conditions['script']}, {conditions['measured_utc']}, "
        f"code {conditions['code_version']}) on {where}, SCA centre, m = {conditions['magnitudes']}, "
        f"{conditions['method']}; combined: {roman_parts.COMBINATION}"
    )
    if differences:
        basis += (
            f". Measured at the default's readout, exposure, beta0, full well and state; this request differs in "
            f"{'; '.join(differences)}: the parts are the default's, not measured again"
        )
        if offset:
            basis += f", read at the magnitude whose charge in the measured exposure is this star's (m {offset:+.3f})"
    out = {
        "included": included,
        "left_out": parts,
        "ranges": ranges,
        "stated_against": "modulus" if metric in ("e1", "e2") else "slope",
        "combine": Rule.ROMAN_PARTS,
        "basis": basis,
    }
    if offset:
        out["magnitude_offset"] = offset
    return out


#: The shipped measurements a model part is read from, by name (``presets.Policy.measured_as``).
SHIPPED = {
    "paper": paper_scene_model,
    "roman": lambda band, sca, metric, mode, scene, fidelity, *, pupil_scale=None, request=None: roman_default_model(
        band, sca, metric, mode, scene, pupil_scale=pupil_scale, request=request
    ),
}


def _optics_for_rule(band: str, sca: int, entry: dict, rule: str) -> dict:
    """The optics part of an answer whose pupil rule is not the official one: the jointly fitted
    optics less the rule's own log scale, through the same sensitivities."""
    data = roman_parts.shipped()
    scales = data.get("pupil_log_scale", {}).get(f"{band} {sca}", {})
    if rule not in scales:
        return {
            "impact": None,
            "by_magnitude": [[r[0], None] for r in entry["parts"]["optics"]["by_magnitude"]],
            "why": f"not measured: this answer uses the {rule} rule, whose pupil scale on {band} SCA {sca} is not shipped",
        }
    fit = data["optics_fit"][band]
    rows = []
    for m, sv, ss in entry["optics_sensitivity"]:
        if sv is None or ss is None:
            rows.append([m, None])
            continue
        value, offset = roman_parts.optics_value(fit, np.array([sv, ss]), scales[rule])
        rows.append([m, math.copysign(float(value), float(offset))])
    values = [r[1] for r in rows if r[1] is not None]
    return {
        "impact": max(values, key=abs) if values else None,
        "by_magnitude": rows,
        "why": f"this answer uses the {rule} rule (ln s = {scales[rule]:+.4f} from the official one): the jointly fitted "
        "optics' distance from this rule's PSF, with the fit's covariance",
    }


def roman_measurement_differences(request) -> tuple[list[str], float]:
    """(how ``request`` differs from the conditions the Roman default's parts were measured at, the
    magnitude offset to the star of equal charge in the measured exposure): the default's readout
    and exposure at the request's band and SCA, ``defaults.BETA0``, ``defaults.FULL_WELL_E``, the
    corrected state (``scripts/model_uncertainty_roman.py``)."""
    import math

    from nlpsf import defaults
    from nlpsf.request import presets as roman_default

    measured = roman_default.default_fill(request.band, request.sca)
    out = []
    if not math.isclose(request.exptime, measured.exptime, rel_tol=1e-9):
        out.append(f"exposure {request.exptime:g} s (measured at {measured.exptime:g} s)")
    if request.ramp != measured.ramp:
        out.append("readout (measured with the default's HLWAS ramp)")
    if not math.isclose(request.beta0, defaults.BETA0, rel_tol=1e-9):
        out.append(f"beta0 {request.beta0:g} (measured at {defaults.BETA0:g})")
    if not math.isclose(request.full_well, defaults.FULL_WELL_E, rel_tol=1e-9):
        out.append(f"full well {request.full_well:g} e- (measured at {defaults.FULL_WELL_E:g})")
    if request.linearise_at != measured.linearise_at:
        out.append(f"state {request.linearise_at} (measured at {measured.linearise_at})")
    offset = -2.5 * math.log10(request.exptime / measured.exptime)
    return out, (0.0 if abs(offset) < 1e-12 else offset)


def roman_effects_at(info: dict, magnitudes, scales) -> np.ndarray:
    """:func:`model_at`'s ``effects_relative`` of the Roman default's parts (``info["combine"]``
    :attr:`Rule.ROMAN_PARTS`) at many (magnitude, component scale) pairs at once -- an SCA's field-grid nodes, each
    at its own answer: each part read at every magnitude in one look-up
    (``roman_uncertainty.at_magnitudes``), scaled, and combined by ``roman_uncertainty.combine``'s
    rule with numpy's sums (``combine`` adds with ``math.fsum``: the two agree to the last bits)."""
    offset = info.get("magnitude_offset", 0.0)
    shifted = np.array([m + offset for m in magnitudes], dtype=np.float64)
    count = shifted.size
    layout = _effects_layout(info["left_out"])
    if layout is None:
        return np.zeros(count)  # parts named, not measured, count zero
    looked_rows, scaled, here, standard_rows, left_out_rows = layout
    # One magnitude at every node: each part looked up once (``at_magnitude``, the same neighbours).
    one = count and (shifted == shifted[0]).all()
    at = roman_parts.at_magnitudes_of(looked_rows, shifted[:1] if one else shifted)
    # Parts x nodes: each part's |value x the node's component scale| (a part measured at the point
    # is not scaled), NaN (nothing measured there) counting zero; the standard parts in quadrature,
    # the left-out shifts added, in the parts' order (numpy reduces axis 0 row after row).
    if here is None:
        read = np.abs(at * np.asarray(scales, dtype=np.float64)[None, :])
    else:
        values = np.empty((scaled.size, at.shape[1]))
        values[scaled] = at
        values[~scaled] = here[:, None]
        read = np.abs(np.where(scaled[:, None], values * np.asarray(scales, dtype=np.float64)[None, :], values))
    read[np.isnan(read)] = 0.0
    if read.shape != (scaled.size, count):  # the values measured at the point alone: one column for every node
        read = np.broadcast_to(read, (scaled.size, count))
    standard, left_out = read[standard_rows], read[left_out_rows]
    root = np.sqrt(np.add.reduce(standard * standard, axis=0)) if standard.size else np.zeros(count)
    return root + (np.add.reduce(left_out, axis=0) if left_out.size else np.zeros(count))


#: :func:`_effects_layout` by the parts' rows, measured flags, values and kinds (the rows kept with it).
_LAYOUTS: dict[tuple, tuple] = {}


def _effects_layout(parts: list[dict]) -> tuple | None:
    """What :func:`roman_effects_at` reads of the parts that count (measured by magnitude or at the
    point), built once for each such set: the looked-up parts' rows, which parts are scaled, the
    values measured at the point (None: none), and the standard and left-out parts' rows."""
    counted = [part for part in parts if part.get("measured_here") or "by_magnitude" in part]
    if not counted:
        return None
    kinds = tuple(part.get("kind", roman_parts.KINDS.get(part["name"], roman_parts.STANDARD)) for part in counted)
    here_values = tuple(
        (math.nan if part["impact"] is None else abs(part["impact"])) if part.get("measured_here") else None for part in counted
    )
    looked_rows = [part["by_magnitude"] for part in counted if not part.get("measured_here")]
    key = (tuple(id(rows) for rows in looked_rows), kinds, here_values)
    kept = _LAYOUTS.get(key)
    if kept is not None and all(a is b for a, b in zip(kept[0], looked_rows, strict=True)):
        return kept
    scaled = np.array([value is None for value in here_values])
    here = None if scaled.all() else np.array([value for value in here_values if value is not None])
    standard = np.array([kind != roman_parts.LEFT_OUT for kind in kinds])
    built = (looked_rows, scaled, here, np.flatnonzero(standard), np.flatnonzero(~standard))
    if len(_LAYOUTS) >= 4096:
        _LAYOUTS.clear()
    _LAYOUTS[key] = built
    return built


def _roman_model_at(info: dict, magnitude: float | None, scale: float) -> dict:
    """:func:`model_at` for the Roman default's parts: each read at ``magnitude`` (the larger of the
    measured magnitudes around it; shifted by ``magnitude_offset`` to the star of equal charge where
    the request's exposure is not the measured one), restated against this metric's slope, combined
    by the rule. A part measured at the answer's own point (``measured_here``: an ``accuracy``
    answer's left-out set) is already relative to this metric's slope and is read as measured."""
    left = []
    values: dict[str, float | None] = {}
    kinds: dict[str, str] = {}
    shifted = None if magnitude is None else magnitude + info.get("magnitude_offset", 0.0)
    for part in info["left_out"]:
        if part.get("measured_here"):
            value = None if part["impact"] is None else abs(part["impact"])
        elif "by_magnitude" in part:
            value = roman_parts.at_magnitude(part["by_magnitude"], shifted)
            value = None if value is None else value * scale
        else:
            value = None  # named, not measured (e.g. the position an accuracy answer stands in for)
        values[part["name"]] = value
        kinds[part["name"]] = part.get("kind", roman_parts.KINDS.get(part["name"], "choice"))
        left.append({**part, "impact": value if not part.get("measured_here") else part["impact"]})
    standard, shifts = roman_parts.split(values, kinds)
    relative = standard + shifts  # roman_parts.combine's sum, its two pieces found once
    out = {**info, "left_out": left, "stated_against": "slope", "effects_relative": relative, "pupil_scale_relative": 0.0}
    out.update(relative_uncertainty=relative, combination=roman_parts.COMBINATION, optical_model_included=True)
    out.update(standard_relative=standard, shifts_relative=shifts)
    out["ranges"] = _ranges_at(info.get("ranges", {}), shifted, scale)
    if scale != 1.0:
        out["component_scale"] = scale
    return out


def _ranges_at(ranges: dict, magnitude: float | None, scale: float) -> dict:
    """Each star-to-star range at ``magnitude``: the slope's relative change at its two ends
    (signed; e1 / e2 restated against the component's own slope by ``scale``), linear between the
    measured magnitudes (the ends' changes are smooth in m), the nearest outside them."""
    out = {}
    for name, shipped in ranges.items():
        rows = shipped["by_magnitude"]
        at = float(np.median([r[0] for r in rows])) if magnitude is None else magnitude
        ends = [float(roman_parts.at_signed(rows, np.array([at]), column)[0]) * scale for column in (1, 2)]
        out[name] = {
            "ends": list(shipped["ends"]),
            "relative_slope_change": ends,
            "unit": "relative change of this answer's slope at each end (signed)",
            "why": "what varies from star to star: a range the answer holds over, not an uncertainty",
        }
    return out


# --- beside the nominal answer: the conservative one and the star-to-star ranges --------------

#: Coverage factor of the conservative answer on the standard parts (statistical, fidelity, the
#: model's standard uncertainties): about 95 % for normal errors; the left-out shifts count in full.
CONSERVATIVE_K = 2.0
#: d ln|c| / dm of a slope proportional to the flux (the linear regime): -0.4 ln 10.
FLUX_LAW_LOG_DERIVATIVE = -0.4 * math.log(10.0)


def answer_extras(solved_for: str, result, log_derivative: float | None = None) -> tuple[dict | None, dict | None]:
    """(the conservative answer, the ranges) of a solved answer ``result`` (the solver's
    ``_Answer``: precision, tolerance, magnitude, slope, slope_error, parts, model, binding, m_nl).

    Conservative: the answer that still holds if the slope's modulus is at the top of its
    uncertainty, |c| (1 + U) with U = k hypot(statistical, fidelity, the model's standard parts,
    the optical model) + the left-out shifts, k = :data:`CONSERVATIVE_K`: the tolerance reached
    T (1 + U), the precision needed p / (1 + U), the brightest usable star where |c| p beta0 (1 + U)
    meets the tolerance (first order in ln(1 + U) through the slope's log derivative; at saturation
    the flux law). Ranges: each star-to-star range's ends (the model's, e.g. the SED's) as the
    solved quantity there. None where the answer has no uncertainty."""
    model, parts, slope = result.model, result.parts, result.slope
    if model is None or parts is None or parts.statistical is None or not slope:
        return None, None
    value = {"precision": result.precision, "tolerance": result.tolerance, "magnitude": result.magnitude}[solved_for]
    if value is None or not math.isfinite(value):
        return None, None
    if log_derivative is not None and not math.isfinite(log_derivative):
        log_derivative = None  # an NL limit past the tables' bright end (saturation binds): no slope there
    if solved_for == "magnitude":
        scale = abs(log_derivative) if log_derivative else None
        statistical = (result.slope_error or 0.0) / abs(slope)
        fidelity = (parts.fidelity or 0.0) * scale if scale else 0.0
        optical = (parts.optical_model or 0.0) * scale if scale else 0.0
    else:
        statistical, fidelity, optical = (
            (x or 0.0) / abs(value) for x in (parts.statistical, parts.fidelity, parts.optical_model)
        )
    standard = model.get("standard_relative")
    shifts = model.get("shifts_relative")
    if standard is None:
        # The paper scene's parts: the effects left out are shifts (added, as its rule adds them);
        # the pupil rule and the official-PSF figure both measure the optics, the larger counts.
        standard, shifts = max(model.get("pupil_scale_relative", 0.0), optical), model.get("effects_relative", 0.0)
        optical = 0.0
    k = CONSERVATIVE_K
    bound = k * math.sqrt(statistical**2 + fidelity**2 + standard**2 + optical**2) + shifts
    conservative = {
        "relative_slope_bound": bound,
        "slope_bound": abs(slope) * (1 + bound),
        "coverage": (
            f"|c| (1 + U), U = {k:g} x hypot(statistical, fidelity, the model's standard parts, optical model) + the "
            "left-out shifts: about 95 % for normal errors, the shifts in full"
        ),
        "coverage_factor": k,
        "solved_for": solved_for,
    }
    conservative[solved_for] = _solved_at(solved_for, value, bound, result, log_derivative)
    ranges = {}
    for name, entry in (model.get("ranges") or {}).items():
        ends = entry["relative_slope_change"]
        ranges[name] = {
            **entry,
            solved_for: [_solved_at(solved_for, value, change, result, log_derivative) for change in ends],
        }
    return conservative, ranges


def _solved_at(solved_for: str, value: float, change: float, result, log_derivative: float | None) -> float | None:
    """The solved quantity if the slope's modulus were (1 + change) times the answer's."""
    if 1 + change <= 0:
        return None
    if solved_for == "tolerance":
        return value * (1 + change)
    if solved_for == "precision":
        return value / (1 + change)
    if result.binding == "saturation":
        # The NL limit moves by the slope's log derivative (the flux law there); saturation holds
        # the answer unless the moved NL limit falls fainter than it.
        moved = None if result.m_nl is None else result.m_nl + math.log(1 + change) / abs(FLUX_LAW_LOG_DERIVATIVE)
        return value if moved is None else max(value, moved)
    if not log_derivative:
        return None
    return value + math.log(1 + change) / abs(log_derivative)
