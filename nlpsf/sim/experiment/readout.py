"""The up-the-ramp readout inside a simulation: per-pixel ramp factors, resultants used, their flags."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nlpsf.flags import FlagCode, make

from .. import ramps
from .prepared import Scene


@dataclass(frozen=True)
class RampEffect:
    """What the ramp fit does to the quadratic NL at one magnitude.

    ``factor`` is the per-pixel c_2 (``ramps.order_factors``): the fitted image is
    s (psi - beta s psi^2 c_2), so the final-frame machinery runs unchanged with -psi^2 replaced
    by -psi^2 c_2 (and d image / d beta = -s^2 psi^2 c_2 exactly: the weights do not depend on beta).
    """

    factor: np.ndarray
    usable: np.ndarray
    used_peak_e: float
    flags: list[str]
    extras: dict
    #: A scene with detector effects (IPC, background, polynomial NL): every order's factor and the
    #: charge the NL acts on (``ramps.scene_factors``); None for the paper's detector.
    scene_ramp: ramps.SceneRamp | None = None
    #: The pipeline's linearity correction per resultant (``experiment.correction.Correction``), when the
    #: residual is modelled that way (``residual_nl="per_resultant_correction"``); None otherwise.
    correction: object | None = None


def ramp_effect(scene: Scene, charge_scale: float, index: int | None = None, beta: float = 0.0) -> RampEffect:
    """Per-pixel ramp factors, resultants used, and the flags, for all realizations (or one).

    ``beta``: the quadratic NL the ramp's "signal" saturation rule sees (``ramps.usable_resultants``;
    the ramp's own ``saturation_beta`` wins when set); the factors do not depend on it."""
    config = scene.config
    ramp = config.ramp
    assert ramp is not None
    state = (beta, *config.scene.nl_coefficients)
    stamps = scene.stamps if index is None else scene.stamps[index : index + 1]
    weighted = scene.weighted_region if index is None else scene.weighted_region[index : index + 1]
    K = ramp.table.n_resultants
    last = ramp.table.last_read_fractions(config.exptime_s)
    if not config.scene.plain_detector:
        return _scene_ramp_effect(scene, charge_scale, index, state)
    peak = charge_scale * float(stamps.max())
    if ramp.fit == "ols" and peak * last[-1] <= config.full_well_e and (ramp.saturation == "charge" or beta >= 0):
        # Every pixel keeps every resultant and OLS weights do not depend on the charge: one factor
        # (the same number order_factors gives each pixel), no per-pixel work.
        factor, _ = ramps.order_factors(np.zeros(1), ramp, config.exptime_s, config.full_well_e, (2,))
        pixels = int(weighted.sum())
        summary = {"pixels": pixels, "resultants": K, "fitted_on_all": pixels, "fitted_on_fewer": 0, "unusable": 0}
        summary.update(pixels_by_resultants={str(K): pixels}, fewest_resultants=K, stamp_unusable=0, description=ramp.describe())
        weighted_peak = scene.weighted_peak_fraction if index is None else scene.weighted_peak_fraction[index : index + 1]
        used_peak = charge_scale * float(weighted_peak.max()) * last[-1]
        return RampEffect(factor.reshape(1, 1, 1), np.full(1, K), used_peak, [], {"ramp": summary})
    charge = charge_scale * stamps
    factors, usable = ramps.order_factors(charge, ramp, config.exptime_s, config.full_well_e, (2,), state=state)
    return _ramp_summary(scene, charge, factors[0], usable, weighted, None)


def _scene_ramp_effect(scene: Scene, charge_scale: float, index: int | None, state: tuple[float, ...]) -> RampEffect:
    """The ramp inside a scene with detector effects: ``ramps.scene_factors`` on Q = s psi + B."""
    config = scene.config
    model = config.scene
    pick = slice(None) if index is None else slice(index, index + 1)
    weighted = scene.weighted_region[pick]
    orders = tuple(range(2, 3 + len(model.nl_coefficients)))
    if model.ipc is not None and model.ipc_order == "after":
        # Every coupled image from the scene's coupled unit powers (ramps.CoupledPowers), none per flux;
        # the factors of all realizations only on the moments' core (every pixel of the one a scatter uses).
        sr, usable = ramps.scene_factors_coupled(
            scene.coupled_powers,
            charge_scale,
            model.background_e,
            config.ramp,
            config.exptime_s,
            config.full_well_e,
            state,
            orders,
            pick,
            margin=scene.core_margin if index is None else 0,
            region=scene.factor_region if index is None else None,
        )
        return _coupled_summary(scene, charge_scale, pick, sr.factors[0], usable, sr)
    charge = charge_scale * scene.charge[pick] + model.background_e
    sr = ramps.scene_factors(
        charge, config.ramp, config.exptime_s, config.full_well_e, state, orders, model.ipc, model.ipc_order, config.oversampling
    )
    return _ramp_summary(scene, sr.charge, sr.factors[0], sr.usable, weighted, sr)


def _ramp_summary(scene: Scene, charge, factor, usable, weighted, scene_ramp) -> RampEffect:
    config = scene.config
    K = config.ramp.table.n_resultants
    last = config.ramp.table.last_read_fractions(config.exptime_s)
    used_charge = charge * last[np.maximum(usable, 1) - 1]
    used_peak = float(np.where(weighted, used_charge, 0.0).max())
    summary = ramps.usage_summary(usable, K, weighted)
    summary["stamp_unusable"] = int(np.sum(usable == 0))
    return _ramp_flags(scene, factor, usable, weighted, scene_ramp, used_peak, summary, lambda: float(charge.max()))


def _coupled_summary(scene: Scene, charge_scale: float, pick: slice, factor, usable, scene_ramp) -> RampEffect:
    """:func:`_ramp_summary` for IPC after the NL, from the weighted pixels alone: the whole stamps'
    charge is never formed (each number is the same elementwise arithmetic on fewer pixels, and a
    maximum of s psi + B is s max(psi) + B exactly, rounding being monotonic)."""
    config = scene.config
    background = config.scene.background_e
    K = config.ramp.table.n_resultants
    last = config.ramp.table.last_read_fractions(config.exptime_s)
    weighted = scene.weighted_region[pick]
    where = scene.weighted_pixels if pick == slice(None) else np.flatnonzero(weighted)
    one = _one_value(usable)
    kept = np.full(where.size, one, dtype=usable.dtype) if one is not None else usable.reshape(-1)[where]
    used_charge = (charge_scale * scene.charge[pick].reshape(-1)[where] + background) * last[np.maximum(kept, 1) - 1]
    # As np.where(weighted, used, 0).max(): the pixels outside the weight count as 0.
    used_peak = float(used_charge.max(initial=0.0) if used_charge.size < weighted.size else used_charge.max())
    summary = ramps.usage_summary(kept, K)
    summary["stamp_unusable"] = (usable.size if one == 0 else 0) if one is not None else int(np.count_nonzero(usable == 0))
    peak = scene.charge_peak_fraction[pick]
    return _ramp_flags(
        scene, factor, usable, weighted, scene_ramp, used_peak, summary, lambda: float((charge_scale * peak + background).max())
    )


def _one_value(array: np.ndarray):
    """The value of an array that is one value broadcast (every stride zero), else None."""
    return array[(0,) * array.ndim] if array.size and not any(array.strides) else None


def _ramp_flags(scene: Scene, factor, usable, weighted, scene_ramp, used_peak: float, summary: dict, final_peak) -> RampEffect:
    """The ramp's flags from its usage summary; ``final_peak()``: the stamps' largest final charge."""
    config = scene.config
    ramp = config.ramp
    K = ramp.table.n_resultants
    summary["description"] = ramp.describe()
    flags = []
    needed = min(ramp.min_usable, K)
    first_end = ramp.table.resultants[needed - 1][-1] * ramp.table.frame_time_s
    if summary["unusable"]:
        hit = int(np.sum(np.any(weighted & (usable == 0), axis=(1, 2))))
        where = "in the first resultant" if needed == 1 else "by the second resultant (one gives no slope, as in romancal)"
        flags.append(
            make(
                FlagCode.RAMP_UNUSABLE_PIXELS,
                where=where,
                unusable=summary["unusable"],
                hit=hit,
                realizations=len(usable),
                full_well_e=config.full_well_e,
                time_s=first_end,
            )
        )
    if summary["fitted_on_fewer"]:
        flags.append(
            make(
                FlagCode.RAMP_FEWER_RESULTANTS,
                fewer=summary["fitted_on_fewer"],
                pixels=summary["pixels"],
                resultants=K,
                fewest=summary["fewest_resultants"],
                peak_e=final_peak(),
                full_well_e=config.full_well_e,
            )
        )
    return RampEffect(factor, usable, used_peak, flags, {"ramp": summary}, scene_ramp)


def _nl_shape(stamps: np.ndarray, factor: np.ndarray | None) -> np.ndarray:
    """psi^2 for the final frame, psi^2 c_2 after a ramp fit (``factor``, the ramp effect's c_2 on
    the same pixels): the pattern that -beta s multiplies."""
    return stamps**2 if factor is None else stamps**2 * factor
