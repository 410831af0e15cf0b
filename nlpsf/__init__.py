"""nlpsf: how well must the nonlinearity of a Roman detector be calibrated for PSF modelling?

The library behind the tool, in the order a request flows: the Roman data and instrument
(``nlpsf.roman``), the simulator (``nlpsf.sim``: the Roman WFI PSF through a nonlinear detector
measured with adaptive moments), a request resolved once (``nlpsf.request``), where slopes come
from (``nlpsf.slopes``: the paper's tables, the field grid, the simulator) and the two-of-three
requirement calculator (``nlpsf.solve``). See ``README.md`` and Plazas et al. (2016).

The public API is importable from here (``from nlpsf import solve, simulate, slopes, load_tables,
SimulationConfig``; a solve as a typed request: ``answer(SolveRequest(...))``); each name is
imported on first use, so ``import nlpsf`` stays cheap.

``nlpsf.solve`` and ``nlpsf.slopes`` are the public functions, as they always were; the subpackages
of the same names are reached by import (``from nlpsf.solve import solver``), never as attributes.
"""

from __future__ import annotations

import sys
from importlib import import_module
from types import ModuleType
from typing import TYPE_CHECKING, Any

from ._version import __version__

#: public name -> module that defines it
_PUBLIC = {
    "solve": "nlpsf.solve.solver",
    "Solution": "nlpsf.solve.solution",
    "Uncertainty": "nlpsf.solve.solution",
    "SolveRequest": "nlpsf.request.resolve",
    "answer": "nlpsf.solve.solver",
    "FlagCode": "nlpsf.flags",
    "simulate": "nlpsf.sim.experiment",
    "slopes": "nlpsf.sim.experiment",
    "prepare": "nlpsf.sim.experiment",
    "SimulationConfig": "nlpsf.sim.experiment",
    "load_tables": "nlpsf.slopes.tables",
    "InputError": "nlpsf.checks",
    "SimulationError": "nlpsf.checks",
}

__all__ = [
    "FlagCode",
    "InputError",
    "SimulationConfig",
    "SimulationError",
    "Solution",
    "SolveRequest",
    "Uncertainty",
    "__version__",
    "answer",
    "load_tables",
    "prepare",
    "simulate",
    "slopes",
    "solve",
]

if TYPE_CHECKING:
    from .checks import InputError, SimulationError
    from .flags import FlagCode
    from .request.resolve import SolveRequest
    from .sim.experiment import SimulationConfig, prepare, simulate, slopes
    from .slopes.tables import load_tables
    from .solve.solution import Solution, Uncertainty
    from .solve.solver import answer, solve


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        value = getattr(import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'nlpsf' has no attribute {name!r}")


#: Public functions that share their name with a subpackage.
_FUNCTIONS_NAMED_AS_PACKAGES = frozenset({"solve", "slopes"})


class _Package(ModuleType):
    """``nlpsf`` itself: importing the subpackage ``nlpsf.solve`` (or ``nlpsf.slopes``) does not
    rebind the public function of that name (Python binds a subpackage on its parent when it is
    first imported)."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name in _FUNCTIONS_NAMED_AS_PACKAGES and isinstance(value, ModuleType):
            return
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Package
