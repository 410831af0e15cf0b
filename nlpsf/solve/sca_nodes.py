"""The Roman default without a position: every node of the SCA's field grid answered at once.

``solver.answer`` answers such a request with the most demanding of the SCA's nodes
(``over_field.sca_range``): it needs every node's solved value and uncertainty, and the whole
answer of one node. The values and uncertainties come from here, every node at once -- the grid
read at each node's own magnitude in one call (``FieldGrid.slopes_at_nodes``), a magnitude solve's
scan of every node from one evaluation and the crossings found side by side, the model parts read at
every node's magnitude in one look-up (``model_part.roman_effects_at``) -- with the arithmetic of
``quantity`` and ``magnitude_scan`` repeated number for number: each node's value is what answering
it alone gives, bit for bit, and its uncertainty agrees to the last bits (the field interpolation's
term read once for all nodes, the parts added with numpy's sums). Where a node leaves the common
case (a magnitude the grid does not hold, a refusal, an answer extrapolated past the scan, a
crossing the secant does not bracket), :func:`answer_nodes` returns None and the caller answers
node by node. A magnitude solve reads only what its answers use: no secant where no node crosses
inside its scan, and no slope where saturation binds at every node (each answer is then its
saturation magnitude, its parts 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from functools import lru_cache

import numpy as np

from nlpsf.slopes import tables

from . import model_part
from .magnitude_scan import _H, _TREND_MAG, NodeScan


@dataclass(frozen=True)
class NodeAnswers:
    """Every node's solved value and total uncertainty (as its own answer's ``Solution`` holds them)."""

    solved_for: str
    values: list[float | None]
    uncertainties: list[float | None]
    #: Node k's scan of a magnitude solve (``magnitude_scan.NodeScan``): its c(m) on the scan's
    #: magnitudes, and where it crossed inside the scan, the root and d ln|c| / dm there (None where
    #: saturation binds), as ``magnitude_scan.scan_magnitude`` finds them at the node.
    crossings: dict[int, NodeScan] = field(default_factory=dict)
    #: The plan of the first node (``solver.plan``), which the most demanding node's answer moves there.
    plan: object | None = None
    #: (each node's magnitude, its slope there, |error|): what node k's own answer reads at that
    #: magnitude (``Slopes.at``), read with the others: the slope bit for bit, the error to the last
    #: bits (a magnitude solve's field-interpolation term is read once for every node's root).
    reads: tuple[list[float], list[float], list[float]] | None = None

    def read_of(self, k: int) -> tuple[float, float, float] | None:
        """Node k's (magnitude, slope, |error|) read with the others (None: none kept)."""
        return None if self.reads is None else (self.reads[0][k], self.reads[1][k], self.reads[2][k])


class _Nodes:
    """The grid read at the SCA's nodes, each node at its own magnitude, as ``Slopes.at`` reads it."""

    def __init__(self, request, grid):
        self.request, self.grid = request, grid
        self.band, self.sca, self.metric, self.mode = request.band, request.sca, request.metric, request.mode
        self.n = int(grid.meta["tables"][f"{self.band}_{self.sca:02d}"]["grid"])
        self.brightest, self.faintest = grid.magnitude_range(self.band, self.sca)

    def held(self, magnitudes) -> bool:
        """Whether every magnitude is one every node holds (else ``Slopes.at`` would simulate)."""
        return all(self.brightest <= m for m in magnitudes)

    def at(self, magnitudes: list[float]) -> tuple[list[float], list[float]]:
        """(slope, |error|) of node k at ``magnitudes[k]`` (None: keep it at the faint end): in the
        grid, or fainter than its faint end by the flux law from there (``Slopes._from_grid``)."""
        inside = [min(m, self.faintest) for m in magnitudes]
        one = inside[0] if all(m == inside[0] for m in inside) else None  # one magnitude: read (and kept) once
        at = np.reshape(inside, (self.n, self.n)) if one is None else one
        if one is not None and self.metric in ("e1", "e2"):
            # The other component in the same read (kept): the modulus over the component reads it next.
            other = "e2" if self.metric == "e1" else "e1"
            names = [f"{self.mode}_{self.metric}{part}" for part in ("", "_err", "_interp")] + [f"{self.mode}_{other}"]
            self.grid.columns_node_values(self.band, self.sca, names, one)
        value, error = self.grid.slopes_at_nodes(self.band, self.sca, self.metric, self.mode, at)
        return self._faint_law(magnitudes, value.reshape(-1).tolist(), error.reshape(-1).tolist())

    def at_sets(self, sets: list[list[float]]) -> list[tuple[list[float], list[float]]]:
        """:meth:`at` of each list of node magnitudes in ``sets``, read together (the same numbers)."""
        if len(sets) == 1:
            return [self.at(sets[0])]
        inside = np.minimum(np.array(sets, dtype=np.float64).T, self.faintest).reshape(self.n, self.n, len(sets))
        value, error = self.grid.slopes_at_nodes(self.band, self.sca, self.metric, self.mode, inside)
        value, error = value.reshape(-1, len(sets)), error.reshape(-1, len(sets))
        return [self._faint_law(m, value[:, j].tolist(), error[:, j].tolist()) for j, m in enumerate(sets)]

    def _faint_law(self, magnitudes, values: list[float], errors: list[float]) -> tuple[list[float], list[float]]:
        """Slopes and |errors| read at the faint end moved to a fainter node magnitude by the flux law."""
        for k, m in enumerate(magnitudes):
            if m > self.faintest:
                scale = 10 ** (-0.4 * (m - self.faintest))
                values[k], errors[k] = values[k] * scale, abs(errors[k]) * scale
            else:
                errors[k] = abs(errors[k])
        return values, errors

    def held_values(self, magnitudes: list[float]) -> list[float] | None:
        """Node k's slope at ``magnitudes[k]`` (each within the grid), None where ``Slopes.at`` would
        not read it from the grid (a value or an error not stated there)."""
        found = self.held_value_sets([magnitudes])
        return None if found is None else found[0]

    def held_value_sets(self, sets: list[list[float]]) -> list[list[float]] | None:
        """:meth:`held_values` of each list of node magnitudes in ``sets``, read together; None where
        any is not held."""
        column = f"{self.mode}_{self.metric}"
        m = np.array(sets, dtype=np.float64).T.reshape(self.n, self.n, len(sets))
        if self.metric == "e":
            names = [f"{self.mode}_{c}{s}" for c in ("e1", "e2") for s in ("", "_err", "_interp")]
            e1, e1_err, e1_interp, e2, e2_err, e2_interp = self.grid.columns_at_nodes(self.band, self.sca, names, m)
            values, checks = np.hypot(e1, e2), (e1_err, e1_interp, e2_err, e2_interp)
        else:
            names = (column, f"{column}_err", f"{column}_interp")
            values, *checks = self.grid.columns_at_nodes(self.band, self.sca, names, m)
        if not all(np.isfinite(c).all() for c in checks):
            return None
        values = values.reshape(-1, len(sets))
        return [values[:, j].tolist() for j in range(len(sets))]

    def modulus_over_component(self, magnitudes: list[float]) -> list[float | None]:
        """``Slopes.modulus_over_component`` at every node (e1 / e2 answers; 1 otherwise)."""
        if self.metric not in ("e1", "e2"):
            return [1.0] * len(magnitudes)
        inside = [min(v, self.faintest) for v in magnitudes]
        columns = (f"{self.mode}_e1", f"{self.mode}_e2")
        if all(m == inside[0] for m in inside):  # one magnitude: read once, and kept for the node answered in full
            read = self.grid.columns_node_values(self.band, self.sca, columns, inside[0])
        else:
            read = self.grid.columns_at_nodes(self.band, self.sca, columns, np.reshape(inside, (self.n, self.n)))
        e1, e2 = (v.reshape(-1) for v in read)
        component = np.abs(e1 if self.metric == "e1" else e2)
        # A magnitude fainter than the grid's is not held there: the answer takes the tables' ratio.
        # (numpy's hypot may differ from math.hypot in the last bit: the ratio scales only the
        # uncertainty, which agrees with the node's own answer to 1e-12.)
        ok = np.isfinite(e1) & np.isfinite(e2) & (component > 0) & (np.asarray(magnitudes) <= self.faintest)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.hypot(e1, e2) / component
        return [r if held else None for r, held in zip(ratio.tolist(), ok.tolist(), strict=True)]


def answer_nodes(request, the_plan, saturation: list[float], systematic: float | None) -> NodeAnswers | None:
    """Every node's value and uncertainty of ``request`` (the Roman default without a position, its
    plan ``the_plan`` read from the field grid; ``saturation``: each node's saturation magnitude, the
    ramp's, ``systematic``: the fidelity level's relative error), or None where a node leaves the
    common case (see the module docstring)."""
    if the_plan.grid is None or the_plan.model.get("combine") != model_part.Rule.ROMAN_PARTS or request.throughput is not None:
        return None
    nodes = _Nodes(request, the_plan.grid)
    if not nodes.held(saturation):
        return None
    if request.solved_for == "magnitude":
        return _magnitudes(request, nodes, the_plan.model, saturation, systematic)
    return _at_magnitude(request, nodes, the_plan.model, saturation, systematic)


def _effects(model: dict, nodes: _Nodes, magnitudes: list[float]) -> np.ndarray | None:
    """``model_at``'s relative model part at each node's magnitude (None: a node needs the tables' ratio)."""
    scales = nodes.modulus_over_component(magnitudes) if model["stated_against"] == "modulus" else [1.0] * len(magnitudes)
    if any(s is None for s in scales):
        return None
    return model_part.roman_effects_at(model, magnitudes, scales)


def _totals(statistical, fidelity, effects) -> list[float]:
    """``Uncertainty.total`` of every node (its optical-model and pupil parts are 0 for the Roman
    default: its parts hold the optical model's vintage)."""
    fidelity = np.zeros_like(statistical) if fidelity is None else fidelity
    return [math.hypot(s, f, e, 0.0) for s, f, e in zip(statistical.tolist(), fidelity.tolist(), effects.tolist(), strict=True)]


def _at_magnitude(request, nodes: _Nodes, model: dict, saturation: list[float], systematic) -> NodeAnswers | None:
    """``quantity.answer_at_magnitude`` at every node (one magnitude for all), node by node in arrays."""
    magnitude, beta0 = request.magnitude, request.beta0
    if any(magnitude < m_sat - tables.BRIGHT_MARGIN_MAG for m_sat in saturation) or not nodes.held([magnitude]):
        return None  # refused (too bright) or not held: the node-by-node answer says so
    count = len(saturation)
    read = nodes.at([magnitude] * count)
    slopes, errors = (np.array(v) for v in read)
    if not (np.isfinite(slopes).all() and np.isfinite(errors).all()):
        return None
    effects = _effects(model, nodes, [magnitude] * count)
    if effects is None:
        return None
    averaging = 1.0 / math.sqrt(request.stars)
    c, c_err = np.abs(slopes) * averaging, errors * averaging
    if request.solved_for == "tolerance":
        values = c * request.precision * beta0
        statistical = c_err * request.precision * beta0
        zero = np.zeros(count, dtype=bool)
    else:
        zero = c <= np.maximum(c_err, 1e-300)  # a slope consistent with zero: no precision needed
        with np.errstate(divide="ignore", invalid="ignore"):
            values = np.where(zero, math.inf, request.target_tolerance / (c * beta0))
            statistical = values * c_err / c
    fidelity = None if systematic is None else values * systematic
    totals = _totals(statistical, fidelity, values * effects)
    uncertainties = [None if z else u for z, u in zip(zero, totals, strict=True)]
    return NodeAnswers(request.solved_for, values.tolist(), uncertainties, reads=([magnitude] * count, *read))


def _magnitudes(request, nodes: _Nodes, model: dict, saturation: list[float], systematic) -> NodeAnswers | None:
    """``quantity.answer_magnitude`` at every node: ``magnitude_scan.scan_magnitude`` on the field
    grid's c(m) of each node, then the binding limit."""
    averaging = 1.0 / math.sqrt(request.stars)
    required = request.target_tolerance / (request.precision * request.beta0 * averaging)
    faintest = nodes.faintest
    longest, sizes, within = _scan_grid(faintest, nodes.brightest, tuple(saturation))
    everywhere = _scan_values(nodes, longest)
    # Each node's scan is the first sizes[k] magnitudes of the longest (every scan steps from the
    # faint end alike): where its c(m) first exceeds what the tolerance allows, all nodes at once.
    above = np.abs(everywhere) > required
    above_inside = above & within
    at_faint_end, crossed = above[:, 0].tolist(), above_inside.any(axis=1).tolist()
    first_above = np.argmax(above_inside, axis=1).tolist()
    step = float(longest[0] - longest[1])
    m_nl: list[float | None] = []
    brackets: dict[int, tuple[float, float]] = {}
    log_derivatives: dict[int, float] = {}
    for k, size in enumerate(sizes):
        if at_faint_end[k]:
            at_faint, brighter = float(everywhere[k, 0]), float(everywhere[k, min(round(_TREND_MAG / step), size - 1)])
            if not abs(at_faint) < abs(brighter):
                return None  # no star meets the tolerance: the node-by-node answer refuses
            m_nl.append(float(faintest + 2.5 * math.log10(abs(at_faint) / required)))
            log_derivatives[k] = -0.4 * math.log(10)
        elif not crossed[k]:
            m_nl.append(None)
        else:
            first = first_above[k]
            brackets[k] = (float(longest[first]), float(longest[first - 1]))
            m_nl.append(math.nan)
    roots = _secant_roots(nodes, brackets, required)
    if roots is None:
        return None
    for k, root in roots.items():
        m_nl[k] = root
    found = _magnitude_answers(request, nodes, model, saturation, systematic, m_nl, set(brackets), log_derivatives)
    if found is None:
        return None
    scans = {k: NodeScan(*found.crossings.get(k, (None, None)), everywhere[k, :size]) for k, size in enumerate(sizes)}
    return replace(found, crossings=scans)


@lru_cache(maxsize=1024)
def _scan_grid(faintest: float, brightest: float, saturation: tuple[float, ...]) -> tuple[np.ndarray, list[int], np.ndarray]:
    """The longest of the nodes' scans (``magnitude_scan``'s: from the grid's faint end in steps
    of 0.05 mag to the node's saturation magnitude or the grid's bright end), each node's length
    of it, and (nodes, magnitudes) whether a magnitude is within the node's scan; kept per SCA."""
    grids = [np.arange(faintest, max(m_sat, brightest) - 1e-9, -0.05) for m_sat in saturation]
    longest = max(grids, key=len)
    longest.flags.writeable = False
    sizes = [g.size for g in grids]
    within = np.arange(longest.size)[None, :] < np.array(sizes)[:, None]
    within.flags.writeable = False
    return longest, sizes, within


def _scan_values(nodes: _Nodes, magnitudes: np.ndarray) -> np.ndarray:
    """(nodes, magnitudes): each node's c(m) on the scan's magnitudes (``FieldGrid.slope``'s values at
    a node: the node's own, its weights being 0 and 1 there)."""
    grid, band, sca = nodes.grid, nodes.band, nodes.sca
    if nodes.metric == "e":
        e1, e2 = grid.columns_node_values(band, sca, (f"{nodes.mode}_e1", f"{nodes.mode}_e2"), magnitudes)
        values = np.hypot(e1, e2)
    else:
        values = grid.node_values(band, sca, f"{nodes.mode}_{nodes.metric}", magnitudes)
    return values.reshape(-1, magnitudes.size)


def _secant_roots(nodes: _Nodes, brackets: dict[int, tuple[float, float]], required: float) -> dict[int, float] | None:
    """``magnitude_scan._secant_root`` of every bracketed node, side by side: each iteration reads
    every node still iterating at once. None where a bracket does not hold a sign change (the
    node-by-node answer widens it) or a slope is not held."""
    count = len(nodes.grid.arrays[f"{nodes.band}_{nodes.sca:02d}/positions"].reshape(-1, 2))

    def excesses(*points: dict[int, float]) -> list[dict[int, float] | None]:
        sets = [[p.get(k, nodes.faintest) for k in range(count)] for p in points]
        if any(not nodes.held(m) or max(m) > nodes.faintest for m in sets):
            return [None] * len(points)
        read = nodes.held_value_sets(sets)
        if read is None:
            return [None] * len(points)
        out: list[dict[int, float] | None] = []
        for p, slopes in zip(points, read, strict=True):
            if any(not math.isfinite(slopes[k]) or slopes[k] == 0 for k in p):
                return [None] * len(points)
            out.append({k: math.log(abs(slopes[k]) / required) for k in p})
        return out

    def excess(points: dict[int, float]) -> dict[int, float] | None:
        return excesses(points)[0]

    if not brackets:
        return {}  # no node crossed inside its scan: nothing to read
    a = {k: bright for k, (bright, _) in brackets.items()}
    b = {k: faint for k, (_, faint) in brackets.items()}
    fa, fb = excesses(a, b)  # both ends of every bracket in one read
    if fa is None or fb is None or any(fa[k] * fb[k] > 0 for k in brackets):
        return None
    roots: dict[int, float] = {}
    c = dict(b)
    active = set(brackets)
    for _ in range(12):
        if not active:
            break
        c.update({k: b[k] - fb[k] * (b[k] - a[k]) / (fb[k] - fa[k]) for k in active})
        fc = excess({k: c[k] for k in active})
        if fc is None:
            return None
        for k in sorted(active):
            if abs(fc[k]) < 1e-6 or abs(c[k] - b[k]) < 1e-4:
                roots[k] = c[k]
                active.discard(k)
            elif fa[k] * fc[k] < 0:
                b[k], fb[k] = c[k], fc[k]
            else:
                a[k], fa[k] = c[k], fc[k]
    roots.update({k: c[k] for k in active})
    return roots


def _crossed_slopes(nodes, crossed, binds, at_root, log_derivatives) -> tuple[list[float], list[float]] | None:
    """Every node's slope and |error| at its root (``at_root``), and d ln|c| / dm at each crossed
    node's root from the step fainter and brighter (put in ``log_derivatives``), as
    ``magnitude_scan`` finds them; the root and the step fainter in one read. None where a step
    is not held (the node-by-node answer says why)."""
    plus_points = [m + _H if k in crossed and not binds[k] else nodes.faintest for k, m in enumerate(at_root)]
    (slopes, errors), (plus, plus_errors) = nodes.at_sets([at_root, plus_points])
    minus_points = [m - _H if k in crossed and not binds[k] else nodes.faintest for k, m in enumerate(at_root)]
    if not nodes.held(minus_points) or max(minus_points) > nodes.faintest:
        return None
    minus = nodes.held_values(minus_points)
    if minus is None:
        return None
    for k in crossed:
        if binds[k]:
            continue
        read = (plus[k], plus_errors[k], minus[k])
        if not all(math.isfinite(v) for v in read) or plus[k] == 0 or minus[k] == 0:
            return None
        log_derivatives[k] = (math.log(abs(plus[k])) - math.log(abs(minus[k]))) / (2 * _H)
    return slopes, errors


def _magnitude_answers(request, nodes, model, saturation, systematic, m_nl, crossed, log_derivatives) -> NodeAnswers | None:
    """The binding limit and the uncertainty of every node's magnitude answer (``quantity.answer_magnitude``)."""
    count = len(saturation)
    binds = [m is None or m < m_sat for m, m_sat in zip(m_nl, saturation, strict=True)]
    at_root = [nodes.faintest if bound else m for m, bound in zip(m_nl, binds, strict=True)]
    if not crossed and all(binds):
        # Saturation binds at every node: each answer is its saturation magnitude, whose parts are 0
        # (no slope is read for them). A component's ratio is still asked where the parts are stated
        # against the modulus: where a node has none, the node-by-node answer says so.
        if model["stated_against"] == "modulus" and any(s is None for s in nodes.modulus_over_component(at_root)):
            return None
        return NodeAnswers("magnitude", list(saturation), [0.0] * count, {})
    if crossed:
        read = _crossed_slopes(nodes, crossed, binds, at_root, log_derivatives)
        if read is None:
            return None
        slopes, errors = read
    else:
        slopes, errors = nodes.at(at_root)
    effects = _effects(model, nodes, at_root)
    if effects is None:
        return None
    derivative = np.array([abs(log_derivatives.get(k) or 0.0) for k in range(count)])
    answered = np.array([not binds[k] and bool(log_derivatives.get(k)) for k in range(count)])
    slopes, errors = np.array(slopes), np.array(errors)
    if not (np.isfinite(slopes[answered]).all() and np.isfinite(errors[answered]).all()):
        return None
    with np.errstate(divide="ignore", invalid="ignore"):
        statistical = np.where(answered, (errors / np.abs(slopes)) / derivative, 0.0)
        fidelity = None if systematic is None else np.where(answered, systematic / derivative, 0.0)
        totals = _totals(statistical, fidelity, np.where(answered, effects / derivative, 0.0))
    values = [saturation[k] if binds[k] else m_nl[k] for k in range(count)]
    crossings = {k: (m_nl[k], None if binds[k] else log_derivatives[k]) for k in crossed}
    return NodeAnswers("magnitude", values, totals, crossings, reads=(at_root, slopes.tolist(), errors.tolist()))
