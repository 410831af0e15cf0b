"""Speed versus accuracy: the fidelity levels, what each one simulates, and their measured errors.

The one owner of "fidelity level -> simulation settings". Levels, cheapest first:

- ``table``: the shipped slope tables (achromatic PSF at the band's effective wavelength,
  100 centroids, linear response at beta0, cubic interpolation);
- ``linear``: a fresh linear-response simulation at the request's conditions (achromatic);
- ``monte_carlo``: a fresh Monte Carlo, the paper's finite differences over beta0 * (1 +- 1%) and
  per-pixel beta maps for the scatter (achromatic);
- ``polychromatic``: the Monte Carlo with the PSF integrated over the band (8 wavelengths,
  flat f_nu star), which the paper did not have.

Each level's relative error against a more exact reference is measured by ``nlpsf tradeoff``
(``nlpsf.slopes.tradeoff``) and shipped in ``nlpsf/data/fidelity.json``; ``accuracy`` in the solver
picks the cheapest level whose measured error meets it. This module is light (json only).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path

from nlpsf.checks import InputError, SimulationError, check_number
from nlpsf.defaults import ACCURACY_RANGE
from nlpsf.flags import FlagCode, make

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


def _fidelity_path() -> Path:
    return Path(str(resources.files("nlpsf") / "data" / "fidelity.json"))


@lru_cache(maxsize=1)
def measured() -> dict:
    """The stored tradeoff measurement (``nlpsf tradeoff --write``)."""
    path = _fidelity_path()
    if not path.exists():
        raise SimulationError("no measured fidelity errors are shipped; run `nlpsf tradeoff --write`")
    return json.loads(path.read_text())


#: ``measured()`` keys: the paper scene's measurement is the file's top level (as it always was);
#: the Roman default's sits under ``"roman"`` with the same structure (``tradeoff(default="roman")``).
DEFAULT_SCENES = ("paper", "roman")


def measured_for(default: str = "paper") -> dict:
    """The tradeoff measurement for a default scene: "paper" (the top level) or "roman"."""
    if default not in DEFAULT_SCENES:
        raise InputError("default", f"must be one of {', '.join(DEFAULT_SCENES)}, got {default!r}")
    data = measured()
    if default == "paper":
        return data
    if "roman" not in data:
        raise SimulationError("no fidelity errors are shipped for the Roman default; run `nlpsf tradeoff --scene roman --write`")
    return data["roman"]


def level_error(band: str, metric: str, mode: str, level: str, default: str = "paper") -> float:
    """Measured relative error of ``level`` on this band's slopes (worst of its test points)."""
    return float(measured_for(default)["errors"][band][mode][metric][level])


def cheapest_meeting(accuracy: float, band: str, metric: str, mode: str, default: str = "paper") -> tuple[str, str]:
    """The cheapest level whose measured relative error on this band is below ``accuracy``
    (``default``: the scene's measurement, :func:`measured_for`)."""
    data = measured_for(default)
    errors = data["errors"][band][mode][metric]
    for level in LEVELS:
        if errors[level] <= accuracy:
            return level, make(
                FlagCode.FIDELITY_CHOSEN,
                level=level,
                accuracy=accuracy,
                band=band,
                metric=metric,
                mode=mode,
                error=errors[level],
                date=data["date"],
            )
    best = min(LEVELS, key=lambda level: errors[level])
    return best, make(
        FlagCode.FIDELITY_NONE_MEETS, accuracy=accuracy, band=band, metric=metric, mode=mode, level=best, error=errors[best]
    )


def write_measured(result: dict, default: str = "paper") -> Path:
    """Store a tradeoff measurement where ``measured`` reads it: the paper scene's as the file's top
    level (keeping a stored Roman one), the Roman default's under ``"roman"`` (keeping the rest)."""
    path = _fidelity_path()
    if default == "roman":
        data = json.loads(path.read_text()) if path.exists() else {}
        data["roman"] = result
    else:
        data = dict(result)
        if path.exists() and "roman" in (old := json.loads(path.read_text())):
            data["roman"] = old["roman"]
    path.write_text(json.dumps(data, indent=1) + "\n")
    measured.cache_clear()
    return path


def choose_fidelity(
    level: str | None, accuracy: float | None, band: str, metric: str, mode: str, default: str = "paper"
) -> tuple[str, list[str]]:
    """The fidelity level a solve uses (``accuracy`` picks the cheapest meeting it), and a note on why."""
    if accuracy is None:
        return check_level(level or "table"), []
    accuracy = check_number(accuracy, "accuracy", *ACCURACY_RANGE)
    chosen, note = cheapest_meeting(accuracy, band, metric, mode, default)
    return chosen, [note]


def fidelity_error(level: str, band: str, metric: str, mode: str, default: str = "paper") -> tuple[float | None, str | None]:
    """The level's measured relative error on this slope (``nlpsf tradeoff``), or why it is unknown;
    ``default``: the scene's measurement ("paper" or "roman")."""
    try:
        return level_error(band, metric, mode, level, default), None
    except (SimulationError, KeyError):
        return None, make(FlagCode.FIDELITY_ERROR_UNKNOWN)
