"""Speed versus accuracy: the fidelity levels' measured errors (the levels and what each one
simulates are ``nlpsf.sim.levels``'s).

Each level's relative error against a more exact reference is measured by ``nlpsf tradeoff``
(``nlpsf.solve.tradeoff``) and shipped in ``nlpsf/data/fidelity.json``; ``accuracy`` in the solver
picks the cheapest level whose measured error meets it. This module is light (json only).
"""

from __future__ import annotations

import json
from functools import lru_cache
from importlib import resources
from pathlib import Path

from nlpsf.checks import InputError, SimulationError, check_number
from nlpsf.defaults import ACCURACY_RANGE
from nlpsf.flags import FlagCode, make

# The levels are the simulator's (``nlpsf.sim.levels``); the calculator reads them with their errors here.
from nlpsf.sim.levels import (  # noqa: F401
    LEVELS,
    POLYCHROMATIC_WAVELENGTHS,
    SIMULATION_LEVELS,
    LevelSettings,
    check_level,
    level_name,
    simulation_settings,
)


def _fidelity_path() -> Path:
    return Path(str(resources.files("nlpsf") / "data" / "fidelity.json"))


@lru_cache(maxsize=1)
def measured() -> dict:
    """The stored tradeoff measurement (``nlpsf tradeoff --write``)."""
    path = _fidelity_path()
    if not path.exists():
        raise SimulationError("no measured fidelity errors are shipped; run `nlpsf tradeoff --write`")
    return json.loads(path.read_text())


#: Where ``measured()`` holds each default scene's measurement: the paper scene's is the file's top
#: level (None; as it always was), the Roman default's sits under ``"roman"`` with the same structure
#: (``tradeoff(default="roman")``).
STORED_UNDER = {"paper": None, "roman": "roman"}
DEFAULT_SCENES = tuple(STORED_UNDER)


def measured_for(default: str = "paper") -> dict:
    """The tradeoff measurement for a default scene: "paper" (the top level) or "roman"."""
    if default not in STORED_UNDER:
        raise InputError("default", f"must be one of {', '.join(DEFAULT_SCENES)}, got {default!r}")
    data, under = measured(), STORED_UNDER[default]
    if under is None:
        return data
    if under not in data:
        raise SimulationError(f"no fidelity errors are shipped for {default!r}; run `nlpsf tradeoff --scene {default} --write`")
    return data[under]


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
    old = json.loads(path.read_text()) if path.exists() else {}
    under = STORED_UNDER[default]
    if under is not None:
        data = {**old, under: result}
    else:  # the top level, keeping every section stored under a name
        data = dict(result) | {name: old[name] for name in STORED_UNDER.values() if name is not None and name in old}
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
