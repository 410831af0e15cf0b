"""Answers over the field: the worst of an SCA's centre and four corners (or of the focal plane's
18 SCAs), from the shipped field-point tables where they hold the request, else simulated."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

from nlpsf import roman
from nlpsf.checks import InputError
from nlpsf.flags import FlagCode, make
from nlpsf.frozen import replaced
from nlpsf.serialise import json_number
from nlpsf.slopes.providers import field_tables

from .solution import Solution


@dataclass(frozen=True)
class _Where:
    band: str
    sca: int


def field_points(sca: int) -> list[tuple[float, float]]:
    """Where ``solve_over_field`` looks on an SCA: its centre and the four corner field points
    (``roman.field_points`` 1-4). The Zernikes are interpolated bilinearly between the corners, so
    every coefficient takes its extremes there; the centre is where the SCA-centre tables are."""
    centre = (roman.SCA_PIXELS / 2, roman.SCA_PIXELS / 2)
    return [centre, *roman.field_points(sca)[1:]]


def over_field_from_tables(scene=None, fidelity: str | None = None, accuracy: float | None = None, ramp=None) -> bool:
    """Whether ``solve_over_field`` answers such a request from the tables alone (milliseconds, no
    simulation): the paper's scene, the table level, no accuracy to measure, no ramp, and the
    field-point tables installed."""
    plain = (scene is None or scene.no_effects) and ramp is None and accuracy is None
    return plain and fidelity in (None, "table") and field_tables() is not None


def worst_over_field(
    solve, band: str, scas="all", scene=None, progress=None, filled_for: int | None = None, **request
) -> Solution:
    """The answer for the worst position over the given SCAs (``"all"``: the 18 of the focal plane):
    the Roman default's field-grid nodes (:func:`range_positions`), another scene's centre and four
    corners. At the table level it reads the default's grid or the paper's field-point tables.
    A scene with other effects, or a simulating fidelity, simulates every point (linear response unless another level is asked
    for; seconds per point). Worst means the most demanding answer: the smallest precision, the
    largest tolerance, or the faintest brightest-usable magnitude. The Solution returned is that
    point's, with every point's value in ``conditions["over_field"]`` and where the worst lies in a
    flag. ``solve`` is ``nlpsf.solve.solver.solve`` (passed in: this module sits below the solver).

    ``filled_for``: the SCA whose Roman-default conditions the ``scene`` and ``ramp`` given were
    filled with (the request's own SCA; ``SolveRequest`` fills them): its sky over the exposure
    and its official read noise. Every other SCA gets its own instead (:func:`own_conditions`);
    what the caller set (a background, a read noise) stays. None: nothing was filled.
    """

    from nlpsf.request import presets as roman_default
    from nlpsf.sim import scene as scenes

    chosen = list(range(1, roman.N_SCA + 1)) if scas == "all" else [roman.check_sca(s) for s in scas]
    preset = request.get("preset") or (scene if isinstance(scene, str) else None)
    if isinstance(scene, str):
        scene = None
    request["preset"] = preset = roman_default.preset_of(scene, preset)
    default = roman_default.policy(preset).field_grid
    base = scene if scene is not None else (roman_default.preset_scene(preset) or scenes.SceneModel())
    if base is not None and base.position is not None:
        raise InputError("position", "give a position or ask for the worst over the field, not both")
    answers = []
    points = _points_over_field(band, chosen, default, base, request)
    for index, (sca, position) in enumerate(points):
        if progress:
            progress(index, len(points), f"SCA {sca} at {position[0]:.0f},{position[1]:.0f}")
        # The default's own scene at bg 0 is filled by the request with that SCA's sky.
        point_scene = roman_default.scene(position, 0.0) if default and scene is None else replace(base, position=position)
        point_request = request
        if default and filled_for is not None and sca != filled_for:
            point_scene, point_request = own_conditions(point_scene, request, band, filled_for, sca)
        answers.append((sca, position, solve(band, sca, scene=point_scene, **point_request)))
    if progress:
        progress(len(points), len(points), "done")
    solved = answers[0][2].solved_for
    demand = _demand(solved)  # the most demanding answer, as the SCA range ranks its nodes
    sca, position, worst = max(answers, key=lambda item: demand(item[2]))
    values = [getattr(a[2], solved) for a in answers]
    finite = [v for v in values if v is not None and math.isfinite(v)]
    conditions = dict(worst.conditions)
    conditions["over_field"] = [
        {"sca": s, "position": list(p), solved: json_number(getattr(a, solved)), "uncertainty": json_number(a.uncertainty)}
        for s, p, a in answers
    ]
    where = "all 18 SCAs" if scas == "all" else "SCA " + ", ".join(map(str, chosen))
    flag = make(
        FlagCode.WORST_OVER_FIELD,
        points=len(points),
        where=where,
        sca=sca,
        x=position[0],
        y=position[1],
        solved=solved,
        low=min(finite),
        high=max(finite),
    )
    return replace(worst, flags=[flag, *worst.flags], conditions=conditions)


def _points_over_field(band: str, chosen: list[int], default: bool, base, request: dict) -> list[tuple[int, tuple]]:
    """(SCA, position) of every point :func:`worst_over_field` answers: the Roman default's field-grid
    nodes (read from the shipped grid where it holds them, else simulated by the solver, which says
    so), another scene's centre and four corners (each corner's own table is found by ``solve`` from
    the position: ``providers.PaperTables``; without field-point tables, or with a scene they do not
    hold, every point is simulated: ``request["fidelity"]`` becomes "linear")."""
    if default:
        return [(sca, position) for sca in chosen for position in range_positions(_Where(band, sca))]
    corners = field_tables() if base.no_effects and request.get("tables_set") is None else None
    if corners is None and request.get("fidelity") in (None, "table"):
        request["fidelity"] = "linear"
    return [(s, p) for s in chosen for p in field_points(s)]


def own_conditions(scene, request: dict, band: str, filled_for: int, sca: int) -> tuple[object, dict]:
    """(scene, request) for ``sca`` where they hold what the Roman default filled in for the SCA
    ``filled_for``: its sky over the exposure (``roman_default.fill``, the owner of the default's
    values, with ``backgrounds``) becomes ``sca``'s, and a ramp with that SCA's official read noise
    (``ramps.build``) gets ``sca``'s. A background or read noise the caller gave is kept: it is
    recognised as filled only when it is exactly what the same functions fill for ``filled_for``."""
    from nlpsf.request import presets as roman_default
    from nlpsf.sim import ramps

    exptime, ramp = request.get("exptime"), request.get("ramp")
    there = roman_default.default_fill(band, filled_for, exptime, ramp)
    here = roman_default.default_fill(band, sca, exptime, ramp)
    if scene is not None and math.isclose(scene.background_e, there.background_e, rel_tol=1e-12, abs_tol=0.0):
        scene = replace(scene, background_e=here.background_e)
    if ramp is not None:
        rules = {"saturation": ramp.saturation, "single_resultant": ramp.single_resultant}

        def official(at: int):
            built, _ = ramps.build(ma_table=ramp.table, fit=ramp.fit, exptime_s=there.exptime, sca=at, **rules)
            return replace(built, saturation_beta=ramp.saturation_beta)

        filled = official(filled_for)
        if filled == ramp and filled.read_noise_source == ramp.read_noise_source:
            request = {**request, "ramp": official(sca)}
    return scene, request


# --- the Roman default over an SCA -----------------------------------------------------------


def grid_size(grid, request) -> int:
    return int(grid.meta["tables"][f"{request.band}_{request.sca:02d}"]["grid"])


#: Nodes of the SCA range when no field grid gives its own: the 3 x 3 grid of ``nlpsf.slopes.fieldgrid``.
RANGE_GRID = 3


def range_positions(request) -> list[tuple[float, float]]:
    """Where the SCA range looks: the field grid's nodes of this (band, SCA), else the 3 x 3 grid
    (corners, edge midpoints, centre), on which the Zernikes take their extremes (bilinear)."""
    from nlpsf.slopes import fieldgrid

    grid = fieldgrid.shipped_grid()
    nodes = None if grid is None else grid.node_positions(request.band, request.sca)
    return list(nodes) if nodes is not None else [p for _, _, p in fieldgrid.grid_positions(RANGE_GRID)]


def _demand(solved: str):
    def demand(solution: Solution) -> float:
        return _demand_of(solved, getattr(solution, solved))

    return demand


def _demand_of(solved: str, value: float | None) -> float:
    """How demanding an answer is: the smallest precision, the largest tolerance, the faintest star."""
    if value is None or not math.isfinite(value):
        return -math.inf
    return {"precision": -value, "tolerance": value, "magnitude": value}[solved]


def _demands_of(solved: str, values: list[float | None]) -> list[float]:
    """:func:`_demand_of` of each value (the same numbers, the sign chosen once)."""
    sign = -1.0 if solved == "precision" else 1.0
    return [-math.inf if value is None or not math.isfinite(value) else sign * value for value in values]


def _node(position, value: float | None, error: float | None, fidelity: str, solved: str) -> dict:
    return {"position": list(position), solved: json_number(value), "uncertainty": json_number(error), "fidelity": fidelity}


def sca_range(answer, request, tables_set=None, progress=None, nodes=None, start: float | None = None) -> Solution:
    """The Roman default without a position: the answer at every node of the SCA's field grid, the
    most demanding one returned (it holds everywhere on the SCA: the smallest precision, the largest
    tolerance, the faintest brightest-usable star), the least demanding and every node's value in
    ``conditions["sca_range"]`` and a flag. ``answer`` is ``nlpsf.solve.solver.answer`` (passed in).

    ``progress(done, total, message)``, if given, is told as the nodes are answered. ``nodes(request,
    positions)``: every node's value and uncertainty at once (``sca_nodes``), or None; then only the
    most demanding node is answered in full (from the slope read for it with the others, its value
    checked against the one found for it), else every node is. ``start``: the ``time.perf_counter()``
    the answer began at (its ``elapsed_s``)."""
    positions = range_positions(request)
    found = nodes(request, positions) if nodes is not None else None
    ranged = _ranged_at_once(answer, request, tables_set, positions, found, progress) if found is not None else None
    if ranged is None:
        ranged = _ranged_node_by_node(answer, request, tables_set, positions, progress)
    solved, (most_at, most), (least_at, least_value), rows, slopes_from = ranged
    conditions = dict(most.conditions)
    conditions["sca_range"] = {
        "primary": "most demanding: the requirement that holds everywhere on the SCA",
        "solved_for": solved,
        "most_demanding": {"position": list(most_at), solved: json_number(getattr(most, solved))},
        "least_demanding": {"position": list(least_at), solved: json_number(least_value)},
        "nodes": rows,
        "slopes_from": slopes_from,
    }
    flag = make(
        FlagCode.SCA_RANGE,
        sca=request.sca,
        points=len(positions),
        x=most_at[0],
        y=most_at[1],
        solved=solved,
        least=least_value,
        lx=least_at[0],
        ly=least_at[1],
        most=getattr(most, solved),
    )
    elapsed = most.elapsed_s if start is None else time.perf_counter() - start
    return replaced(most, flags=[flag, *most.flags], conditions=conditions, elapsed_s=elapsed)


def _at(request, position):
    return request.at_position(position)


def _ranged_at_once(answer, request, tables_set, positions, found, progress):
    """(solved, (where, answer) of the most demanding node, (where, value) of the least, the nodes'
    rows, where their slopes came from) from every node's value found at once; None where the most
    demanding node's own answer is not the one found for it (never expected)."""
    solved = found.solved_for
    demands = _demands_of(solved, found.values)
    ranked = sorted(range(len(positions)), key=demands.__getitem__)
    if progress:
        progress(
            len(positions) - 1, len(positions), f"the SCA's {len(positions)} field-grid nodes at once, the most demanding in full"
        )
    # The node's crossing (a magnitude solve's) is not sought again, nor its plan made again (the first
    # node's, moved), nor its slope read again at the magnitude every node was read at together (the
    # same slope: tests/library/test_sca_nodes.py reads each node alone). Its answer's arithmetic is
    # checked against the value found for it all the same.
    most_k = ranked[-1]
    most = answer(
        _at(request, positions[most_k]),
        tables_set,
        crossing=found.crossings.get(most_k),
        node_plan=found.plan,
        node_read=found.read_of(most_k),
    )
    if not _same_answer(getattr(most, solved), most.uncertainty, found, most_k):
        return None
    rows = [_node(p, found.values[k], found.uncertainties[k], "table", solved) for k, p in enumerate(positions)]
    least = (positions[ranked[0]], found.values[ranked[0]])
    return solved, (positions[ranked[-1]], most), least, rows, ["field grid"]


def _ranged_node_by_node(answer, request, tables_set, positions, progress):
    """:func:`_ranged_at_once`'s figures from every node answered in full, one after the other."""
    answers = []
    for index, p in enumerate(positions):
        if progress:
            progress(
                index, len(positions), f"the SCA's field-grid node {index + 1} of {len(positions)}, pixel ({p[0]:g}, {p[1]:g})"
            )
        answers.append((p, answer(_at(request, p), tables_set)))
    solved = answers[0][1].solved_for
    ranked = sorted(answers, key=lambda item: _demand(solved)(item[1]))
    (least_at, least), most = ranked[0], ranked[-1]
    rows = [_node(p, getattr(a, solved), a.uncertainty, a.fidelity, solved) for p, a in answers]
    slopes_from = sorted({"field grid" if a.fidelity == "table" else f"simulation ({a.fidelity})" for _, a in answers})
    return solved, most, (least_at, getattr(least, solved)), rows, slopes_from


def _same_answer(value, error, found, k: int) -> bool:
    """Whether a node's own answer is the one found for it with the others: its value to the last
    bit, its uncertainty to 1e-12 (the field interpolation's term is read once for all nodes)."""
    if value != found.values[k] and not (value is not None and math.isnan(value) and math.isnan(found.values[k])):
        return False
    other = found.uncertainties[k]
    if error is None or other is None:
        return error is other
    return math.isclose(error, other, rel_tol=1e-12, abs_tol=0.0)
