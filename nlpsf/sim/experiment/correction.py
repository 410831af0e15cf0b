"""The calibration residual as the pipeline leaves it: the linearity correction applied per resultant.

Two models of the detector a calibration error acts on (``slopes(linearise_at="corrected", residual_nl=...)``,
docs/ramps.md "The slope a calibration error acts through"):

- ``per_resultant_correction`` (the Roman default): the detector's raw NL S = Q - beta0 Q^2 on every read,
  IPC after it, the reads averaged into resultants, the saturation flags on those, then romancal's linearity
  step: the calibrated correction evaluated on each resultant of the measured, IPC-coupled, read-averaged
  signal (``ramps.correction``), then the ramp fit. A calibration error Delta_beta leaves the residual
  r(Q) = -Delta_beta Q^2 at each resultant's corrected level, through the measuring pixel's weights; the
  slope is taken about a perfect calibration (Delta_beta = 0), whose image still differs from the linear
  one (L of a read mean is not the mean of L; L of a coupled signal is not the coupled charge).
- ``per_read_beta`` (the earlier model, selectable): a residual beta = CORRECTED_RESIDUAL x beta0 on every
  read's charge, before IPC, with the saturation flags of the raw beta0.

The scene's higher NL orders (``nl_coefficients``, b3, b4, ...) are, in both, residuals the correction
leaves: here -sum b_m Q^m at each resultant's corrected level, part of the state.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

from nlpsf.checks import InputError

from .. import ramps
from .prepared import Scene
from .readout import RampEffect

#: The residual models (``slopes(residual_nl=...)``, ``conditions["residual_nl"]``).
RESIDUAL_MODELS: tuple[str, ...] = ("per_resultant_correction", "per_read_beta")
#: The model of the corrected state unless a request names one (the Roman default's).
DEFAULT_RESIDUAL_MODEL = "per_resultant_correction"

RESIDUAL_DESCRIPTIONS = {
    "per_resultant_correction": (
        "the detector's NL (raw beta0) on every read, IPC after it, resultants, saturation flags, then the linearity "
        "correction evaluated on each resultant of the measured signal as romancal's linearity step does (stcal's "
        "classic path): a calibration error leaves r(Q) = -Delta_beta Q^2 at each resultant's corrected level, weighted "
        "by the measuring pixel's fit; slope about a perfect calibration"
    ),
    "per_read_beta": (
        "a residual beta of 1e-2 beta0 on every read's charge before IPC (the earlier model), saturation flags of the raw beta0"
    ),
}


@dataclass(frozen=True, eq=False)
class Correction:
    """The per-resultant correction of a scene's stamps at one flux (``ramps.CorrectedRamp``), on the stamps'
    core ``margin`` pixels in from each side (0: whole stamps), with the way to the whole stamps."""

    ramp: ramps.CorrectedRamp
    margin: int
    #: The detector's raw quadratic NL the correction inverts (paper convention, 1/e-).
    raw_beta: float
    whole: Callable[[], Correction] | None = field(default=None, repr=False)
    region: np.ndarray | None = field(default=None, repr=False)

    def at_margin(self, margin: int) -> tuple[Correction, tuple]:
        """(a correction covering the core of ``margin``, the slice that trims its images to it)."""
        corr = self
        if self.margin > margin:
            corr = self.whole() if self.whole is not None else self
        trim = margin - corr.margin
        n = corr.ramp.shape[-1]
        return corr, (Ellipsis, slice(trim, n - trim), slice(trim, n - trim))

    @property
    def baseline(self) -> np.ndarray:
        """The perfectly corrected image less the linear one [e-], (R, core, core)."""
        return self.ramp.baseline_image

    @property
    def quadratic(self) -> np.ndarray:
        """The image of the residual r(Q) = -Q^2 (a unit Delta_beta) [e-], (R, core, core)."""
        return self.ramp.residual_image(ramps.correction.quadratic_residual(1.0))


def check_model(residual_nl: str | None, linearise_at: str) -> str | None:
    """The residual model a corrected state uses (None for the paper's state, beta0)."""
    if linearise_at != "corrected":
        if residual_nl is not None and residual_nl not in RESIDUAL_MODELS:
            raise InputError("residual_nl", f"must be one of {', '.join(RESIDUAL_MODELS)}, got {residual_nl!r}")
        return None
    if residual_nl is None:
        return DEFAULT_RESIDUAL_MODEL
    if residual_nl not in RESIDUAL_MODELS:
        raise InputError("residual_nl", f"must be one of {', '.join(RESIDUAL_MODELS)}, got {residual_nl!r}")
    return residual_nl


def corrected_effect(
    scene: Scene, charge_scale: float, raw_beta: float, effect: RampEffect | None, index: int | None = None
) -> RampEffect:
    """``effect`` (the ramp's factors and flags; None on a final frame) with the per-resultant correction of
    the stamps at this flux: the detector's raw NL ``raw_beta`` corrected exactly on every resultant."""
    config = scene.config
    model = config.scene
    if model.bfe_coefficient:
        raise InputError(
            "residual_nl",
            "the per-resultant correction is not modelled with brighter-fatter (its charge shift is not a read's "
            "polynomial); use residual_nl='per_read_beta'",
        )
    pick = slice(None) if index is None else slice(index, index + 1)
    ramp = config.ramp
    raw = (float(raw_beta),)
    terms = tuple(model.nl_coefficients)
    background = model.background_e
    sr = None if effect is None else effect.scene_ramp
    coupled = model.ipc is not None and model.ipc_order == "after"
    if coupled and (ramp is None or (sr is not None and sr.coupled is not None)):
        margin = sr.margin if sr is not None else (scene.core_margin if index is None else 0)
        region = sr.region if sr is not None else (scene.factor_region if index is None else None)

        def build(m: int, reg, usable) -> Correction:
            cr = ramps.corrected_coupled(
                scene.coupled_powers, charge_scale, background, ramp, config.exptime_s, usable, raw, terms, pick, m, reg
            )
            whole = None if m == 0 else (lambda: build(0, None, None if sr is None else _whole_usable(sr)))
            return Correction(cr, m, raw[0], whole, reg)

        correction = build(margin, region, None if sr is None else sr.usable)
    else:
        charge = charge_scale * scene.charge[pick] + background
        usable = None
        if ramp is not None:
            usable = effect.usable if sr is None else _whole_usable(sr)
            if usable.ndim < charge.ndim:  # one value for every pixel (a plain ramp keeping every resultant)
                usable = usable.reshape((1,) * charge.ndim) if usable.size == 1 else usable
        cr = ramps.corrected_images(
            charge, ramp, config.exptime_s, usable, raw, terms, model.ipc, model.ipc_order, config.oversampling
        )
        correction = Correction(cr, 0, raw[0])
    if effect is None:
        return RampEffect(None, None, float("nan"), [], {}, None, correction)
    return replace(effect, correction=correction)


def _whole_usable(sr: ramps.SceneRamp) -> np.ndarray:
    return sr.usable if not sr.margin else sr.whole().usable


def star_free_ramp(config, raw_beta: float) -> tuple[np.ndarray, np.ndarray] | None:
    """(levels, weights) of a star-free pixel's resultants, as ``ramps.CorrectedRamp`` holds them (K,);
    None without a sky."""
    cr = _star_free_ramp(config, float(raw_beta))
    if cr is None:
        return None
    size = 3 * config.oversampling
    centre = size * size // 2 + size // 2
    return cr.level[centre].copy(), cr.weights[centre].copy()


def star_free_correction(scene: Scene, raw_beta: float) -> tuple[float, float]:
    """(a star-free pixel's corrected level less the linear sky, its d / d Delta_beta) [e-]: what a local
    sky estimate removes under the per-resultant correction (``sky.star_free_level``'s counterpart)."""
    return _star_free_correction(scene.config, float(raw_beta))


@lru_cache(maxsize=256)
def _star_free_correction(config, raw_beta: float) -> tuple[float, float]:
    cr = _star_free_ramp(config, raw_beta)
    if cr is None:
        return 0.0, 0.0
    size = 3 * config.oversampling
    centre = size * size // 2 + size // 2
    derivative = cr.response(ramps.correction.quadratic_residual(1.0))
    return float(cr.baseline[centre]), float(derivative[centre])


@lru_cache(maxsize=256)
def _star_free_ramp(config, raw_beta: float) -> ramps.CorrectedRamp | None:
    """The per-resultant correction of a uniform, star-free stamp (3 x 3 native pixels: its centre sees the
    whole IPC kernel); None without a sky."""
    model = config.scene
    if model.background_e <= 0:
        return None
    n = config.oversampling
    size = 3 * n  # IPC reaches n fine pixels: the centre of a 3 x 3 native stamp sees the whole kernel
    sky = np.full((1, size, size), model.background_e)
    ramp = config.ramp
    usable = None
    if ramp is not None:
        state = (raw_beta, *model.nl_coefficients)
        usable = ramps.scene_factors(
            sky, ramp, config.exptime_s, config.full_well_e, state, (2,), model.ipc, model.ipc_order, n
        ).usable
    return ramps.corrected_images(
        sky, ramp, config.exptime_s, usable, (raw_beta,), model.nl_coefficients, model.ipc, model.ipc_order, n
    )
