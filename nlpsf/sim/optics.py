"""The Roman WFI effective PSF (optics convolved with the native pixel), in Fourier form.

The optical PSF depends only on (SCA, band, wavelengths, position on the SCA), so it is computed
once and kept as the Fourier coefficients of the *effective* PSF (optics times the native-pixel
transfer function) on a periodic field of side ``field_arcsec``. Rendering any sub-pixel centroid
at any oversampling is then a matrix Fourier transform of those coefficients
(``nlpsf.sim.render``), with no interpolation of a sampled image.

How it is computed, for each wavelength:

1. the pupil function W = T exp(2 pi i Phi) on the binned pupil grid, Phi the Zernike wavefront in
   waves at that wavelength;
2. the amplitude E(theta) = sum W exp(-2 pi i (u theta_x + v theta_y) / lambda) by matrix Fourier
   transforms on a grid that samples the intensity above Nyquist (spacing < lambda / (2 D));
3. the intensity |E|^2, normalised by Parseval so that it integrates to one over the whole sky;
4. its Fourier coefficients on the frequencies m / field_arcsec inside the optical cut-off
   (the OTF vanishes beyond the pupil's extent / lambda, so nothing is lost by the crop);
5. times the native pixel's transfer function sinc(p f_x) sinc(p f_y).

The PSF beyond half the field is dropped (it falls outside any stamp the field is made for), so the
zero-frequency coefficient is the fraction of the flux inside the field.
"""

from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from nlpsf import roman
from nlpsf.checks import InputError, check_integer, check_number
from nlpsf.threads import limited_blas

ARCSEC_PER_RADIAN = 180.0 * 3600.0 / math.pi


def noll_to_nm(j: int) -> tuple[int, int]:
    """Radial order n and signed azimuthal order m of Noll index j (m > 0: cos, m < 0: sin)."""
    if j < 1:
        raise ValueError(f"Noll index starts at 1, got {j}")
    n, remaining = 0, j - 1
    while remaining > n:
        n += 1
        remaining -= n
    m_abs = (n % 2) + 2 * ((remaining + ((n + 1) % 2)) // 2)
    m = m_abs if j % 2 == 0 else -m_abs
    return n, m if m_abs else 0


class _PolarBasis:
    """Powers of rho and cos/sin(m theta) at a set of pupil points, each computed once.

    Every Zernike is a combination of these. Integer powers ``rho ** k`` go through the general
    float power (slow for k > 2), and a wavefront sums ~20 Zernikes over the whole pupil: the
    repeated products and the shared trigonometry make it several times cheaper.
    """

    def __init__(self, rho: np.ndarray, theta: np.ndarray) -> None:
        self.rho = rho
        self._powers = [np.ones_like(rho)]
        # cos(m theta) + i sin(m theta) = (e^{i theta})^m: one cos and one sin for every m.
        self._turns = [np.ones_like(rho, dtype=np.complex128), np.cos(theta) + 1j * np.sin(theta)]
        self._angular: dict[int, np.ndarray] = {}

    def power(self, k: int) -> np.ndarray:
        while len(self._powers) <= k:
            self._powers.append(self._powers[-1] * self.rho)
        return self._powers[k]

    def angular(self, m: int) -> np.ndarray:
        """cos(m theta) for m > 0, sin(|m| theta) for m < 0."""
        if m not in self._angular:
            while len(self._turns) <= abs(m):
                self._turns.append(self._turns[-1] * self._turns[1])
            turn = self._turns[abs(m)]
            self._angular[m] = turn.real.copy() if m > 0 else turn.imag.copy()
        return self._angular[m]

    def zernike(self, j: int) -> np.ndarray:
        """Noll-normalised Zernike polynomial Z_j (unit RMS over the unit disc)."""
        n, m = noll_to_nm(j)
        m_abs = abs(m)
        radial = np.zeros_like(self.rho)
        for k in range((n - m_abs) // 2 + 1):
            coefficient = (
                (-1) ** k
                * math.factorial(n - k)
                / (math.factorial(k) * math.factorial((n + m_abs) // 2 - k) * math.factorial((n - m_abs) // 2 - k))
            )
            radial += coefficient * self.power(n - 2 * k)
        if m == 0:
            return math.sqrt(n + 1) * radial
        return math.sqrt(2 * (n + 1)) * radial * self.angular(m)


def zernike(j: int, rho: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Noll-normalised Zernike polynomial Z_j (unit RMS over the unit disc)."""
    return _PolarBasis(np.asarray(rho, dtype=np.float64), np.asarray(theta, dtype=np.float64)).zernike(j)


def wavefront_waves(coefficients: np.ndarray, u_m: np.ndarray, v_m: np.ndarray, radius_m: float) -> np.ndarray:
    """Wavefront (in waves) of Noll ``coefficients`` (index 0 unused) at pupil points (u, v)."""
    return _wavefront(_ZernikeCache(np.hypot(u_m, v_m) / radius_m, np.arctan2(v_m, u_m)), coefficients)


class _ZernikeCache:
    """The Zernikes at one set of pupil points, each evaluated once (``_PolarBasis.zernike``).

    The basis (powers of rho, cos/sin of m theta: about twice the Zernikes' memory) is built when a
    Zernike not yet held is asked for and dropped after each wavefront (``release``); rebuilt, it
    gives the same numbers."""

    def __init__(self, rho: np.ndarray, theta: np.ndarray) -> None:
        self.rho, self.theta = rho, theta
        self._basis: _PolarBasis | None = None
        self._values: dict[int, np.ndarray] = {}
        self._lock = threading.Lock()  # the basis grows its powers in place: one thread at a time

    def zernike(self, j: int) -> np.ndarray:
        with self._lock:
            if j not in self._values:
                if self._basis is None:
                    self._basis = _PolarBasis(self.rho, self.theta)
                self._values[j] = self._basis.zernike(j)
            return self._values[j]

    def release(self) -> None:
        with self._lock:
            self._basis = None


def _wavefront(zernikes: _ZernikeCache, coefficients: np.ndarray) -> np.ndarray:
    total = np.zeros_like(zernikes.rho)
    for j in range(1, len(coefficients)):
        if coefficients[j] != 0.0:
            total += coefficients[j] * zernikes.zernike(j)
    zernikes.release()
    return total


#: The open pupil points' Zernikes of the last few pupils: every wavelength of a PSF and every field
#: position of an SCA evaluate the same polynomials on the same points, and only the coefficients
#: change (the same numbers as evaluating them afresh; ~30 MB a pupil at the default binning).
_PUPIL_ZERNIKES: dict[tuple, tuple[np.ndarray, _ZernikeCache]] = {}
_PUPIL_ZERNIKES_KEPT = 2
_PUPIL_ZERNIKES_LOCK = threading.Lock()


def clear_caches() -> None:
    """Forget every computed PSF and pupil's Zernikes (what a request in a fresh process pays again)."""
    effective_psf.cache_clear()
    with _PUPIL_ZERNIKES_LOCK:
        _PUPIL_ZERNIKES.clear()


def _open_pupil_zernikes(pupil: roman.Pupil, t: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, _ZernikeCache]:
    """(open pixels of the cropped pupil ``t``, their Zernikes), cached per pupil."""
    key = (pupil.sca, pupil.mask_kind, pupil.scale_m, t.shape, hash(t.tobytes()), hash(u.tobytes()), hash(v.tobytes()))
    with _PUPIL_ZERNIKES_LOCK:
        if key not in _PUPIL_ZERNIKES:
            uu, vv = np.meshgrid(u, v)
            open_pixels = t > 0
            u_m, v_m = uu[open_pixels], vv[open_pixels]
            zernikes = _ZernikeCache(np.hypot(u_m, v_m) / (roman.DIAMETER_M / 2), np.arctan2(v_m, u_m))
            while len(_PUPIL_ZERNIKES) >= _PUPIL_ZERNIKES_KEPT:
                _PUPIL_ZERNIKES.pop(next(iter(_PUPIL_ZERNIKES)))
            _PUPIL_ZERNIKES[key] = (open_pixels, zernikes)
        return _PUPIL_ZERNIKES[key]


@dataclass(frozen=True)
class OpticsConfig:
    """What the optical PSF depends on. ``wavelength_nm=None`` means the band's effective wavelength.

    ``n_wavelengths`` = 1 is the achromatic PSF (the paper's choice); more integrates the band for
    a flat-f_nu source (photon weights proportional to A_eff(lambda) / lambda). Both use the
    effective-area curve of this SCA from the ``throughput`` data set (``roman.THROUGHPUTS``).
    """

    band: str = "H158"
    sca: int = 18
    wavelength_nm: float | None = None
    n_wavelengths: int = 1
    pupil_bin: int = 4
    pupil_scale: str = "galsim"
    position_pixels: tuple[float, float] | None = None
    #: The star's f_lambda (any units) tabulated as (wavelengths nm, values); None: flat f_nu.
    spectrum: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    throughput: str = roman.DEFAULT_THROUGHPUT

    def __post_init__(self) -> None:
        object.__setattr__(self, "band", roman.check_band(self.band))
        object.__setattr__(self, "sca", roman.check_sca(self.sca))
        roman.check_throughput(self.throughput)
        check_integer(self.n_wavelengths, "n_wavelengths", 1, 64)
        if self.wavelength_nm is not None:
            check_number(self.wavelength_nm, "wavelength_nm", 300.0, 3000.0)
            if self.n_wavelengths != 1:
                raise InputError("wavelength_nm", "give a single wavelength or n_wavelengths > 1, not both")
        if self.position_pixels is not None:
            object.__setattr__(self, "position_pixels", tuple(float(v) for v in self.position_pixels))

    def wavelengths_and_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """Wavelengths [nm] and their normalised photon weights (the star's SED, flat f_nu by default)."""
        curve = roman.throughput(self.band, sca=self.sca, source=self.throughput)
        if self.n_wavelengths == 1 and self.spectrum is None:
            wavelength = self.wavelength_nm if self.wavelength_nm is not None else curve.effective_wavelength_nm
            return np.array([float(wavelength)]), np.array([1.0])
        return band_wavelengths_and_weights(curve, self.n_wavelengths, tabulated_sed(curve, self.spectrum))


def tabulated_sed(curve: roman.Throughput, spectrum) -> Callable[[np.ndarray], np.ndarray] | None:
    """f_lambda interpolated from a table (wavelengths nm, values), refused if it does not cover the band."""
    if spectrum is None:
        return None
    wave, flambda = (np.asarray(v, dtype=np.float64) for v in spectrum)
    if curve.blue_limit_nm < wave[0] or curve.red_limit_nm > wave[-1]:
        raise InputError(
            "sed",
            f"the SED covers {wave[0]:g}-{wave[-1]:g} nm but {curve.band} spans "
            f"{curve.blue_limit_nm:g}-{curve.red_limit_nm:g} nm",
        )
    return lambda lam: np.interp(lam, wave, flambda)


def band_wavelengths_and_weights(
    curve: roman.Throughput, n_wavelengths: int, sed_flambda: Callable[[np.ndarray], np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``n_wavelengths`` wavelengths [nm] over the band and their normalised photon weights.

    Photons per unit wavelength are proportional to A_eff(lambda) f_lambda(lambda) lambda; for the
    default flat-f_nu source (f_lambda proportional to lambda^-2) that is A_eff / lambda.
    ``sed_flambda`` gives f_lambda (any normalisation) at wavelengths in nm.
    """
    # Equal-width bins over the band; each bin is represented by its photon-weighted mean
    # wavelength and carries its share of the photons.
    fine = np.linspace(curve.blue_limit_nm, curve.red_limit_nm, 64 * n_wavelengths + 1)
    photons = np.interp(fine, curve.wavelength_nm, curve.effective_area_m2) / fine
    if sed_flambda is not None:
        photons = photons * np.asarray(sed_flambda(fine), dtype=np.float64) * fine**2
    edges = np.linspace(0, fine.size - 1, n_wavelengths + 1).astype(int)
    wavelengths, weights = [], []
    for lo, hi in itertools.pairwise(edges):
        w = np.trapezoid(photons[lo : hi + 1], fine[lo : hi + 1])
        wavelengths.append(np.trapezoid(photons[lo : hi + 1] * fine[lo : hi + 1], fine[lo : hi + 1]) / w)
        weights.append(w)
    weights_array = np.asarray(weights)
    return np.asarray(wavelengths), weights_array / weights_array.sum()


def photon_weights_fine(curve: roman.Throughput, spectrum, n_wavelengths: int) -> tuple[np.ndarray, np.ndarray]:
    """Photons per unit wavelength over the band, on a grid fine enough to bin into n_wavelengths.

    Counts per unit wavelength are proportional to A_eff(lambda) f_lambda lambda (photon energy
    h c / lambda); for a flat f_nu star f_lambda ~ lambda^-2, i.e. A_eff / lambda.
    """
    fine = np.linspace(curve.blue_limit_nm, curve.red_limit_nm, 64 * n_wavelengths + 1)
    area = np.interp(fine, curve.wavelength_nm, curve.effective_area_m2)
    if spectrum is None:
        return fine, area / fine
    wave, flambda = (np.asarray(v, dtype=np.float64) for v in spectrum)
    if fine[0] < wave[0] or fine[-1] > wave[-1]:
        raise InputError("sed", f"the SED covers {wave[0]:g}-{wave[-1]:g} nm but {curve.band} spans {fine[0]:g}-{fine[-1]:g} nm")
    return fine, area * np.interp(fine, wave, flambda) * fine


@dataclass(frozen=True, eq=False)
class EffectivePSF:
    """Fourier coefficients of the effective PSF on a periodic field.

    ``coefficients[a, b]`` is the Fourier transform (flux-normalised) of the effective PSF at
    spatial frequency (f_y, f_x) = (frequencies[a], frequencies[b]) in cycles per arcsec, where the
    PSF was kept within ``field_arcsec`` (side of the square) around its centre.
    """

    optics: OpticsConfig | None
    field_arcsec: float
    frequencies: np.ndarray
    coefficients: np.ndarray
    wavelengths_nm: np.ndarray
    weights: np.ndarray
    flux_in_field: float = field(init=False)

    def __post_init__(self) -> None:
        centre = self.frequencies.size // 2
        object.__setattr__(self, "flux_in_field", float(self.coefficients[centre, centre].real))


def _clear_aperture(pupil: roman.Pupil) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pupil cropped to its open part: transmission and its u, v coordinates [m]."""
    transmission = pupil.transmission
    rows = np.flatnonzero(transmission.any(axis=1))
    cols = np.flatnonzero(transmission.any(axis=0))
    coords = pupil.coordinates_m
    return (
        transmission[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1],
        coords[cols[0] : cols[-1] + 1],
        coords[rows[0] : rows[-1] + 1],
    )


def psf_intensity(
    pupil: roman.Pupil, coefficients_waves: np.ndarray, wavelength_nm: float, theta_arcsec: np.ndarray
) -> np.ndarray:
    """Optical PSF [fraction of the flux per arcsec^2] on the square grid theta x theta.

    Normalised by Parseval over one period (lambda / pupil pixel) of the sampled pupil's far field,
    i.e. to unit total flux. Rows are theta_y, columns theta_x.
    """
    t, u, v = _clear_aperture(pupil)
    # The wavefront only matters where light passes: evaluating the Zernikes on the open pixels
    # alone gives the same pupil function at about half the cost.
    open_pixels, zernikes = _open_pupil_zernikes(pupil, t, u, v)
    # t exp(2 pi i phase) on the open pixels only (a closed one is exactly 0 either way).
    pupil_function = np.zeros(t.shape, dtype=np.complex128)
    pupil_function[open_pixels] = t[open_pixels] * np.exp(2j * np.pi * _wavefront(zernikes, coefficients_waves))
    wavelength_m = wavelength_nm * 1e-9
    theta_rad = np.asarray(theta_arcsec, dtype=np.float64) / ARCSEC_PER_RADIAN
    # GalSim's sign convention (an inverse FFT of the pupil); it only turns the PSF by 180
    # degrees, which moments do not see, but keeps images identical to the reference's.
    kernel_u = np.exp(2j * np.pi * np.outer(theta_rad, u) / wavelength_m)
    kernel_v = np.exp(2j * np.pi * np.outer(theta_rad, v) / wavelength_m)
    amplitude = kernel_v @ pupil_function @ kernel_u.T
    period_arcsec = wavelength_m / pupil.scale_m * ARCSEC_PER_RADIAN
    return np.abs(amplitude) ** 2 / (period_arcsec**2 * np.sum(np.abs(pupil_function) ** 2))


def _intensity_coefficients(
    pupil: roman.Pupil,
    coefficients_waves: np.ndarray,
    wavelength_nm: float,
    frequencies: np.ndarray,
    field_arcsec: float,
) -> np.ndarray:
    """Fourier coefficients (at ``frequencies``, cycles/arcsec) of the optical PSF kept in the field."""
    cutoff = _optical_cutoff(pupil, wavelength_nm)
    # Sample the intensity above Nyquist for its band limit (the OTF support).
    n_theta = 2 * math.ceil(field_arcsec * cutoff * 1.05) + 2
    spacing = field_arcsec / n_theta
    theta_arcsec = (np.arange(n_theta) - n_theta // 2) * spacing
    intensity = psf_intensity(pupil, coefficients_waves, wavelength_nm, theta_arcsec)
    dft = np.exp(-2j * np.pi * np.outer(frequencies, theta_arcsec))
    return spacing**2 * (dft @ intensity @ dft.T)


def frequency_grid(field_arcsec: float, cutoff_per_arcsec: float) -> np.ndarray:
    """Frequencies m / field (cycles/arcsec) covering [-cutoff, cutoff], symmetric about zero."""
    m_max = math.ceil(cutoff_per_arcsec * field_arcsec)
    return np.arange(-m_max, m_max + 1) / field_arcsec


def _optical_cutoff(pupil: roman.Pupil, wavelength_nm: float) -> float:
    """Highest spatial frequency (cycles/arcsec) of the OTF: the open pupil's extent / lambda."""
    _t, u, v = _clear_aperture(pupil)
    extent_m = max(u[-1] - u[0], v[-1] - v[0]) + pupil.scale_m
    return extent_m / (wavelength_nm * 1e-9) / ARCSEC_PER_RADIAN


@lru_cache(maxsize=64)
def effective_psf(optics: OpticsConfig, field_arcsec: float) -> EffectivePSF:
    """Effective PSF (optics convolved with the 0.11" pixel) of ``optics`` on a field of this side.

    Cached per (optics, field): the only expensive step of a simulation, done once. It is computed
    on the kernels' BLAS threads (``threads.limited_blas``) whoever asks first: a multithreaded matrix
    product sums in another order, so a PSF cached by a caller outside the kernels would differ in its
    last bits from the same PSF computed inside one (e.g. the SCA centre given or defaulted).
    """
    field_arcsec = check_number(field_arcsec, "field_arcsec", 0.5, 60.0)
    pupil = roman.pupil(optics.sca, optics.band, optics.pupil_bin, optics.pupil_scale)
    wavelengths, weights = optics.wavelengths_and_weights()
    with limited_blas():
        return psf_from_pupil(
            pupil, roman.aberrations(optics.sca, optics.position_pixels), wavelengths, weights, field_arcsec, optics
        )


def psf_from_pupil(
    pupil: roman.Pupil,
    aberrations_waves: np.ndarray,
    wavelengths_nm: np.ndarray,
    weights: np.ndarray,
    field_arcsec: float,
    optics: OpticsConfig | None = None,
    aberration_wavelength_nm: float = roman.ZERNIKE_REFERENCE_WAVELENGTH_NM,
    pixel_response: bool = True,
) -> EffectivePSF:
    """Effective PSF of any pupil; ``aberrations_waves`` are Noll coefficients in waves at
    ``aberration_wavelength_nm`` (the optical path difference is the same at every wavelength).
    ``pixel_response=False`` leaves out the native pixel: the optical PSF alone."""
    wavelengths_nm = np.atleast_1d(np.asarray(wavelengths_nm, dtype=np.float64))
    weights = np.atleast_1d(np.asarray(weights, dtype=np.float64))
    frequencies = frequency_grid(field_arcsec, _optical_cutoff(pupil, float(wavelengths_nm.min())))
    total = np.zeros((frequencies.size, frequencies.size), dtype=np.complex128)
    for wavelength, weight in zip(wavelengths_nm, weights, strict=True):
        scaled = np.asarray(aberrations_waves, dtype=np.float64) * aberration_wavelength_nm / wavelength
        total += weight * _intensity_coefficients(pupil, scaled, float(wavelength), frequencies, field_arcsec)
    if pixel_response:
        pixel = np.sinc(roman.PIXEL_SCALE_ARCSEC * frequencies)
        total *= pixel[:, None] * pixel[None, :]
    total.setflags(write=False)
    frequencies.setflags(write=False)
    return EffectivePSF(optics, field_arcsec, frequencies, total, wavelengths_nm, weights)


def _series(psf: EffectivePSF, y_arcsec: np.ndarray, x_arcsec: np.ndarray, dy: int = 0, dx: int = 0) -> np.ndarray:
    """The effective PSF (flux per arcsec^2), or its ``dy``-th / ``dx``-th partial derivative, on
    the grid y x x [arcsec], summed from its Fourier coefficients (no sampling, no interpolation)."""
    f = psf.frequencies
    phase_y = np.exp(2j * np.pi * np.outer(y_arcsec, f)) * (2j * np.pi * f) ** dy
    phase_x = np.exp(2j * np.pi * np.outer(x_arcsec, f)) * (2j * np.pi * f) ** dx
    return (phase_y @ psf.coefficients @ phase_x.T).real / psf.field_arcsec**2


#: Where the peak of a PSF centred on the origin is looked for [arcsec]: aberrations move it by a
#: small fraction of a native pixel, so a window of +-1.5 native pixels holds it with room to spare.
PEAK_SEARCH_HALF_WIDTH_ARCSEC = 1.5 * roman.PIXEL_SCALE_ARCSEC


def _local_expansion(psf: EffectivePSF, y: float, x: float) -> tuple[float, np.ndarray, np.ndarray]:
    """Value, gradient (d/dy, d/dx) and Hessian of the effective PSF at one point (flux per
    arcsec^2 and its derivatives), from one set of phases of its Fourier series."""
    f = psf.frequencies
    k = 2j * np.pi * f
    ey, ex = np.exp(k * y), np.exp(k * x)
    c = psf.coefficients
    cx = c @ ex, c @ (k * ex), c @ (k**2 * ex)  # d^n/dx^n summed over x frequencies
    yv = ey, k * ey, k**2 * ey
    value = (yv[0] @ cx[0]).real
    gradient = np.array([(yv[1] @ cx[0]).real, (yv[0] @ cx[1]).real])
    hessian = np.array([[(yv[2] @ cx[0]).real, (yv[1] @ cx[1]).real], [(yv[1] @ cx[1]).real, (yv[0] @ cx[2]).real]])
    scale = psf.field_arcsec**2
    return float(value / scale), gradient / scale, hessian / scale


def peak_value(psf: EffectivePSF) -> tuple[float, tuple[float, float]]:
    """The effective PSF's largest value over the plane (flux per arcsec^2) and where (x, y) [arcsec].

    A fine pixel of a stamp is the effective PSF sampled at one point, and the stamp's centroid
    moves that point over a whole fine pixel, so this is the brightest pixel over every sub-pixel
    centroid: a property of the star, not of the centroids drawn. Found on a grid of 1/20 native
    pixel, then refined by Newton steps on the Fourier series (exact derivatives), which converge
    to ~1e-15 of the peak in a few steps.
    """
    grid = np.linspace(-PEAK_SEARCH_HALF_WIDTH_ARCSEC, PEAK_SEARCH_HALF_WIDTH_ARCSEC, 61)
    values = _series(psf, grid, grid)
    iy, ix = np.unravel_index(int(np.argmax(values)), values.shape)
    point = np.array([grid[iy], grid[ix]])
    best, best_point = float(values[iy, ix]), point
    step_limit = grid[1] - grid[0]
    for _ in range(20):
        value, gradient, hessian = _local_expansion(psf, *point)
        if value >= best:
            best, best_point = value, point
        if hessian[0, 0] >= 0 or np.linalg.det(hessian) <= 0:
            break  # not a maximum's neighbourhood: keep the best point found
        step = -np.linalg.solve(hessian, gradient)
        if np.hypot(*step) > step_limit or np.hypot(*step) < 1e-13:
            break
        point = point + step
    return best, (float(best_point[1]), float(best_point[0]))
