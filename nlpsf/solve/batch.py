"""Answers at table cost: the solver's own answer (``solver.answer``) where the shipped tables or
the Roman default's field grid cover the request, and a refusal naming why where it would simulate.

A batch (the service's ``POST /api/v1/solve/batch``, the page's CSV) answers many requests in one
call inside the HTTP worker, so it may not start a fresh simulation (seconds each): the service
sends those to ``POST /api/v1/solve``, which runs them as jobs under its limits. What a batch
answers is exactly what a single solve answers for the same request -- the same function, the same
conditions and uncertainty -- because there is no second path: :func:`answer_from_tables` is
``solver.answer`` with ``simulate=False``.

Two refusals, one before and one during the answer, both :class:`NeedsSimulation` with the
provider's refusal (its code, the field at fault, why):

- before: the plan (``solver.table_plan``: the first slope provider that covers the request) is
  the simulator's -- an accuracy target (its effects are measured by simulation), a simulating level, a
  scene, pupil rule, state, exposure or beta0 the tables and the grid do not hold;
- during: a magnitude brighter than a grid node's magnitudes is found only while the answer reads
  the slopes (fainter ones follow the flux law from the grid's faint end); a plan made with
  ``simulate=False`` makes the slopes refuse it before the simulator is loaded, so a refused row
  costs table time only.
"""

from __future__ import annotations

from nlpsf.slopes.providers import NeedsSimulation

__all__ = ["NeedsSimulation", "answer_from_tables"]


def answer_from_tables(request, tables_set=None):
    """``solver.answer(request)`` where it reads tables or the field grid only; else
    :class:`NeedsSimulation` naming the field and why, raised before any simulation starts
    (``solver.table_plan``)."""
    from . import solver

    return solver.answer(request, tables_set, simulate=False)
