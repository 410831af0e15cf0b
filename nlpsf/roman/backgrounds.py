"""Sky, thermal and dark backgrounds and read noise of the Roman WFI, from the official data.

Every number comes from STScI's ``roman-technical-information`` 1.5.0 (vendored in
``nlpsf/data/roman_technical_information``, see ``nlpsf/data/SOURCES.md``):

- zodiacal light: count rate per native pixel at the *minimum* zodiacal light, per filter
  (``zodiacal_light.ecsv``). The official sensitivity tables (``AB_mag_limiting_sensitivity.ecsv``)
  assume twice the minimum, "roughly equivalent to that obtained at an ecliptic latitude of 25
  degrees at a Solar elongation of 90 degrees": that is the typical level here. Brighter sky (near
  the ecliptic, small elongation) is a larger factor, which the official data do not tabulate: pass
  it as ``zodiacal_factor``;
- internal thermal background per filter (``internal_thermal_backgrounds.ecsv``): negligible in the
  blue filters, 1.03 e-/s in W146 and 4.38 e-/s in K213;
- dark current per SCA, the TVAC2 median (``WFI_Dark_current_summary.ecsv``; the README notes these
  include the instrument's internal thermal background of the dark element, so they are an upper
  bound on the detector's own dark current);
- CDS noise per SCA (``WFI_CDS_Noise_summary.ecsv``, median): the noise of the difference of two
  reads, so one read's noise is CDS / sqrt(2) (independent reads); the total noise of a ~170 s
  55-read ramp fit (``WFI_Total_noise.ecsv``) is given for comparison.

The files write the rates as "ct / pix" and describe them as count rates per pixel; counts are
detected photons, i.e. electrons, per second. The FPS tables number detectors by their SCU (the
focal-plane position 1-18, what GalSim and nlpsf call the SCA); the "SCA" column there is the
detector's serial number.

Backgrounds are e- per *native* pixel over the exposure. On the oversampled grid each fine pixel
holds the charge a native pixel would (DESIGN.md), so the same number is added to every fine pixel.
"""

from __future__ import annotations

import csv
import math
from dataclasses import asdict, dataclass
from functools import cache, lru_cache

import numpy as np

from nlpsf import roman
from nlpsf.checks import InputError, check_exptime, check_full_well, check_number

#: Named background presets: zodiacal light as a multiple of its minimum, plus thermal and dark.
#: "none" is the paper's noiseless scene.
PRESETS: dict[str, dict] = {
    "none": {"zodiacal_factor": 0.0, "thermal": False, "dark": False},
    "roman-minimum": {"zodiacal_factor": 1.0, "thermal": True, "dark": True},
    "roman-typical": {"zodiacal_factor": 2.0, "thermal": True, "dark": True},
}
DEFAULT_PRESET = "roman-typical"
SOURCE_VERSION = "roman-technical-information 1.5.0 (zodiacal light and thermal 2024-06-03; TVAC2 dark current and noise)"


@cache
def _rate_by_filter(name: str) -> dict[str, float]:
    from astropy.table import Table  # only the background presets need it

    table = Table.read(roman.official_data_dir() / name, format="ascii.ecsv")
    return {str(f).strip(): float(r) for f, r in zip(table["filter"], table["rate"], strict=True)}


@cache
def _per_sca(name: str, column: str) -> tuple[float, ...]:
    # The per-SCA summaries are ECSV whose body is comma-separated under a header row: the standard
    # library reads it, so a ramp's default read noise costs no astropy import (tests/library/test_backgrounds.py
    # checks this reading against astropy's ECSV reader).
    with open(roman.official_data_dir() / name, newline="") as handle:
        rows = list(csv.reader(line for line in handle if line.strip() and not line.startswith("#")))
    header = [name.strip() for name in rows[0]]
    index = header.index(column)
    values = {int(row[0]): float(row[index]) for row in rows[1:] if row[0].strip().isdigit()}
    return tuple(values[s] for s in range(1, roman.N_SCA + 1))


def zodiacal_rate(band: str, factor: float = 2.0) -> float:
    """Zodiacal light [e-/s per native pixel] at ``factor`` times its minimum."""
    return _zodiacal_rate(roman.check_band(band), check_number(factor, "zodiacal_factor", 0.0, 100.0))


def thermal_rate(band: str) -> float:
    """Internal thermal background [e-/s per native pixel] of ``band``'s filter."""
    return _thermal_rate(roman.check_band(band))


# The rates of a band already checked (``background`` checks its arguments once, then reads these).
def _zodiacal_rate(band: str, factor: float) -> float:
    return factor * _rate_by_filter("zodiacal_light.ecsv")[roman.OFFICIAL_FILTER_NAMES[band]]


def _thermal_rate(band: str) -> float:
    return _rate_by_filter("internal_thermal_backgrounds.ecsv")[roman.OFFICIAL_FILTER_NAMES[band]]


def dark_rate(sca: int) -> float:
    """Median dark current of ``sca`` [e-/s per pixel] (TVAC2, 89.5 K)."""
    return _per_sca("WFI_Dark_current_summary.ecsv", "Dark Current - Median")[roman.check_sca(sca) - 1]


def cds_noise(sca: int) -> float:
    """Median correlated-double-sampling noise of ``sca`` [e-]: the noise of a two-read difference."""
    return _per_sca("WFI_CDS_Noise_summary.ecsv", "CDS Noise - Median")[roman.check_sca(sca) - 1]


def read_noise(sca: int) -> float:
    """Noise of one read of ``sca`` [e-], CDS / sqrt(2): what a ramp fit's weights need per read."""
    return cds_noise(sca) / math.sqrt(2.0)


def total_noise(sca: int) -> float:
    """Median total noise of ``sca`` [e-] for the official ~170 s, 55-read dark ramp (for comparison)."""
    return _per_sca("WFI_Total_noise.ecsv", "Total noise - median")[roman.check_sca(sca) - 1]


@dataclass(frozen=True)
class Background:
    """Background charge per native pixel over one exposure, by component [e-]."""

    preset: str
    band: str
    sca: int
    exptime_s: float
    zodiacal_factor: float
    zodiacal_e: float
    thermal_e: float
    dark_e: float

    @property
    def total_e(self) -> float:
        return self.zodiacal_e + self.thermal_e + self.dark_e

    def to_dict(self) -> dict:
        return {**asdict(self), "total_e": self.total_e, "source": SOURCE_VERSION}


def check_preset(name: str) -> str:
    if name not in PRESETS:
        raise InputError(
            "background", f"unknown background preset {name!r}; choose one of {', '.join(PRESETS)} or give e- per pixel"
        )
    return name


def background(preset: str, band: str, sca: int, exptime_s: float, zodiacal_factor: float | None = None) -> Background:
    """Background of the named preset for ``band`` on ``sca`` over ``exptime_s`` seconds.

    ``zodiacal_factor`` overrides the preset's multiple of the minimum zodiacal light.
    """
    spec = PRESETS[check_preset(preset)]
    band, sca = roman.check_band(band), roman.check_sca(sca)
    exptime_s = check_exptime(exptime_s)
    factor = spec["zodiacal_factor"] if zodiacal_factor is None else zodiacal_factor
    factor = check_number(factor, "zodiacal_factor", 0.0, 100.0)
    return Background(
        preset=preset,
        band=band,
        sca=sca,
        exptime_s=exptime_s,
        zodiacal_factor=float(factor),
        zodiacal_e=_zodiacal_rate(band, factor) * exptime_s,
        thermal_e=_thermal_rate(band) * exptime_s if spec["thermal"] else 0.0,
        dark_e=dark_rate(sca) * exptime_s if spec["dark"] else 0.0,
    )


@lru_cache(maxsize=4096)
def background_electrons(preset: str, band: str, sca: int, exptime_s: float) -> float:
    """Total background [e- per native pixel over the exposure] of a preset: what a scene adds
    (kept per arguments: every request of an SCA and exposure reads the same)."""
    return background(preset, band, sca, exptime_s).total_e


def saturation_shift_mag(background_e: float, full_well_e: float) -> float:
    """How much fainter a star saturates when ``background_e`` already fills part of the well.

    The brightest pixel holds star + background; it reaches the full well when the star's share is
    full_well - background, so the saturation magnitude moves by -2.5 log10(1 - background / full_well).
    """
    full_well_e = check_full_well(full_well_e)
    background_e = check_number(background_e, "background", 0.0, full_well_e)
    if background_e == full_well_e:
        raise InputError("background", "the background alone fills the full well: every pixel is saturated")
    return float(-2.5 * np.log10(1.0 - background_e / full_well_e))


def resolve(spec: str | float, band: str, sca: int, exptime_s: float) -> float:
    """A scene's background [e- per native pixel]: a preset's name, or a number of electrons.

    What a ``--background`` option (CLI) or ``background`` field (service) can pass straight through:
    "roman-typical", "none", or "120" / 120.0 electrons.
    """
    if isinstance(spec, str) and spec in PRESETS:
        return background_electrons(spec, band, sca, exptime_s)
    if isinstance(spec, str):
        try:
            spec = float(spec)
        except ValueError:
            raise InputError("background", f"give e- per pixel or one of {', '.join(PRESETS)}, got {spec!r}") from None
    return check_number(spec, "background", 0.0, 1e9)
