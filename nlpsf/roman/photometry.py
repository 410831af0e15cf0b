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

The arithmetic is in SI with the constants written out (the 2019 SI fixes h exactly), not through
astropy.units: importing astropy.units costs 0.3-0.4 s of CPU, more than a one-band simulation's
photometry is worth, in every ``nlpsf simulate`` process. ``tests/library/test_data.py`` checks the
numbers against astropy's units and constants.
"""

from __future__ import annotations

from functools import cache

import numpy as np

from nlpsf import roman
from nlpsf.checks import InputError, check_exptime

#: Planck constant [J s], exact in the SI since 2019.
PLANCK_J_S = 6.62607015e-34
#: One jansky [W m^-2 Hz^-1].
JANSKY_W_M2_HZ = 1e-26
#: Flat-f_nu flux density of an AB magnitude 0 source [W m^-2 Hz^-1], per throughput data set (see
#: above): 10^(-48.60 / 2.5) erg s^-1 cm^-2 Hz^-1 (1 erg s^-1 cm^-2 = 1e-3 W m^-2), or 3631 Jy.
AB_REFERENCE_W_M2_HZ = {
    "roman-2024": 10.0 ** (-0.4 * 48.60) * 1e-3,
    "galsim-2021": 3631.0 * JANSKY_W_M2_HZ,
}


@cache
def electrons_per_second_at_zero_magnitude(band: str, *, sca: int, throughput: str) -> float:
    """Electrons per second from an AB magnitude 0 flat-f_nu source through ``band`` on ``sca``.

    rate = f_nu / h * integral A_eff(lambda) / lambda d lambda: the integral is dimensionless in
    lambda (m^2 for the area), so the wavelength unit of the data drops out."""
    curve = roman.throughput(band, sca=sca, source=throughput)
    area_per_wavelength_m2 = np.trapezoid(curve.effective_area_m2 / curve.wavelength_nm, curve.wavelength_nm)
    return float(AB_REFERENCE_W_M2_HZ[curve.source] / PLANCK_J_S * area_per_wavelength_m2)


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
