"""The scene's kernels: what the scene effects do to the stamps.

Gaussian blurs (jitter, charge diffusion) on the effective PSF's Fourier coefficients; IPC and
brighter-fatter on the oversampled stamps; and the detector chain (charge, brighter-fatter, IPC
before or after the NL, background) that ``nlpsf.sim.experiment`` runs. The scene's description and its
validation are ``nlpsf.sim.scene``'s (which re-exports these); the kernels trust a validated scene.

Native-pixel kernels on the oversampled grid. A fine pixel (i, j) of the stamp holds the effective
PSF (optics convolved with the native pixel's top hat) sampled at its centre x_ij; that value is
exactly the charge a native pixel centred at x_ij would collect. The native pixel's neighbour to
the right is centred at x_ij + p, and x_ij + p is the centre of fine pixel (i, j + N) because fine
pixels are p / N apart. So the oversampled stamp is the interleave of N^2 native-pixel images
(one per sub-pixel phase), and a kernel that couples native pixels -- IPC, brighter-fatter --
acts on each interleaved image separately, i.e. on the fine grid its taps are N fine pixels apart.
``tests/library/test_scene.py`` checks this against GalSim's ``applyIPC`` on the de-interleaved images.
"""

from __future__ import annotations

import math
from typing import Protocol

import numpy as np


class DetectorEffects(Protocol):
    """The fields of a scene (``nlpsf.sim.scene.SceneModel``) the detector chain reads."""

    ipc: tuple[tuple[float, ...], ...] | None
    ipc_order: str
    bfe_coefficient: float
    nl_coefficients: tuple[float, ...]
    background_e: float


# --- Gaussian blurs ---------------------------------------------------------------------------


def gaussian_transfer(frequencies: np.ndarray, sigma_arcsec: float) -> np.ndarray:
    """Fourier transform of a unit-flux circular Gaussian of rms ``sigma`` per axis, on (f_y, f_x)."""
    f2 = frequencies[:, None] ** 2 + frequencies[None, :] ** 2
    return np.exp(-2.0 * math.pi**2 * sigma_arcsec**2 * f2)


def blur(psf, sigma_arcsec: float):
    """The effective PSF convolved with a Gaussian of rms ``sigma_arcsec`` (jitter, diffusion)."""
    from nlpsf.sim.optics import EffectivePSF

    if sigma_arcsec == 0:
        return psf
    coefficients = psf.coefficients * gaussian_transfer(psf.frequencies, sigma_arcsec)
    coefficients.setflags(write=False)
    return EffectivePSF(psf.optics, psf.field_arcsec, psf.frequencies, coefficients, psf.wavelengths_nm, psf.weights)


# --- native-pixel kernels on the oversampled grid -----------------------------------------------


def _shifted(images: np.ndarray, oversampling: int) -> dict[tuple[int, int], np.ndarray]:
    """Views of ``images`` shifted by (dy, dx) native pixels = (dy N, dx N) fine pixels, edges
    continued with the nearest value (so a uniform field stays uniform)."""
    n = oversampling
    pad = [(0, 0)] * (images.ndim - 2) + [(n, n), (n, n)]
    padded = np.pad(images, pad, mode="edge")
    ny, nx = images.shape[-2:]
    return {
        (dy, dx): padded[..., n + dy * n : n + dy * n + ny, n + dx * n : n + dx * n + nx]
        for dy in (-1, 0, 1)
        for dx in (-1, 0, 1)
    }


def apply_ipc(images: np.ndarray, kernel, oversampling: int) -> np.ndarray:
    """IPC on (stacks of) oversampled images: out = sum K[1+dy, 1+dx] in[y + dy N, x + dx N].

    This is GalSim's ``Image.applyIPC`` convention (kernel element (1+dy, 1+dx) weights the pixel
    at offset (dy, dx)), with taps N fine pixels apart (module docstring).
    """
    k = np.asarray(kernel, dtype=np.float64)
    images = np.asarray(images, dtype=np.float64)
    out = np.zeros(images.shape)
    if images.size == 0:
        return out
    stack, total = images.reshape(-1, *images.shape[-2:]), out.reshape(-1, *images.shape[-2:])
    # A few images at a time, so that the padded copy and the sum stay in cache across the nine taps
    # (each pixel's sum is the same nine terms in the same order, so the same numbers).
    block = max(1, _IPC_BLOCK_PIXELS // (images.shape[-1] * images.shape[-2]))
    for first in range(0, stack.shape[0], block):
        part = total[first : first + block]
        for (dy, dx), view in _shifted(stack[first : first + block], oversampling).items():
            part += k[1 + dy, 1 + dx] * view
    return out


#: Pixels per block of :func:`apply_ipc` (about half a megabyte of float64).
_IPC_BLOCK_PIXELS = 1 << 16


def apply_ipc_adjoint(images: np.ndarray, kernel, oversampling: int) -> np.ndarray:
    """The transpose of :func:`apply_ipc` (needed to move a pixel gradient back through IPC)."""
    flipped = np.asarray(kernel, dtype=np.float64)[::-1, ::-1]
    return apply_ipc(images, flipped, oversampling)


def brighter_fatter(charge: np.ndarray, coefficient: float, oversampling: int) -> np.ndarray:
    """Charge moved by the brighter-fatter effect (the change, not the image), nearest neighbours.

    The form of Antilogus et al. (2014, JINST 9, C03048, eq. 2-4) keeping only the nearest-neighbour
    boundary shifts: the boundary between pixel p and its neighbour X moves towards p by
    a (Q_p - Q_X) pixel widths (collected charge repels incoming charge), and the charge that crosses
    it is that shift times the mean charge density at the boundary, (Q_p + Q_X) / 2, halved again
    because the charge builds up linearly over the exposure:

        dQ_p = (a / 4) sum_X (Q_X^2 - Q_p^2),

    the discrete form of Coulton et al. (2018, AJ 155, 258) (1/2) div(Q grad(K * Q)) with a
    delta-function kernel. It conserves charge and broadens peaks for a > 0. ``coefficient`` a is in
    1/e- (the user's; there is no default). Neighbours are native pixels, N fine pixels apart.
    """
    q2 = np.asarray(charge, dtype=np.float64) ** 2
    shifted = _shifted(q2, oversampling)
    neighbours = shifted[(-1, 0)] + shifted[(1, 0)] + shifted[(0, -1)] + shifted[(0, 1)]
    return 0.25 * coefficient * (neighbours - 4.0 * q2)


# --- the detector chain ----------------------------------------------------------------------


def detector_chain(
    psi: np.ndarray, charge_scale: float, beta, model: DetectorEffects, oversampling: int
) -> tuple[np.ndarray | None, np.ndarray, np.ndarray]:
    """The detector effects on unit-flux stamps ``psi`` (effective PSF samples, before IPC).

    With s = ``charge_scale`` (flux N^2) and B the background, the charge is Q = s psi + B, moved by
    brighter-fatter, coupled by IPC before or after the NL S(Q) = Q - b2 Q^2 - b3 Q^3 ..., and the
    background is subtracted as the linear model would. Returns, per unit flux (divided by s):

    - ``shift``: the NL-free image minus the stored linear stamp IPC(psi) (brighter-fatter's own
      change of the image, which the metrics' reference includes), or None;
    - ``perturbation``: the image with the NL minus the NL-free one;
    - ``derivative``: d perturbation / d b2 for a uniform b2.

    Every difference is computed term by term (never as a difference of images), so faint stars
    and tiny coefficients keep full relative precision.
    """
    kernel = model.ipc
    charge = charge_scale * psi + model.background_e
    shift = None
    if model.bfe_coefficient != 0:
        moved = brighter_fatter(charge, model.bfe_coefficient, oversampling)
        charge = charge + moved
        shift = (apply_ipc(moved, kernel, oversampling) if kernel is not None else moved) / charge_scale
    if kernel is not None and model.ipc_order == "before":
        charge = apply_ipc(charge, kernel, oversampling)
    from nlpsf.sim.detector import polynomial_perturbation

    perturbation = polynomial_perturbation(charge, beta, model.nl_coefficients)
    derivative = -(charge * charge)
    if kernel is not None and model.ipc_order == "after":
        perturbation = apply_ipc(perturbation, kernel, oversampling)
        derivative = apply_ipc(derivative, kernel, oversampling)
    return shift, perturbation / charge_scale, derivative / charge_scale


def charge_before_nl(psi: np.ndarray, charge_scale: float, model: DetectorEffects, oversampling: int) -> np.ndarray:
    """The charge the NL acts on (for validity checks and per-pixel gradients)."""
    charge = charge_scale * psi + model.background_e
    if model.bfe_coefficient != 0:
        charge = charge + brighter_fatter(charge, model.bfe_coefficient, oversampling)
    if model.ipc is not None and model.ipc_order == "before":
        charge = apply_ipc(charge, model.ipc, oversampling)
    return charge
