"""The refusal to simulate: inside :func:`no_simulation` a solve that would start a fresh
simulation raises :class:`NeedsSimulation` instead, before the simulator is loaded.

Its own module, below the solver: the slope source (``slope_source.Slopes._simulate``) asks
:func:`check_simulation_allowed` before it simulates, and ``nlpsf.solve.batch`` (above the solver) sets it.
"""

from __future__ import annotations

import contextlib
import contextvars

from nlpsf.checks import InputError

#: What a refusal says after its reason.
REFUSAL = "an answer at table cost does not run simulations"


class NeedsSimulation(InputError):
    """The request is valid, but its answer needs a fresh simulation: not at table cost."""


_REFUSING: contextvars.ContextVar[bool] = contextvars.ContextVar("nlpsf_refuse_simulation", default=False)


@contextlib.contextmanager
def no_simulation():
    """Within the block (this thread or task), a solve that would simulate raises :class:`NeedsSimulation`."""
    token = _REFUSING.set(True)
    try:
        yield
    finally:
        _REFUSING.reset(token)


def check_simulation_allowed(magnitude: float) -> None:
    """Called by the slope source before it simulates; refuses inside :func:`no_simulation`."""
    if _REFUSING.get():
        raise NeedsSimulation(
            "magnitude",
            f"the slope at m={magnitude:.4g} is outside what the tables and the Roman default's field grid hold "
            f"(a magnitude brighter than a node's grid), so it would be simulated: {REFUSAL}",
        )
