"""AB magnitude <-> electrons through a Roman band on one detector.

Flux in electrons is the internal variable; a magnitude is only a label for it. For a source
with a flat f_nu spectrum (the AB system's reference), the electron count in exposure time t is

    N_e = t * integral f_nu / (h * lambda) * A_eff(lambda) d lambda,

photon counting through the effective area A_eff (m^2, which already holds the collecting area,
mirrors, filter and detector QE), integrated with the trapezoid rule on the data's own grid.

The AB reference flux density follows each throughput data set's own convention, so that each
reproduces its source exactly:

- "roman-2024": m_AB = -2.5 log10(f_nu / (erg s^-1 cm^-2 Hz^-1)) - 48.60 (Oke & Gunn 1983; astropy's
  ``u.ABmag``, used by synphot 1.4, which computed the official ``Roman_zeropoints_20240301.ecsv``:
  its zero point is the magnitude giving 1 count/s, ``-2.5 log10(h / integral A_eff / lambda dlambda) - 48.60``,
  the same integral as above);
- "galsim-2021": f_nu(m=0) = 3631 Jy, GalSim's ``Bandpass.withZeropoint('AB')``, so that
  ``galsim.roman.getBandpasses(AB_zeropoint=True)`` and this module give the same electrons.

The two references differ by 6.6e-5 mag (3630.78 vs 3631 Jy).
"""

from __future__ import annotations

from functools import cache

import astropy.units as u
import numpy as np
from astropy.constants import h as planck

from . import roman
from .checks import InputError, check_exptime

#: Flat-f_nu flux density of an AB magnitude 0 source, per throughput data set (see above).
AB_REFERENCE = {
    "roman-2024": (0.0 * u.ABmag).to(u.Jy),
    "galsim-2021": 3631.0 * u.Jy,
}


@cache
def electrons_per_second_at_zero_magnitude(band: str, *, sca: int, throughput: str) -> float:
    """Electrons per second from an AB magnitude 0 flat-f_nu source through ``band`` on ``sca``."""
    curve = roman.throughput(band, sca=sca, source=throughput)
    wavelength = curve.wavelength_nm * u.nm
    integrand = (AB_REFERENCE[curve.source] / (planck * wavelength)) * (curve.effective_area_m2 * u.m**2)
    rate = np.trapezoid(integrand, wavelength)
    return float(rate.to(1 / u.s).value)


def zero_point(band: str, *, sca: int, throughput: str) -> float:
    """AB magnitude that gives one electron per second (the official tables' ``ABMag``)."""
    return 2.5 * float(np.log10(electrons_per_second_at_zero_magnitude(band, sca=sca, throughput=throughput)))


def magnitude_to_electrons(magnitude, band: str, exptime_s: float, *, sca: int, throughput: str) -> np.ndarray:
    """Total electrons collected on ``sca`` from a star of AB ``magnitude`` in ``exptime_s`` seconds."""
    m = np.asarray(magnitude, dtype=np.float64)
    if not np.all(np.isfinite(m)):
        raise InputError("magnitude", f"must be finite, got {magnitude!r}")
    rate = electrons_per_second_at_zero_magnitude(band, sca=sca, throughput=throughput)
    return rate * _check_exptime(exptime_s) * 10.0 ** (-0.4 * m)


def electrons_to_magnitude(electrons, band: str, exptime_s: float, *, sca: int, throughput: str) -> np.ndarray:
    """AB magnitude of a star that gives ``electrons`` on ``sca`` in ``exptime_s`` seconds."""
    e = np.asarray(electrons, dtype=np.float64)
    if not np.all(np.isfinite(e)) or np.any(e <= 0):
        raise InputError("flux_electrons", f"must be finite and positive, got {electrons!r}")
    rate = electrons_per_second_at_zero_magnitude(band, sca=sca, throughput=throughput)
    return 2.5 * np.log10(rate * _check_exptime(exptime_s) / e)


def _check_exptime(exptime_s: float) -> float:
    return check_exptime(exptime_s)
