"""The prepared scene: the magnitude- and beta-independent part of a simulation (optics, stamps, reference moments)."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from nlpsf.threads import single_blas

from .. import moments, optics, ramps, render
from .. import scene as scenes
from .config import Progress, SimulationConfig

#: Growth in size of the reference fits' weight windows within which the ramp factors are computed
#: (``Scene.factor_region``); the core itself allows the same growth.
FACTOR_REGION_GROWTH = 1.25


@dataclass(frozen=True, eq=False)
class Scene:
    """The magnitude- and beta-independent part of a simulation (see :func:`prepare`)."""

    config: SimulationConfig
    psf: optics.EffectivePSF
    offsets: np.ndarray  # (R, 2) centroid offsets in fine pixels
    stamps: np.ndarray  # (R, n, n) unit-flux stamps
    reference: moments.Moments
    elapsed_s: float
    #: Unit-flux charge stamps before IPC (None: the same as ``stamps``, no IPC in the scene).
    unit_charge: np.ndarray | None = None

    @property
    def charge(self) -> np.ndarray:
        return self.stamps if self.unit_charge is None else self.unit_charge

    @cached_property
    def coupled_powers(self) -> ramps.CoupledPowers:
        """IPC of the unit charge stamps' powers, shared by every flux of an up-the-ramp scene with IPC after the NL."""
        powers = ramps.CoupledPowers(self.charge, self.config.scene.ipc, self.config.oversampling)
        if self.unit_charge is not None:
            # The linear stamps are IPC(psi) already (``prepare``, the same call): not coupled twice.
            powers.seed(1, self.stamps)
        return powers

    @cached_property
    def core_margin(self) -> int:
        """Pixels each side of the stamps can lose for a perturbed fit (``moments.core_margin``).

        The paper's detector keeps its room for weight windows twice the reference's (its answers bit
        for bit); a scene with detector effects 1.25 times (a third of the pixels of the paper's core
        for H158, where an up-the-ramp scene's per-pixel ramp factors are the cost). Either way a fit
        whose window leaves the core is redone on the whole stamps, so the answer does not depend on it."""
        growth = 2.0 if self.config.scene.plain_detector else 1.25
        return moments.core_margin(self.stamps.shape[-1], self.reference, self.config.weight_cut_rho2, growth)

    @cached_property
    def factor_region(self) -> np.ndarray | None:
        """Where on the core (``core_margin``) an up-the-ramp scene's per-pixel factors are computed:
        inside each reference fit's weight window grown by ``FACTOR_REGION_GROWTH`` in size. A
        perturbed fit moves its window by ~1e-4 of its size at the corrected state (3e-4 at most
        over an H158 table) and ~1 % at the raw beta0; a fit whose window leaves the region is redone
        on the whole stamps (``kernels._perturbed_fit``). None: no core, or no finite cut."""
        margin, cut = self.core_margin, float(self.config.weight_cut_rho2)
        if not margin or not math.isfinite(cut):
            return None
        core = self.stamps.shape[-1] - 2 * margin
        region = _weighted_region(core, self.reference.parameters(), cut * FACTOR_REGION_GROWTH**2)
        region.setflags(write=False)
        return region

    @cached_property
    def peak_fraction(self) -> np.ndarray:
        """Largest fine-pixel value of each unit-flux stamp (of the centroids drawn)."""
        return self.stamps.max(axis=(1, 2))

    @cached_property
    def star_peak(self) -> tuple[float, tuple[float, float]]:
        """The star's brightest fine pixel (unit flux) over *every* sub-pixel centroid, and where
        the PSF peaks (x, y) [arcsec]: the maximum of the effective PSF (``optics.peak_value``),
        which does not depend on the centroids drawn. ``peak_fraction`` never exceeds it."""
        value, position = optics.peak_value(self.psf)
        return value * self.config.grid.scale_arcsec**2, position

    @property
    def star_peak_fraction(self) -> float:
        return self.star_peak[0]

    @cached_property
    def weighted_region(self) -> np.ndarray:
        """Pixels inside each reference fit's weight cut (where the moments look), (R, n, n)."""
        return _weighted_region(self.stamps.shape[-1], self.reference.parameters(), self.config.weight_cut_rho2)

    @cached_property
    def weighted_pixels(self) -> np.ndarray:
        """``np.flatnonzero(weighted_region)``: the pixels that carry weight, as flat indices."""
        return np.flatnonzero(self.weighted_region)

    @cached_property
    def charge_peak_fraction(self) -> np.ndarray:
        """Largest value of each unit-flux charge stamp (before IPC), per realization."""
        return self.charge.max(axis=(1, 2))

    @cached_property
    def star_peak_stamp(self) -> np.ndarray:
        """One unit-flux stamp with a fine-pixel centre on the PSF's peak (``star_peak_electrons``)."""
        grid = self.config.grid
        centres = grid.pixel_centres_arcsec()
        x, y = self.star_peak[1]
        # A fine-pixel centre c sees the PSF at c - offset: put the nearest centre on the peak.
        offset = np.array([[(centres[np.argmin(np.abs(centres - v))] - v) / grid.scale_arcsec for v in (x, y)]])
        stamp = render.draw(self.psf, grid, offset)
        stamp.setflags(write=False)
        return stamp

    @cached_property
    def weighted_peak_fraction(self) -> np.ndarray:
        """Largest unit-flux value among the pixels that carry weight, per realization."""
        return np.where(self.weighted_region, self.stamps, 0.0).max(axis=(1, 2))


@single_blas
def prepare(config: SimulationConfig, progress: Progress | None = None) -> Scene:
    """Optics, stamps for every centroid realization, and their reference moments."""
    start = time.perf_counter()
    grid = config.grid
    if progress:
        progress(0, 3, "optics")
    psf = optics.effective_psf(config.optics, round(grid.field_arcsec(), 9))
    # Jitter and charge diffusion: Gaussian blurs, a multiplication of the Fourier coefficients.
    psf = scenes.blur(psf, config.scene.blur_sigma_arcsec())
    rng = np.random.default_rng(config.seed)
    offsets = render.draw_offsets(rng, config.realizations, config.oversampling)
    chunk = 256
    blocks = range(0, config.realizations, chunk)
    stamps = np.empty((config.realizations, grid.stamp, grid.stamp))
    for k, first in enumerate(blocks):
        if progress:
            progress(1 + k / len(blocks), 3, "rendering")
        stamps[first : first + chunk] = render.draw(psf, grid, offsets[first : first + chunk])
    unit_charge = None
    if config.scene.ipc is not None:
        # The linear image the moments are referred to is the IPC-coupled one.
        unit_charge, stamps = stamps, scenes.apply_ipc(stamps, config.scene.ipc, config.oversampling)
    parts = []
    for k, first in enumerate(blocks):
        if progress:
            progress(2 + k / len(blocks), 3, "reference moments")
        parts.append(moments.fit(stamps[first : first + chunk], config.moment_settings))
    reference = moments.concatenate(parts)
    return Scene(config, psf, offsets, stamps, reference, time.perf_counter() - start, unit_charge)


def _weighted_region(n: int, params: np.ndarray, cut: float) -> np.ndarray:
    coords = np.arange(n) - (n - 1) / 2.0
    x0, y0, mxx, mxy, myy = params.T
    det = mxx * myy - mxy**2
    dx = coords[None, None, :] - x0[:, None, None]
    dy = coords[None, :, None] - y0[:, None, None]
    rho2 = (myy[:, None, None] * dx**2 - 2 * mxy[:, None, None] * dx * dy + mxx[:, None, None] * dy**2) / det[:, None, None]
    limit = cut if math.isfinite(cut) else 50.0
    return rho2 <= limit


def star_peak_electrons(scene: Scene, charge_scale: float) -> float:
    """The star's brightest pixel before the NL [e-], over every sub-pixel centroid (background included).

    Plain detector: charge_scale times ``Scene.star_peak_fraction``, exact. With detector effects
    the charge before the NL is computed on one stamp whose fine-pixel centre sits on the PSF's
    peak: exact for a background and for IPC after the NL (neither moves the peak); with IPC
    before the NL or brighter-fatter it is the charge at the optical peak's centring.
    """
    model = scene.config.scene
    if model.plain_detector:
        return charge_scale * scene.star_peak_fraction
    return float(scenes.charge_before_nl(scene.star_peak_stamp, charge_scale, model, scene.config.oversampling).max())


def _peak_electrons(scene: Scene, charge_scale: float, count: int | None = None) -> np.ndarray:
    """Largest charge in any pixel before the NL, per realization (background included)."""
    model = scene.config.scene
    if model.plain_detector:
        peak = charge_scale * scene.peak_fraction
        return peak if count is None else peak[:count]
    pick = slice(None) if count is None else slice(0, count)
    if model.bfe_coefficient == 0 and (model.ipc is None or model.ipc_order != "before"):
        # The charge is s psi + B: its maximum is s max(psi) + B exactly (rounding is monotonic).
        return charge_scale * scene.charge_peak_fraction[pick] + model.background_e
    charge = scenes.charge_before_nl(scene.charge[pick], charge_scale, model, scene.config.oversampling)
    return charge.max(axis=(1, 2))
