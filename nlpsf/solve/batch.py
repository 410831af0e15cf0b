"""Answers at table cost: the solver's own answer (``solver.answer``) where the shipped tables or
the Roman default's field grid hold the request, and a refusal naming why where it would simulate.

A batch (the service's ``POST /api/v1/solve/batch``, the page's CSV) answers many requests in one
call inside the HTTP worker, so it may not start a fresh simulation (seconds each): the service
sends those to ``POST /api/v1/solve``, which runs them as jobs under its limits. What a batch
answers is exactly what a single solve answers for the same request -- the same function, the same
conditions and uncertainty -- because there is no second path: :func:`answer_from_tables` checks,
then calls ``solver.answer``.

Two checks, one before and one during the answer:

- :func:`simulation_needed` reads the solver's own plan (``solver.plan``) for the request, or for
  every node of the SCA range when the Roman default has no position: an accuracy target (its
  effects are measured by simulation), a simulating level, a scene, pupil rule, state, exposure or
  beta0 the tables and the grid do not hold, all say so before anything runs;
- a magnitude brighter than a grid node's magnitudes is found only while the answer reads the slopes
  (fainter ones follow the flux law from the grid's faint end); :func:`no_simulation` makes the
  slope source refuse it (``slope_source.Slopes._simulate`` asks ``simulation_guard``) before the
  simulator is loaded, so a refused row costs table time only.
"""

from __future__ import annotations

from dataclasses import replace

from nlpsf.slopes.guard import REFUSAL, NeedsSimulation, no_simulation

__all__ = ["NeedsSimulation", "answer_from_tables", "simulation_needed"]


def simulation_needed(request, tables_set=None) -> tuple[str, str] | None:
    """(field, why) when answering ``request`` (``nlpsf.request.resolve.SolveRequest``) would simulate
    before reading its slopes; None when the solver's plan reads tables or the field grid only."""
    from nlpsf.request import presets as roman_default

    from . import solver
    from .over_field import range_positions

    if request.accuracy is not None:
        return "accuracy", f"an accuracy target is met by measuring the scene's effects in fresh simulations: {REFUSAL}"
    default = request.preset == roman_default.NAME
    if not default and request.ramp is not None:
        # The paper's scene up the ramp maps onto the tables only for some fits and magnitudes.
        return "ramp", f"a ramp on the paper's scene is simulated where the tables do not map it exactly: {REFUSAL}"
    if default and request.scene.position is None:
        # The SCA range: every node's answer must come from the grid.
        requests = [request.with_changes(scene=replace(request.scene, position=p)) for p in range_positions(request)]
    else:
        requests = [request]
    for one in requests:
        the_plan = solver.plan(one, tables_set)
        if the_plan.fidelity != "table":
            return _field_of(one, the_plan), _why(the_plan)
    return None


def _simulated_codes():
    """The plan's notes that say a table-level request is simulated instead."""
    from nlpsf.flags import FlagCode

    return {FlagCode.SCENE_SIMULATED, FlagCode.PUPIL_SCALE_SIMULATED, FlagCode.DEFAULT_SIMULATED, FlagCode.LINEARISED_SIMULATED}


def _field_of(request, the_plan) -> str:
    """The request field that takes the answer off the tables, as a refusal names it."""
    import math

    from nlpsf.flags import FlagCode
    from nlpsf.request import presets as roman_default

    if request.fidelity not in (None, "table"):
        return "fidelity"
    if request.preset == roman_default.NAME:
        own = roman_default.readout(request.band, request.sca).exptime_s
        if not math.isclose(request.exptime, own, rel_tol=1e-9):
            return "exptime"  # the grid holds the default's own exposure (its sky too is over that exposure)
    for note in the_plan.notes:
        code = getattr(note, "code", None)
        if code == FlagCode.PUPIL_SCALE_SIMULATED:
            return "pupil_scale"
        if code == FlagCode.LINEARISED_SIMULATED:
            return "linearise_at"
        if code == FlagCode.DEFAULT_SIMULATED:
            why = str(note.values.get("why", ""))
            if "readout" in why:
                return "ramp"
            for name, said in (("exptime", "exptime_s"), ("beta0", "beta0"), ("full_well", "full_well_e"),
                               ("pupil_scale", "pupil_scale"), ("linearise_at", "linearise_at"),
                               ("throughput", "throughput")):  # fmt: skip
                if f"grid's {said} " in why or (name == "throughput" and "throughput" in why):
                    return name
    return "scene"


def _why(the_plan) -> str:
    codes = _simulated_codes()
    notes = "; ".join(str(n) for n in the_plan.notes if getattr(n, "code", None) in codes)
    return f"it needs a fresh simulation ({notes or 'fidelity ' + the_plan.fidelity}): {REFUSAL}"


def answer_from_tables(request, tables_set=None):
    """``solver.answer(request)`` where it reads tables or the field grid only; else
    :class:`NeedsSimulation` naming the field and why, raised before any simulation starts."""
    from . import solver

    needed = simulation_needed(request, tables_set)
    if needed is not None:
        raise NeedsSimulation(*needed)
    with no_simulation():
        return solver.answer(request, tables_set)
