"""The fidelity levels and what each one simulates (the one owner of "fidelity level -> simulation
settings"). Levels, cheapest first:

- ``table``: the shipped slope tables (achromatic PSF at the band's effective wavelength,
  100 centroids, linear response at beta0, cubic interpolation);
- ``linear``: a fresh linear-response simulation at the request's conditions (achromatic);
- ``monte_carlo``: a fresh Monte Carlo, the paper's finite differences over beta0 * (1 +- 1%) and
  per-pixel beta maps for the scatter (achromatic);
- ``polychromatic``: the Monte Carlo with the PSF integrated over the band (8 wavelengths,
  flat f_nu star), which the paper did not have.

Each level's measured error against a more exact reference is ``nlpsf.slopes.fidelity``'s.
"""

from __future__ import annotations

from dataclasses import dataclass

from nlpsf.checks import InputError

LEVELS: tuple[str, ...] = ("table", "linear", "monte_carlo", "polychromatic")
#: Levels that run a simulation (everything but the table look-up).
SIMULATION_LEVELS: tuple[str, ...] = LEVELS[1:]
#: Wavelengths across the band of the polychromatic level.
POLYCHROMATIC_WAVELENGTHS = 8


@dataclass(frozen=True)
class LevelSettings:
    """What a simulating level runs: the experiment's method and the wavelengths of the PSF."""

    method: str
    n_wavelengths: int


def check_level(level: str, name: str = "fidelity") -> str:
    if level not in LEVELS:
        raise InputError(name, f"must be one of {', '.join(LEVELS)}, got {level!r}")
    return level


def simulation_settings(level: str, n_wavelengths: int | None = None) -> LevelSettings:
    """The simulation a level runs. ``n_wavelengths`` overrides the polychromatic default and is
    refused for the achromatic levels (they are defined by one wavelength)."""
    check_level(level)
    if level == "table":
        raise InputError("fidelity", "the table level runs no simulation; choose linear, monte_carlo or polychromatic")
    if level == "polychromatic":
        waves = POLYCHROMATIC_WAVELENGTHS if n_wavelengths is None else int(n_wavelengths)
        if waves < 2:
            raise InputError("n_wavelengths", f"a polychromatic PSF needs at least 2 wavelengths, got {waves}")
        return LevelSettings("monte_carlo", waves)
    if n_wavelengths not in (None, 1):
        raise InputError("n_wavelengths", f"only the polychromatic fidelity integrates over wavelengths; got {n_wavelengths}")
    return LevelSettings("linear" if level == "linear" else "monte_carlo", 1)


def level_name(method: str, n_wavelengths: int) -> str:
    """How a simulation's own settings are reported (``monte_carlo+polychromatic``, ...)."""
    return f"{method}{'+polychromatic' if n_wavelengths > 1 else ''}"
