"""nlpsf: how well must the nonlinearity of a Roman detector be calibrated for PSF modelling?

The library behind the tool: the Roman WFI PSF through a nonlinear detector measured with adaptive
moments (``experiment``), slope tables and fits (``tables``), and the two-of-three requirement
calculator (``solver``). See ``README.md`` and Plazas et al. (2016).

The public API is importable from here (``from nlpsf import solve, simulate, slopes, load_tables,
SimulationConfig``; a solve as a typed request: ``answer(SolveRequest(...))``); each name is
imported on first use, so ``import nlpsf`` stays cheap.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING, Any

from ._version import __version__

#: public name -> module that defines it
_PUBLIC = {
    "solve": "nlpsf.solver",
    "Solution": "nlpsf.solution",
    "Uncertainty": "nlpsf.solution",
    "SolveRequest": "nlpsf.request",
    "answer": "nlpsf.solver",
    "FlagCode": "nlpsf.flags",
    "simulate": "nlpsf.experiment",
    "slopes": "nlpsf.experiment",
    "prepare": "nlpsf.experiment",
    "SimulationConfig": "nlpsf.experiment",
    "load_tables": "nlpsf.tables",
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
    from .experiment import SimulationConfig, prepare, simulate, slopes
    from .flags import FlagCode
    from .request import SolveRequest
    from .solution import Solution, Uncertainty
    from .solver import answer, solve
    from .tables import load_tables


def __getattr__(name: str) -> Any:
    if name in _PUBLIC:
        value = getattr(import_module(_PUBLIC[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'nlpsf' has no attribute {name!r}")
