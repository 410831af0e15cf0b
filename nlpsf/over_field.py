"""Answers over the field: the worst of an SCA's centre and four corners (or of the focal plane's
18 SCAs), from the shipped field-point tables where they hold the request, else simulated."""

from __future__ import annotations

import math
from dataclasses import replace

from . import roman, tables
from .checks import InputError
from .flags import FlagCode, make
from .serialise import json_number
from .solution import Solution


def _tables_hold(scene, tableset: tables.TableSet, band: str, sca: int) -> bool:
    """Whether the tables already hold the scene: it differs from the paper's by its position alone,
    and the table of (band, SCA) was built at that position (a field-point table, or the centre's)."""
    if not replace(scene, position=None).is_paper or scene.position is None:
        return False
    held = tableset.get(band, sca).position_pixels
    return all(abs(a - b) < 1e-6 for a, b in zip(held, scene.position, strict=True))


def _corner_tables(scene, sca: int) -> tables.TableSet | None:
    """The field-point tables at the scene's position, if it is one of the SCA's corner field points
    and the scene has no other effect; None otherwise (or where no field-point tables are installed)."""
    if scene.position is None or not replace(scene, position=None).is_paper:
        return None
    for point, position in enumerate(roman.field_points(sca)):
        if point and all(abs(a - b) < 1e-6 for a, b in zip(position, scene.position, strict=True)):
            corners = field_tables()
            return None if corners is None else corners.at_point(point)
    return None


def field_points(sca: int) -> list[tuple[float, float]]:
    """Where ``solve_over_field`` looks on an SCA: its centre and the four corner field points
    (``roman.field_points`` 1-4). The Zernikes are interpolated bilinearly between the corners, so
    every coefficient takes its extremes there; the centre is where the SCA-centre tables are."""
    centre = (roman.SCA_PIXELS / 2, roman.SCA_PIXELS / 2)
    return [centre, *roman.field_points(sca)[1:]]


def field_tables() -> tables.TableSet | None:
    """The shipped field-point tables, None if this installation has none."""
    path = tables.field_table_path()
    return tables.load_tables(str(path)) if path.exists() else None


def over_field_from_tables(scene=None, fidelity: str | None = None, accuracy: float | None = None, ramp=None) -> bool:
    """Whether ``solve_over_field`` answers such a request from the tables alone (milliseconds, no
    simulation): the paper's scene, the table level, no accuracy to measure, no ramp, and the
    field-point tables installed."""
    plain = (scene is None or scene.is_paper) and ramp is None and accuracy is None
    return plain and fidelity in (None, "table") and field_tables() is not None


def worst_over_field(solve, band: str, scas="all", scene=None, progress=None, **request) -> Solution:
    """The answer for the worst position over the field: the centre and four corners of the given
    SCAs (``"all"``: the 18 of the focal plane), each with its own aberrations.

    At the table level (the default) the answer reads the SCA-centre tables and the shipped
    field-point tables (``field_slopes.ecsv.gz``), milliseconds per point. A scene with other effects,
    or a simulating fidelity, simulates every point (linear response unless another level is asked
    for; seconds per point). Worst means the most demanding answer: the smallest precision, the
    largest tolerance, or the faintest brightest-usable magnitude. The Solution returned is that
    point's, with every point's value in ``conditions["over_field"]`` and where the worst lies in a
    flag. ``solve`` is ``nlpsf.solver.solve`` (passed in: this module sits below the solver).
    """

    from . import scene as scenes

    chosen = list(range(1, roman.N_SCA + 1)) if scas == "all" else [roman.check_sca(s) for s in scas]
    base = scene if scene is not None else scenes.SceneModel()
    if base.position is not None:
        raise InputError("position", "give a position or ask for the worst over the field, not both")
    # Each corner's own table is found by ``solve`` from the position (``_corner_tables``).
    corners = field_tables() if base.is_paper and request.get("tables_set") is None else None
    if corners is None and request.get("fidelity") in (None, "table"):
        # Without field-point tables (or with a scene they do not hold) every point is simulated.
        request["fidelity"] = "linear"
    answers = []
    points = [(s, p) for s in chosen for p in field_points(s)]
    for index, (sca, position) in enumerate(points):
        if progress:
            progress(index, len(points), f"SCA {sca} at {position[0]:.0f},{position[1]:.0f}")
        answers.append((sca, position, solve(band, sca, scene=replace(base, position=position), **request)))
    if progress:
        progress(len(points), len(points), "done")
    solved = answers[0][2].solved_for

    def demand(solution: Solution) -> float:
        value = getattr(solution, solved)
        if value is None or not math.isfinite(value):
            return -math.inf
        return {"precision": -value, "tolerance": value, "magnitude": value}[solved]

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
