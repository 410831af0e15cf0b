"""What each scene effect changes: the impact report.

For a request (band, SCA, magnitude, beta0, metric, mode) and a scene, every effect of
``nlpsf.sim.scene.EFFECTS`` is measured at that point with the linear response (exact derivatives at
beta0, cheap): its impact on a metric's slope is

    impact = slope(scene with the effect) / slope(scene without it) - 1.

An effect the scene has on is switched off for the comparison; an effect it leaves off is switched
on at its representative value (``scene.NOMINAL``: Roman's jitter, diffusion and IPC, a flat-f_nu
SED, a corner of the SCA, ...), so the report says what including it would change. Brighter-fatter
has no default coefficient: unless the scene gives one, its impact is not measured (``null``).

``cost_s`` is the seconds the linear-response simulation with the effect took at this point (its
own optics included where it needs new ones: a position or an SED; blurs and detector effects reuse
the cached optical PSF), beside ``conditions.plain_cost_s`` for the paper's scene. The benchmark
``benchmarks/bench_scene.py`` measures each effect's cost relative to the plain simulation with
repeats, in one run.

Both runs use the same centroids (same seed), so most of the realization noise cancels in the
ratio; the quoted ``uncertainty`` combines the two standard errors as if independent, an upper
bound.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

from nlpsf import defaults, roman
from nlpsf.checks import InputError, check_beta0, check_choice, check_exptime, check_integer
from nlpsf.sim import experiment
from nlpsf.sim import scene as scenes

#: Impact metrics: the contract's names, and the simulation metrics each combines.
IMPACT_METRICS: dict[str, tuple[str, ...]] = defaults.METRIC_COLUMNS
MODES = defaults.MODES


def slope_values(result: experiment.SlopeResult, mode: str) -> dict[str, tuple[float | None, float | None]]:
    """(slope, its standard error) per impact metric; |e| combines e1 and e2 in quadrature."""
    return {name: result.slope(mode, parts) for name, parts in IMPACT_METRICS.items()}


_slope_values = slope_values  # the old private name


def _ratio(with_value, without_value):
    (a, da), (b, db) = with_value, without_value
    if a is None or b is None or b == 0:
        return None, None
    ratio = a / b
    return ratio - 1.0, abs(ratio) * math.hypot(da / a if a else 0.0, db / b)


def check_request(
    band: str = defaults.BAND,
    sca: int = defaults.SCA,
    magnitude: float = defaults.MAGNITUDE,
    metric: str = "size",
    mode: str = "bias",
    beta0: float = defaults.BETA0,
    exptime: float = defaults.EXPTIME_S,
    realizations: int = defaults.REALIZATIONS,
    seed: int = defaults.SEED,
) -> dict:
    """An impact request's point, validated (InputError naming the field) and normalised, without
    simulating anything: what a caller checks before queueing the report as a job."""
    if metric not in IMPACT_METRICS:
        raise InputError("metric", f"must be one of {', '.join(IMPACT_METRICS)}, got {metric!r}")
    if mode not in MODES:
        raise InputError("mode", f"must be one of {', '.join(MODES)}, got {mode!r}")
    return {
        "band": roman.check_band(band),
        "sca": roman.check_sca(sca),
        "magnitude": experiment.check_magnitudes([magnitude])[0],
        "metric": metric,
        "mode": mode,
        "beta0": check_beta0(beta0),
        "exptime": check_exptime(exptime),
        "realizations": check_integer(realizations, "realizations", 2, 10_000),
        "seed": check_integer(seed, "seed", *defaults.SEED_RANGE),
    }


def point_config(band: str, sca: int, exptime: float, realizations: int, seed: int = defaults.SEED, **changes):
    """The simulation an effect's impact is measured with: the linear response at one point
    (``changes``: its scene, pupil rule, ...). The impact report and the solver's model part share it."""
    settings = {"band": band, "sca": sca, "exptime_s": exptime, "realizations": realizations, "seed": seed}
    return experiment.SimulationConfig.from_settings(settings, method="linear", **changes)


def impact(
    band: str = defaults.BAND,
    sca: int = defaults.SCA,
    magnitude: float = defaults.MAGNITUDE,
    scene: scenes.SceneModel | None = None,
    metric: str = "size",
    mode: str = "bias",
    beta0: float = defaults.BETA0,
    exptime: float = defaults.EXPTIME_S,
    realizations: int = defaults.REALIZATIONS,
    seed: int = defaults.SEED,
    max_wavelengths: int = 64,
    progress=None,
    pupil_scale: str | None = None,
) -> dict:
    """Every effect's relative change of the slope at this point; see the module docstring.

    ``pupil_scale`` (``roman.PUPIL_SCALE_RULES``): the pupil-mask scale rule of every run (None: the
    simulation's default, the paper tables' rule).

    Returns ``{"effects": [{"name", "on", "impact": {"size", "e1", "e2", "e"}, "uncertainty": {...},
    "cost_s", "value", "note"}, ...], "conditions": {...}}``.
    """
    scene = scene if scene is not None else scenes.SceneModel()
    if not isinstance(scene, scenes.SceneModel):
        raise InputError("scene", "must be a scene description")
    checked = check_request(band, sca, magnitude, metric, mode, beta0, exptime, realizations, seed)
    magnitude, beta0 = checked["magnitude"], checked["beta0"]
    rule = {} if pupil_scale is None else {"pupil_scale": check_choice(pupil_scale, "pupil_scale", roman.PUPIL_SCALE_RULES)}
    base = point_config(checked["band"], sca, exptime, realizations, seed, scene=scene, **rule)
    cache: dict[scenes.SceneModel, tuple[dict, float, list[str]]] = {}

    def run(model: scenes.SceneModel):
        key = replace(model, name=None)
        if key not in cache:
            start = time.perf_counter()
            result = experiment.slopes(replace(base, scene=key), [magnitude], beta0=beta0)[0]
            cache[key] = (slope_values(result, mode), time.perf_counter() - start, result.flags)
        return cache[key]

    total = len(scenes.EFFECTS) + 1
    if progress:
        progress(0, total, "the scene as given")
    start = time.perf_counter()
    scene_slopes, scene_cost, scene_flags = run(scene)
    effects = []
    for index, name in enumerate(scenes.EFFECTS, start=1):
        if progress:
            progress(index, total, name)
        effects.append(_measure_effect(name, scene, run, base, max_wavelengths))
    if progress:
        progress(total, total, "done")
    plain_slopes, plain_cost, _ = run(scenes.SceneModel())
    return {
        "effects": effects,
        "conditions": {
            "band": base.band,
            "sca": base.sca,
            "magnitude": magnitude,
            "metric": metric,
            "mode": mode,
            "beta0": beta0,
            "beta_convention": "paper",
            "exptime_s": exptime,
            "realizations": realizations,
            "seed": seed,
            "pupil_scale": base.pupil_scale,
            "method": "linear response at beta0 (exact derivatives), with and without each effect on the same centroids",
            "scene": scene.to_dict(),
            "scene_description": scene.describe(),
            "slope": {m: v[0] for m, v in scene_slopes.items()},
            "plain_slope": {m: v[0] for m, v in plain_slopes.items()},
            "plain_cost_s": plain_cost,
            "scene_cost_s": scene_cost,
            "flags": scene_flags,
            "beta_q_scaling_broken_by": scene.breaks_beta_q_scaling(),
            "elapsed_s": time.perf_counter() - start,
            "data_version": roman.DATA_VERSION,
        },
    }


def _measure_effect(name: str, scene: scenes.SceneModel, run, base, max_wavelengths: int) -> dict:
    """One effect's entry of the report: the slopes with and without it (at the scene's value, or
    its nominal one when the scene leaves it off), their ratio and what it cost."""
    on = scene.effects_on()[name]
    with_scene = scene if on else scene.with_nominal(name)
    capped = False
    if name == "sed" and not on and with_scene is not None:
        # The nominal SED at the number of wavelengths its accuracy needs, within the caller's cap.
        wanted = with_scene.wavelengths(base.band, 1, base.sca, base.throughput)
        with_scene = replace(with_scene, n_wavelengths=min(wanted, max_wavelengths))
        capped = wanted > max_wavelengths
    entry: dict = {"name": name, "on": on, "value": _effect_value(with_scene, name) if with_scene else None}
    if with_scene is None:
        entry.update(
            impact=dict.fromkeys(IMPACT_METRICS),
            uncertainty=dict.fromkeys(IMPACT_METRICS),
            cost_s=None,
            note=scenes.NOMINAL[name]["note"],
        )
        return entry
    with_values, with_cost, _ = run(with_scene)
    without_values, _, _ = run(with_scene.without(name))
    ratios = {m: _ratio(with_values[m], without_values[m]) for m in IMPACT_METRICS}
    entry.update(
        impact={m: r[0] for m, r in ratios.items()},
        uncertainty={m: r[1] for m, r in ratios.items()},
        cost_s=with_cost,
        note=("as in the scene" if on else f"off in the scene; measured at {scenes.NOMINAL[name]['note']}")
        + (f" with {max_wavelengths} wavelengths, fewer than the {wanted} its accuracy needs" if capped else ""),
    )
    return entry


def _effect_value(model: scenes.SceneModel, name: str):
    """The setting the effect was measured at, in the scene's own words."""
    return {
        "position": model.position,
        "sed": model.sed,
        "jitter": model.jitter_arcsec,
        "charge_diffusion": model.charge_diffusion_px,
        "ipc": None if model.ipc is None else f"{model.ipc_label} {model.ipc_order} NL",
        "nl_polynomial": list(model.nl_coefficients),
        "brighter_fatter": model.bfe_coefficient,
        "background": model.background_e,
    }[name]


def left_out(report: dict, accuracy: float) -> tuple[list[dict], list[dict]]:
    """Split the report's effects at ``accuracy`` on the request's metric: (include, leave out).

    An effect is included when |impact| on the request's metric exceeds the accuracy asked for;
    an effect whose impact could not be measured is left out and says so. This is not how
    ``accuracy`` decides (``nlpsf.solve.accuracy``: impacts inside the full scene, a left-out set
    measured as a set), since effects that share a sign or interact make this split miss A.
    """
    metric = report["conditions"]["metric"]
    include, leave = [], []
    for effect in report["effects"]:
        value = effect["impact"][metric]
        (include if value is not None and abs(value) > accuracy else leave).append(effect)
    return include, leave


def markdown(report: dict) -> str:
    c = report["conditions"]
    lines = [
        f"{c['band']} SCA {c['sca']} m={c['magnitude']:g} beta0={c['beta0']:g} {c['mode']} slopes",
        f"scene: {c['scene_description']}",
        "",
        "| effect | on | size | e1 | e2 | \\|e\\| | cost (s) | measured at |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in report["effects"]:
        cells = ["n/a" if e["impact"][m] is None else f"{100 * e['impact'][m]:+.2f} %" for m in IMPACT_METRICS]
        cost = "n/a" if e["cost_s"] is None else f"{e['cost_s']:.2f}"
        lines.append(f"| {e['name']} | {'yes' if e['on'] else 'no'} | " + " | ".join(cells) + f" | {cost} | {e['note']} |")
    lines.append("")
    lines.append(f"plain (paper) scene: {c['plain_cost_s']:.2f} s; impact = slope with / without - 1 (linear response)")
    return "\n".join(lines)


#: Metrics of the model-uncertainty measurement. ``size`` and ``e`` are relative to their own slope;
#: ``e1`` and ``e2`` are the change of that component's slope relative to |c_e| = hypot(c_e1, c_e2)
#: (as the optical model's part is stated): a component crossing zero would make its own ratio
#: meaningless, so the solver scales these by |c_e| / |c_ei| at the answer's magnitude.
MODEL_METRICS: tuple[str, ...] = defaults.METRICS


def _relative_to_scale(change: dict, slope: dict) -> dict:
    """Impacts (with / without - 1 per metric) restated as in :data:`MODEL_METRICS`."""
    out = {}
    for metric in MODEL_METRICS:
        value = change.get(metric)
        if value is None:
            out[metric] = None
        elif metric in ("e1", "e2"):
            scale, component = slope.get("e"), slope.get(metric)
            out[metric] = None if not scale or component is None else float(value * component / scale)
        else:
            out[metric] = float(value)
    return out


def model_point(
    band: str,
    sca: int,
    magnitude: float,
    mode: str = "bias",
    beta0: float = defaults.BETA0,
    exptime: float = defaults.EXPTIME_S,
    realizations: int = 50,
    seed: int = 1,
) -> dict:
    """What the paper's scene leaves out at one point, in the terms of :data:`MODEL_METRICS`.

    Every effect of the impact report at its nominal Roman value (:func:`impact` on the paper's
    scene), except the position, which is the worst of the SCA's four corner field points and the
    report's nominal corner (the spread over the SCA when no position is given); plus the pupil-mask
    scale rule (``galsim``, used, against ``header``), as the solver's ``accuracy`` path measures it.
    Effects without a nominal value (brighter-fatter) are ``None``. ``scripts/model_uncertainty.py``
    ships this over bands, SCAs, magnitudes and modes.
    """
    report = impact(band, sca, magnitude, mode=mode, beta0=beta0, exptime=exptime, realizations=realizations, seed=seed)
    conditions = report["conditions"]
    base = point_config(band, sca, exptime, realizations, seed)

    def values(config: experiment.SimulationConfig) -> dict:
        return slope_values(experiment.slopes(config, [conditions["magnitude"]], beta0=conditions["beta0"])[0], mode)

    plain = values(base)
    slope = {m: v[0] for m, v in plain.items()}
    effects: dict[str, dict | None] = {}
    for effect in report["effects"]:
        measured = any(v is not None for v in effect["impact"].values())
        effects[effect["name"]] = _relative_to_scale(effect["impact"], slope) if measured else None
    # The spread over the SCA: the worst corner per metric (the report's nominal corner included).
    corners = [tuple(scenes.NOMINAL["position"]["position"]), *roman.field_points(sca)[1:]]
    position = dict(effects["position"] or dict.fromkeys(MODEL_METRICS))
    where = {m: list(corners[0]) for m in MODEL_METRICS}
    for corner in corners[1:]:
        moved = values(replace(base, scene=scenes.SceneModel(position=corner)))
        change = _relative_to_scale({m: _ratio(moved[m], plain[m])[0] for m in IMPACT_METRICS}, slope)
        for m, value in change.items():
            if value is not None and (position[m] is None or abs(value) > abs(position[m])):
                position[m], where[m] = value, list(corner)
    effects["position"] = position
    header = values(replace(base, pupil_scale="header"))
    pupil = _relative_to_scale({m: _ratio(header[m], plain[m])[0] for m in IMPACT_METRICS}, slope)
    return {
        "band": conditions["band"],
        "sca": conditions["sca"],
        "magnitude": conditions["magnitude"],
        "mode": mode,
        "effects": effects,
        "position_worst_corner": where,
        "pupil_scale": pupil,
        "slope": slope,
    }
