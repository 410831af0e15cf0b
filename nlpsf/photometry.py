"""AB magnitude <-> electrons through a Roman band.

Flux in electrons is the internal variable; a magnitude is only a label for it. For a source
with a flat f_nu spectrum (the AB system's reference), the electron count in exposure time t is

    N_e = t * integral f_nu / (h * lambda) * A_eff(lambda) d lambda,

with f_nu = 3631 Jy * 10**(-0.4 m). This is the same number GalSim gets from
``SED.withMagnitude(m, bandpass).calculateFlux(bandpass) * collecting_area * t`` for
``galsim.roman.getBandpasses(AB_zeropoint=True)``.
"""

from __future__ import annotations

from functools import cache

import astropy.units as u
import numpy as np
from astropy.constants import h as planck

from .checks import InputError, check_exptime
from .roman import throughput

_AB_REFERENCE = 3631.0 * u.Jy


@cache
def electrons_per_second_at_zero_magnitude(band: str) -> float:
    """Electrons per second from an AB magnitude 0 flat-f_nu source through ``band``."""
    curve = throughput(band)
    wavelength = curve.wavelength_nm * u.nm
    integrand = (_AB_REFERENCE / (planck * wavelength)) * (curve.effective_area_m2 * u.m**2)
    rate = np.trapezoid(integrand, wavelength)
    return float(rate.to(1 / u.s).value)


def magnitude_to_electrons(magnitude, band: str, exptime_s: float) -> np.ndarray:
    """Total electrons collected from a star of AB ``magnitude`` in ``exptime_s`` seconds."""
    m = np.asarray(magnitude, dtype=np.float64)
    if not np.all(np.isfinite(m)):
        raise InputError("magnitude", f"must be finite, got {magnitude!r}")
    return electrons_per_second_at_zero_magnitude(band) * _check_exptime(exptime_s) * 10.0 ** (-0.4 * m)


def electrons_to_magnitude(electrons, band: str, exptime_s: float) -> np.ndarray:
    """AB magnitude of a star that gives ``electrons`` in ``exptime_s`` seconds."""
    e = np.asarray(electrons, dtype=np.float64)
    if not np.all(np.isfinite(e)) or np.any(e <= 0):
        raise InputError("flux_electrons", f"must be finite and positive, got {electrons!r}")
    return 2.5 * np.log10(electrons_per_second_at_zero_magnitude(band) * _check_exptime(exptime_s) / e)


def _check_exptime(exptime_s: float) -> float:
    return check_exptime(exptime_s)
