"""The calculator's curves for one solve request: the slope c(m) and the precision p(m) a tolerance
asks for, over magnitude, for the request's own scene, position and readout, with its limits.

Each value is the solver's own at that magnitude: the slopes come from the slope source the solver
reads for the request (``slopes.source.Slopes`` on ``solver.plan``'s plan: the Roman default's field
grid, the paper's tables, or the tables mapped up an OLS ramp), the relation is the solver's
(T = |c(m)| p beta0, divided by sqrt(stars) in scatter mode; a slope no larger than its own standard
error asks no precision), and a magnitude the solver refuses (brighter than the slopes reach, past
the ramp's bright margin) is NaN here. So the answer of ``solver.answer`` at a magnitude of the grid
is the curve's value there (``tests/library/test_solve_curves.py`` checks it at random
points). The limits are the solver's, read from its answer at the curve's faint end.

Without a position the Roman default's answer is the most demanding of the SCA's field-grid nodes
(``over_field.sca_range``); its curve is the same envelope: at each magnitude the node with the
largest |c|, hence the smallest precision and the largest tolerance, and NaN wherever the solver
refuses at any node (it then refuses the whole request). Solving for the magnitude, the envelope's
crossing of the required slope, scanned from the faint end, is the faintest of the nodes' crossings:
the answer the range returns.

Curves are read at table cost only: on a plan made with ``simulate=False`` a magnitude whose
slope would be simulated is NaN (``gaps`` says why), and a request whose every slope is simulated
(another scene, exposure or beta0 than the grid or the tables hold, a simulating level, an accuracy
target) has no curve, only its answer (``needs_simulation`` says why).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from dataclasses import dataclass, field, replace

import numpy as np

from nlpsf.checks import InputError
from nlpsf.request.resolve import SolveRequest
from nlpsf.slopes import tables
from nlpsf.slopes.providers import NeedsSimulation

#: Tolerances drawn around the chosen one (multiples of T).
TOLERANCE_FACTORS: tuple[float, ...] = (0.1, 1 / 3, 1.0, 3.0, 10.0)
#: Spacing of the magnitude grid [mag]; the magnitudes asked for (``at``) are added exactly.
STEP_MAG = 0.1
#: The paper's published figure data were computed at these conditions (``nlpsf/data/paper``).
PUBLISHED_CONDITIONS = {"sca": 18, "exptime": 168.1, "beta0": 5e-7}


@dataclass(frozen=True)
class Curves:
    """c(m) and p(m) of one request on a magnitude grid; NaN where the solver gives no answer at
    table cost. Arrays share ``magnitude``'s length."""

    magnitude: np.ndarray
    #: c(m) per unit beta, signed (d metric / d beta, or sigma metric / sigma beta), before averaging.
    slope: np.ndarray
    #: The slope's statistical standard error (the same units).
    slope_statistical: np.ndarray
    #: The method (fidelity level) error as a fraction of |c|, the solver's for this request.
    method_relative: float | None
    #: 1 / sqrt(stars) in scatter mode (the PSF model averages that many stars), else 1.
    averaging: float
    beta0: float
    #: The tolerance the precision curves are for (the request's, or the one it answers); None: none.
    tolerance: float | None
    #: factor -> p(m) at factor x tolerance (dimensionless fraction; inf: no constraint).
    precision: dict[float, np.ndarray]
    #: The statistical standard error of p(m) at the tolerance itself (scales with the factor).
    precision_statistical: np.ndarray
    #: Where on the SCA: one position, or the SCA's nodes (envelope).
    where: dict
    #: The index of the node that gives the envelope at each magnitude (-1: no value); one node: 0.
    node: np.ndarray
    limits: dict
    #: Fainter than this, the slopes follow the flux law from the source's faint end (None: not drawn).
    extrapolated_from: float | None
    #: Why some magnitudes have no value (None: every magnitude has one).
    gaps: str | None
    #: Why the request has no curve at all (None: it has one).
    needs_simulation: str | None
    conditions: dict = field(default_factory=dict)

    def value_at(self, magnitude: float) -> int | None:
        """The grid index of ``magnitude`` (None if not on the grid)."""
        hits = np.flatnonzero(np.abs(self.magnitude - magnitude) <= 1e-9)
        return int(hits[0]) if hits.size else None

    def to_dict(self) -> dict:
        def listed(values) -> list:
            return [None if not math.isfinite(v) else float(v) for v in np.asarray(values, dtype=np.float64)]

        def unbounded(values) -> list:
            # p = inf is an answer ("no constraint"), not a missing value: kept as the string "inf".
            return ["inf" if v == math.inf else (None if not math.isfinite(v) else float(v)) for v in values]

        return {
            "magnitude": listed(self.magnitude),
            "slope": listed(self.slope),
            "slope_abs": listed(np.abs(self.slope)),
            "slope_statistical": listed(self.slope_statistical),
            "slope_method": listed(np.abs(self.slope) * self.method_relative) if self.method_relative is not None else None,
            "method_relative": self.method_relative,
            "signed": bool(np.any(np.isfinite(self.slope) & (self.slope < 0))),
            "averaging": self.averaging,
            "beta0": self.beta0,
            "tolerance": self.tolerance,
            "requirement": [
                {
                    "factor": factor,
                    "tolerance": None if self.tolerance is None else factor * self.tolerance,
                    "precision": unbounded(values),
                    "statistical": listed(factor * self.precision_statistical),
                }
                for factor, values in self.precision.items()
            ],
            "where": self.where,
            "node": [int(k) for k in self.node],
            "limits": self.limits,
            "extrapolated_from": self.extrapolated_from,
            "gaps": self.gaps,
            "needs_simulation": self.needs_simulation,
            "relation": "T = |c(m)| p beta0 (scatter: divided by sqrt(stars)); a slope within its own standard error "
            "asks no precision (p = inf)",
            "conditions": self.conditions,
        }


@dataclass
class _Node:
    """One position's slopes and limits (the solver's plan and slope source for it)."""

    request: SolveRequest
    slopes: object
    answer: object  # the solver's answer at the curve's faint end (limits, conditions, method error)
    bright: float  # the brightest magnitude the solver answers at this node (before grid misses)
    faint: float  # the slope source's faint end (fainter: the flux law)


def curves(
    request: SolveRequest,
    at: Iterable[float] = (),
    tolerance: float | None = None,
    factors: Iterable[float] = TOLERANCE_FACTORS,
    step: float = STEP_MAG,
    refuse: str | None = None,
) -> Curves:
    """The curves of ``request`` (a validated ``SolveRequest``; see the module docstring).

    ``at``: magnitudes added to the grid exactly (the answer's, so that its point is a grid point;
    fainter than the grid, the grid is extended by the flux law); the request's own magnitude is
    always added. ``tolerance``: the T of the precision curves; None: the request's own (its
    tolerance or shear budget), else the tolerance it answers (its precision at its magnitude, on
    this curve). ``step``: the grid's spacing [mag]. ``refuse``: a caller's reason for no curve."""
    asked = [*at, request.magnitude]
    at = sorted({float(m) for m in asked if m is not None and math.isfinite(m)})
    averaging = 1.0 / math.sqrt(request.stars)
    nodes, why = ([], refuse) if refuse is not None else _nodes(request)
    if why is not None:
        empty = np.array(at, dtype=np.float64)
        nan = np.full(empty.shape, np.nan)
        return Curves(
            empty, nan, nan, None, averaging, request.beta0, tolerance or request.target_tolerance,
            {f: nan for f in factors}, nan, _where(request, nodes), np.full(empty.shape, -1), {}, None, None,
            f"this request has no curve at table cost: {why}; its answer is a fresh simulation per magnitude",
        )  # fmt: skip
    faint = min(n.faint for n in nodes)
    magnitudes = _grid(max(n.bright for n in nodes), faint, step, at)
    magnitudes, slope, slope_error, chosen, missed = _refined(nodes, magnitudes, *_envelope(nodes, magnitudes))
    c, c_err = np.abs(slope) * averaging, slope_error * averaging
    beta0 = request.beta0
    if tolerance is None:
        tolerance = request.target_tolerance
    if tolerance is None and request.magnitude is not None and request.precision is not None:
        # Solving for the tolerance: T = |c| p beta0 at the request's magnitude, as the solver answers it.
        i = int(np.argmin(np.abs(magnitudes - request.magnitude)))
        tolerance = float(c[i] * request.precision * beta0) if math.isfinite(c[i]) else None
    with np.errstate(divide="ignore", invalid="ignore"):
        zero = c <= np.maximum(c_err, 1e-300)  # the solver: a slope within its error asks no precision
        precision = {}
        for factor in factors:
            t = None if tolerance is None else (tolerance if factor == 1.0 else factor * tolerance)
            p = np.full(magnitudes.shape, np.nan) if t is None else t / (c * beta0)
            precision[factor] = np.where(np.isfinite(slope), np.where(zero, np.inf, p), np.nan)
        base = precision.get(1.0, np.full(magnitudes.shape, np.nan))
        statistical = np.where(zero | ~np.isfinite(base), np.nan, base * c_err / c)
    answer = nodes[0].answer
    method = answer.parts.fidelity / answer.tolerance if answer.parts.fidelity is not None and answer.tolerance else None
    gaps = None
    if missed:
        gaps = (
            f"the slopes at m = {min(missed):.2f} to {max(missed):.2f} would be simulated (outside what the tables and "
            "the field grid hold, or between the saturation limits at a position): no value there at table cost"
        )
    return Curves(
        magnitude=magnitudes,
        slope=slope,
        slope_statistical=slope_error,
        method_relative=None if method is None else abs(method),
        averaging=averaging,
        beta0=beta0,
        tolerance=tolerance,
        precision=precision,
        precision_statistical=statistical,
        where=_where(request, nodes),
        node=chosen,
        limits=_limits(request, nodes),
        extrapolated_from=faint if magnitudes.size and magnitudes[-1] > faint + 1e-9 else None,
        gaps=gaps,
        needs_simulation=None,
        conditions=_conditions(answer, nodes),
    )


def _grid(bright: float, faint: float, step: float, at: list[float]) -> np.ndarray:
    """Multiples of ``step`` from the brightest magnitude answered to the source's faint end (on to
    the faintest of ``at`` by the flux law), with ``at`` added exactly."""
    grid = np.arange(math.ceil(bright / step - 1e-9) * step, faint + 1e-9, step)
    beyond = [m for m in at if m > faint]
    if beyond:
        grid = np.concatenate([grid, np.arange(grid[-1] + step if grid.size else faint, max(beyond) + 1e-9, step)])
    grid = np.round(grid, 10)
    return np.array(sorted({*grid.tolist(), *at}), dtype=np.float64)


def _envelope(nodes: list[_Node], magnitudes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[float]]:
    """(slope, its standard error, the node giving it, the magnitudes that would be simulated): each
    node's c(m) from its slope source, at table cost; the envelope NaN wherever a node has none (the
    solver refuses the whole request there), else the node with the largest |c| (the most demanding
    answer, as the SCA range ranks them)."""
    values = np.full((len(nodes), magnitudes.size), np.nan)
    errors = np.full_like(values, np.nan)
    missed: list[float] = []
    for k, node in enumerate(nodes):
        values[k], errors[k] = _node_slopes(node, magnitudes, missed)
    complete = np.all(np.isfinite(values), axis=0)
    chosen = np.where(complete, np.argmax(np.where(np.isfinite(values), np.abs(values), -np.inf), axis=0), -1)
    columns = np.arange(magnitudes.size)
    slope = np.where(complete, values[np.maximum(chosen, 0), columns], np.nan)
    slope_error = np.where(complete, errors[np.maximum(chosen, 0), columns], np.nan)
    return slope, slope_error, chosen, missed


def _node_slopes(node: _Node, magnitudes: np.ndarray, missed: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """One node's (c, its error) at ``magnitudes``, NaN where the solver refuses. Inside the Roman
    default's field grid, its reader over all the magnitudes at once (as the solver's own magnitude
    scan reads it, ``magnitude_scan._field_grid_scan``); elsewhere the slope source one magnitude at
    a time (the tables, the grid's flux law fainter than it, a simulation refused at table cost)."""
    values = np.full(magnitudes.shape, np.nan)
    errors = np.full(magnitudes.shape, np.nan)
    todo = magnitudes >= node.bright - 1e-9  # brighter, the solver refuses (the slopes' reach, the ramp's margin)
    slopes, request = node.slopes, node.request
    grid = getattr(slopes, "grid", None)
    if grid is not None and hasattr(grid, "column_value"):
        low, high = grid.magnitude_range(request.band, request.sca)
        inside = todo & (magnitudes >= low) & (magnitudes <= high)
        if inside.any():
            position = slopes.scene_model.position
            value, error = grid.slope(request.band, request.sca, position, request.metric, request.mode, magnitudes[inside])
            values[inside], errors[inside] = value, np.abs(error)
            # Between the saturation limits at a position (not a node) the solver simulates afresh
            # (``validity.between_limits``, issue 28): no value there at table cost.
            between = _between_limits_mask(grid, request, position, magnitudes) & inside
            values[between] = errors[between] = np.nan
            missed.extend(float(m) for m in magnitudes[between])
            todo &= ~between
        todo &= ~np.isfinite(values)
    for i in np.flatnonzero(todo):  # the plan's slopes refuse to simulate (simulate=False)
        try:
            value, error, region = slopes.at(float(magnitudes[i]))
        except NeedsSimulation:
            missed.append(float(magnitudes[i]))
            continue
        if region >= 0:
            values[i], errors[i] = value, error
    return values, errors


def _between_limits_mask(grid, request, position, magnitudes: np.ndarray) -> np.ndarray:
    """Where ``validity.between_limits`` sends the solver to a fresh simulation, over ``magnitudes``."""
    from .validity import between_limits

    mask = np.zeros(magnitudes.shape, dtype=bool)
    if position is None:
        return mask
    ramp = grid.saturation_magnitude(request.band, request.sca, position)
    if between_limits(grid, request.band, request.sca, position, ramp) is None:
        return mask  # a node, or no final-frame limit stated
    final = grid.final_frame_saturation_magnitude(request.band, request.sca, position)
    return (magnitudes >= ramp) & (magnitudes < final)


#: Where the curve is refined: linear (and log) interpolation between neighbours within this
#: fraction of the solver's value at their midpoint, down to :data:`REFINE_DEPTH` halvings.
REFINE_TOLERANCE = 0.002
REFINE_DEPTH = 7


def _refined(nodes: list[_Node], magnitudes, slope, error, chosen, missed):
    """The grid with midpoints added wherever interpolating c(m) (or 1/|c|, which p follows) between
    neighbours misses the solver's value there by more than :data:`REFINE_TOLERANCE`: where the
    most demanding node changes, |c| dips through a sign change, or resultants saturate."""
    for _ in range(REFINE_DEPTH):
        left = np.flatnonzero(np.isfinite(slope[:-1]) & np.isfinite(slope[1:]))
        if left.size == 0:
            break
        middle = 0.5 * (magnitudes[left] + magnitudes[left + 1])
        m_slope, m_error, m_chosen, m_missed = _envelope(nodes, middle)
        a, b, c = np.abs(slope[left]), np.abs(slope[left + 1]), np.abs(m_slope)
        with np.errstate(divide="ignore", invalid="ignore"):
            misses = np.maximum.reduce([
                np.abs(0.5 * (a + b) / c - 1), np.abs(0.5 * (1 / a + 1 / b) * c - 1), np.abs(np.sqrt(a * b) / c - 1),
            ])  # fmt: skip
        bad = ~(misses <= REFINE_TOLERANCE)  # NaN (a gap at the midpoint) counts as a miss too
        if not bad.any():
            break
        missed += m_missed
        order = np.argsort(np.concatenate([magnitudes, middle[bad]]), kind="stable")
        magnitudes = np.concatenate([magnitudes, middle[bad]])[order]
        slope = np.concatenate([slope, m_slope[bad]])[order]
        error = np.concatenate([error, m_error[bad]])[order]
        chosen = np.concatenate([chosen, m_chosen[bad]])[order]
    return magnitudes, slope, error, chosen, missed


def _nodes(request: SolveRequest) -> tuple[list[_Node], str | None]:
    """The request's positions with their slope sources and limits, or why its slopes are all simulated."""
    from . import solver  # the solver imports the slope source; this module sits beside it

    why = _simulated_request(request)
    if why is not None:
        return [], why
    nodes = []
    for position in _positions(request):
        node_request = request if position is None else request.with_changes(scene=replace(request.scene, position=position))
        # At table cost: a slope the plan would simulate is refused (providers.NeedsSimulation).
        # The grid's plan whatever the request's own magnitude; between the saturation limits at a
        # position the solver simulates afresh, and those magnitudes are left out (_node_slopes).
        the_plan = solver.plan(node_request, simulate=False, fresh_between_limits=False)
        if the_plan.fidelity != "table":
            notes = "; ".join(str(n) for n in the_plan.notes)
            return [], f"its slopes are simulated ({notes or 'fidelity ' + the_plan.fidelity})"
        try:
            nodes.append(_node(solver, node_request, the_plan))
        except _Simulated as simulated:
            return [], str(simulated)
    return nodes, None


class _Simulated(Exception):
    """A request whose every slope is simulated, found while its node is read."""


def limits(request: SolveRequest) -> dict:
    """The limits of ``request`` as its curves carry them (:func:`curves`), without the curves; for a
    request whose slopes are simulated, ``needs_simulation`` says why and the limits are absent."""
    nodes, why = _nodes(request)
    if why is not None:
        return {"needs_simulation": f"this request's limits come with its answer: {why}"}
    return {**_limits(request, nodes), "where": _where(request, nodes)}


def _simulated_request(request: SolveRequest) -> str | None:
    """Why every slope of ``request`` is simulated (before any plan is made), else None."""
    if request.accuracy is not None:
        return "an accuracy target is met by measuring the scene's effects in fresh simulations"
    if request.fidelity not in (None, "table"):
        return f"the method {request.fidelity} simulates its slopes"
    return None


def _positions(request: SolveRequest) -> list:
    """[None] (the request's own position, or none), or the SCA's field-grid nodes for the Roman
    default without a position (the solver's SCA range)."""
    if request.policy.ranges_over_sca and request.scene is not None and request.scene.position is None:
        from .over_field import range_positions

        return list(range_positions(request))
    return [None]


def _node(solver, request: SolveRequest, the_plan) -> _Node:
    from nlpsf.slopes.source import Slopes

    slopes = Slopes.for_request(request, the_plan)
    grid = getattr(slopes, "grid", None)
    faint = grid.magnitude_range(request.band, request.sca)[1] if grid is not None else slopes.range()[1]
    # The solver's limits and conditions for this node, from its answer at the faint end (where it
    # always answers): precision 1, so that its tolerance is |c| beta0 and the method error relative.
    reference = request.with_changes(precision=1.0, tolerance=None, magnitude=faint, shear_m=None, shear_c=None, size_ratio=None)
    if request.ramp is not None and not request.policy.field_grid and slopes.ramp_factor is None:
        raise _Simulated("the paper's scene up a ramp the tables do not map (not an OLS fit) is simulated at every magnitude")
    # The table solve (a batch's: it refuses rather than simulates); a ramp on the paper's scene is
    # refused there outright, but at the faint end its OLS mapping onto the tables is exact.
    table_cost = not (request.ramp is not None and not request.policy.field_grid)
    answer = solver.answer(reference, simulate=not table_cost)
    # Past the ramp's bright margin the solver refuses (solve_validity._ramp_magnitude_flags); in a
    # final frame, brighter than the tables reach (region < 0).
    bright = answer.saturation_magnitude - tables.BRIGHT_MARGIN_MAG if request.ramp is not None else slopes.range()[0]
    if grid is not None:
        bright = max(bright, grid.magnitude_range(request.band, request.sca)[0])
    return _Node(request, slopes, answer, bright, faint)


def _where(request: SolveRequest, nodes: list[_Node]) -> dict:
    if len(nodes) > 1:
        positions = [list(n.request.scene.position) for n in nodes]
        return {
            "kind": "envelope",
            "positions": positions,
            "words": f"no position given: at each magnitude the most demanding of the SCA's {len(nodes)} field-grid "
            "nodes (the largest |c|), as the answer without a position is",
        }
    scene = request.scene
    position = None if scene is None else scene.position
    if position is None:
        return {"kind": "centre", "positions": [], "words": "the tables' position (the SCA centre)"}
    return {"kind": "position", "positions": [list(position)], "words": f"at pixel ({position[0]:g}, {position[1]:g})"}


def _limits(request: SolveRequest, nodes: list[_Node]) -> dict:
    """The saturation limit that binds for this readout, the single final frame's, and (the paper's
    quadratic on its tables' star) where 2 beta0 Q_peak reaches 1; over the nodes, the faintest."""
    saturation = [n.answer.saturation_magnitude for n in nodes]
    final = [n.answer.final_frame_saturation_magnitude for n in nodes]
    ramp = request.ramp is not None
    out = {
        "saturation_magnitude": max(saturation),
        "saturation_range": [min(saturation), max(saturation)],
        "final_frame_saturation_magnitude": max(final) if all(f is not None for f in final) else None,
        "final_frame_saturation_range": [min(final), max(final)] if all(f is not None for f in final) else None,
        "readout": "ramp" if ramp else "final frame",
        "brightest_answered_magnitude": max(n.bright for n in nodes),
        "rules": {
            "saturation_magnitude": (
                "up the ramp: brighter than this the brightest pixel saturates in the resultant a slope needs; answers "
                "between this and the final frame's limit drop the saturated resultants"
                if ramp
                else "brighter than this the brightest pixel passes the full well in the final frame"
            ),
            "final_frame_saturation_magnitude": "brighter than this the brightest pixel passes the full well by the end "
            "of the exposure" + ("; up the ramp only its last resultants saturate there" if ramp else ""),
            "brightest_answered_magnitude": "the brightest magnitude the calculator answers for (brighter: refused)",
        },
    }
    if len(nodes) > 1:
        out["rules"]["saturation_range"] = "the saturation limit over the SCA's nodes; the faintest holds everywhere"
    source = nodes[0].answer.conditions.get("saturation_from")
    if source:
        out["saturation_from"] = source
    if request.policy.tables_limits and not ramp and request.scene is None:
        try:
            from .relation import nl_invalid_magnitude

            out["nonmonotonic_magnitude"] = nl_invalid_magnitude(request.band, request.sca, request.beta0, request.exptime)
            out["rules"]["nonmonotonic_magnitude"] = "brighter than this 2 beta0 Q_peak >= 1: S = Q - beta Q^2 no longer rises"
        except InputError:
            pass
    return out


def _conditions(answer, nodes: list[_Node]) -> dict:
    keep = (
        "scene_description", "scene_name", "scene", "exptime_s", "beta0", "full_well_e", "fidelity", "ramp", "linearise_at",
        "slopes_from", "saturation_rule", "pupil_scale", "throughput", "data_version", "code_version",
    )  # fmt: skip
    conditions = {k: answer.conditions[k] for k in keep if k in answer.conditions}
    conditions.update(band=answer.band, sca=answer.sca, metric=answer.metric, mode=answer.mode, exptime=answer.exptime)
    conditions["beta0"], conditions["full_well"] = answer.beta0, answer.full_well
    if len(nodes) > 1:
        # The reference answer is one node's: its description names that node; the curve is the envelope.
        conditions["scene_description"] = _without_position(conditions.get("scene_description"))
    return conditions


def _without_position(description):
    """A scene description without the reference node's position (the envelope holds over the SCA)."""
    if not isinstance(description, str):
        return description
    text = re.sub(r",?\s*position [\d.]+\s*,\s*[\d.]+", "", description)
    return re.sub(r"^(roman):\s*,?\s*", r"\1: anywhere on the SCA, ", text, count=1)


def published(request: SolveRequest, tolerance: float | None) -> dict | None:
    """The paper's published slopes (Fig. 3 bias, Fig. 5 scatter; ``tables.paper_data``) and the
    precision they ask at ``tolerance``, where the request is the paper's scene at the conditions
    they were computed for (SCA 18, 168.1 s, beta0 = 5e-7, final frame); None elsewhere."""
    from nlpsf.slopes.tables import paper_data

    same = (
        request.policy.tables_limits and request.scene is None and request.ramp is None
        and request.sca == PUBLISHED_CONDITIONS["sca"]
        and math.isclose(request.exptime, PUBLISHED_CONDITIONS["exptime"], rel_tol=1e-9)
        and math.isclose(request.beta0, PUBLISHED_CONDITIONS["beta0"], rel_tol=1e-9)
        and request.metric in ("size", "e1", "e2") and request.throughput is None
    )  # fmt: skip
    if not same:
        return None
    data = paper_data()
    figure = data["fig3_bias_slopes_per_beta"] if request.mode == "bias" else data["fig5_scatter_slopes_per_sigma_beta"]
    if request.band not in figure:
        return None
    slopes = [float(v) for v in figure[request.band][request.metric]]
    averaging = 1.0 / math.sqrt(request.stars)
    precision = None
    if tolerance is not None:
        precision = [tolerance / (abs(s) * averaging * request.beta0) if s else math.inf for s in slopes]
    return {
        "magnitude": [float(m) for m in data["magnitudes"]],
        "slope": slopes,
        "precision": precision,
        "tolerance": tolerance,
        "source": data["source"],
    }


def paper_overlay(request: SolveRequest, tolerance: float | None, at: Iterable[float] = ()) -> Curves | None:
    """The paper's idealised scene's curves at the request's band, SCA, metric, mode, beta0, full
    well, stars and exposure (its final frame, the shipped tables), for the same tolerance: the
    overlay beside another scene's answer. None where the request is the paper's scene already."""
    if request.policy.tables_limits and request.scene is None and request.ramp is None:
        return None
    paper = SolveRequest(
        request.band, request.sca, request.metric, request.mode, request.beta0, request.exptime, precision=1.0,
        magnitude=tables.load_tables().get(request.band, request.sca).grid_range(request.exptime, request.beta0)[1],
        full_well=request.full_well, stars=request.stars, scene="paper",
    )  # fmt: skip
    return curves(paper, at=at, tolerance=tolerance)
