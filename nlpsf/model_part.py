"""The model part of an answer: what a solve leaves out of a Roman scene, and what that adds to
its uncertainty.

With ``accuracy`` the full scene is simulated, or a set of effects whose combined impact is
measured within the accuracy is left out (``nlpsf.accuracy.select``, which builds the model
part); otherwise what is left out is read from the shipped measurement (:func:`shipped_model`).
:func:`model_at` states the parts relative to the answer's slope. ``slopes`` arguments are the
solver's c(m) at the request (``band``, ``metric``, ``mode``, ``table``, ``exptime``, ``table_beta0``).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from . import fidelity as levels
from . import roman, tables

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


def shipped_model(band: str, sca: int, metric: str, mode: str, scene, fidelity: str) -> dict:
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


def model_at(info: dict, slopes, magnitude: float) -> dict:
    """The model part at the answer's magnitude: impacts relative to this metric's slope, and the
    relative uncertainty of the effects left out and of the pupil-scale rule (:data:`MODEL_PARTS`).

    A shipped e1 / e2 impact is stated against |c_e| and scaled here by |c_e| / |c_ei|, as the
    optical model's part is."""
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
    from .scene import REGISTRY

    return replace(target, **{f: getattr(source, f) for f in REGISTRY[name].fields})


def optical_model_relative(slopes, magnitude: float | None) -> float:
    """Relative slope uncertainty from the optical model (``roman.optical_model_uncertainty``).

    For one ellipticity component it is stated against |c_e|, so it grows as |c_e| / |c_ei|."""
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
