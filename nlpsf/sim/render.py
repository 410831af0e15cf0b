"""Draw the effective PSF on the oversampled grid, batched over centroid realizations.

A stamp of ``stamp`` x ``stamp`` fine pixels of side p/N (p = 0.11", N = ``oversampling``) holds
the effective PSF sampled at the fine-pixel centres (GalSim's ``drawImage(method='no_pixel')``),
with the PSF centred on the stamp's true centre plus a sub-pixel ``offset`` given in fine pixels.
A sub-pixel shift is a phase ramp on the Fourier coefficients, so each realization costs two small
matrix products and no interpolation.

Values are the fraction of the star's flux per fine pixel; multiply by ``flux * N**2`` to get the
charge a native pixel would hold at that point (the paper's scaling, since NL acts per pixel).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from nlpsf import defaults
from nlpsf.checks import InputError, check_integer
from nlpsf.roman import PIXEL_SCALE_ARCSEC

from .optics import EffectivePSF

#: Limits on the stamp and oversampling a simulation may ask for.
MIN_STAMP, MAX_STAMP = defaults.STAMP_RANGE
MIN_OVERSAMPLING, MAX_OVERSAMPLING = defaults.OVERSAMPLING_RANGE


@dataclass(frozen=True)
class Grid:
    """The oversampled stamp: ``stamp`` fine pixels of ``PIXEL_SCALE / oversampling`` a side."""

    oversampling: int = defaults.OVERSAMPLING
    stamp: int = defaults.STAMP

    def __post_init__(self) -> None:
        check_integer(self.oversampling, "oversampling", MIN_OVERSAMPLING, MAX_OVERSAMPLING)
        check_integer(self.stamp, "stamp", MIN_STAMP, MAX_STAMP)

    @property
    def scale_arcsec(self) -> float:
        return PIXEL_SCALE_ARCSEC / self.oversampling

    @property
    def extent_arcsec(self) -> float:
        return self.stamp * self.scale_arcsec

    def field_arcsec(self, margin_native_pixels: float = 8.0) -> float:
        """Side of the periodic field the optics are computed on for this stamp.

        The field must hold the stamp, the largest centroid offset (one native pixel) and the
        native pixel's width, so that the periodic copies of the truncated PSF never reach the
        stamp. What is left converges slowly with the margin (truncating the PSF's wings leaves a
        ~1e-6-of-peak ripple); at 8 native pixels Delta R / R is within 1e-6 of its limit
        (``tests/library/test_experiment.py::test_optics_field_margin_does_not_move_results``).
        """
        return self.extent_arcsec + 2 * margin_native_pixels * PIXEL_SCALE_ARCSEC

    def pixel_centres_arcsec(self) -> np.ndarray:
        return (np.arange(self.stamp) - (self.stamp - 1) / 2) * self.scale_arcsec


def draw(psf: EffectivePSF, grid: Grid, offsets_fine_pixels: np.ndarray, chunk: int = 8) -> np.ndarray:
    """Stamps of the effective PSF, shape (R, stamp, stamp), for offsets of shape (R, 2) = (dx, dy).

    Offsets are in fine pixels from the stamp's true centre; row index is y, column index is x.
    """
    offsets = np.asarray(offsets_fine_pixels, dtype=np.float64).reshape(-1, 2)
    if not np.all(np.isfinite(offsets)):
        raise InputError("offsets", "centroid offsets must be finite")
    if grid.extent_arcsec > psf.field_arcsec + 1e-9:
        raise InputError("stamp", "the optics field is smaller than the stamp; compute the PSF for this grid")
    centres = grid.pixel_centres_arcsec()
    frequencies = psf.frequencies
    normalisation = grid.scale_arcsec**2 / psf.field_arcsec**2
    # exp(2 pi i f (c - d)) = exp(2 pi i f c) exp(-2 pi i f d): the pixel part E is the same for
    # every realization, and a centroid d only multiplies the coefficients by a phase per frequency,
    # so a stamp is E (C . u v^T) E^T -- one table of complex exponentials instead of one per
    # realization (4x faster; equal to the direct sum to 1e-15 of the peak).
    pixel_phase = np.exp(2j * np.pi * np.outer(centres, frequencies))
    # A few realizations at a time: their phase-shifted coefficients (chunk x F^2 complex, F up to
    # ~240 for R062) then stay small; each stamp's products are its own, so any chunk gives the same.
    out = np.empty((offsets.shape[0], grid.stamp, grid.stamp))
    for start in range(0, offsets.shape[0], chunk):
        block = offsets[start : start + chunk] * grid.scale_arcsec
        shift_x = np.exp(-2j * np.pi * block[:, 0, None] * frequencies[None, :])
        shift_y = np.exp(-2j * np.pi * block[:, 1, None] * frequencies[None, :])
        shifted = psf.coefficients[None] * shift_y[:, :, None] * shift_x[:, None, :]
        out[start : start + chunk] = (pixel_phase @ shifted @ pixel_phase.T).real * normalisation
    return out


def draw_offsets(rng: np.random.Generator, count: int, oversampling: int) -> np.ndarray:
    """Centroids uniform within one native pixel, in fine pixels (the paper's step 2)."""
    return (rng.random((count, 2)) - 0.5) * oversampling
