"""The two-of-three requirement calculator (paper, Eq. ``calib`` and section 4).

For a metric (size ΔR/R, e1, e2, or the modulus |Δe| = hypot(Δe1, Δe2)) and a mode (``bias``: a
calibration error Δβ = p β0 in the mean NL coefficient; ``scatter``: a per-pixel spread
σβ = p β0), the PSF error is

    T = |c(m)| p β0,

with c(m) the slope d(metric)/dβ (bias) or σ(metric)/σβ (scatter) at magnitude m, exposure t and
β0. Given any two of (precision p, tolerance T, magnitude m) the third follows. Solving for m
returns the magnitude at which the NL error reaches the tolerance, and the brightest usable star:
the fainter of that and the saturation magnitude, with which limit binds.

Shear budgets. Instead of the tolerance, a shear-bias budget may be given: ``shear_m`` (the
multiplicative bias, size metric) or ``shear_c`` (the additive bias, e metrics) with the
galaxy-to-PSF size ratio ``size_ratio`` (a number or a distribution); ``nlpsf.request.shear`` turns it into
the tolerance (ΔR/R = |m| ρ²/2, Δe = 2 |c| ρ², derived there). With ``size_ratio`` alone, the answer
reports the shear bias that its tolerance implies.

Averaging (scatter mode). A per-pixel β spread is fixed in the detector, but each star of a PSF
model, and each dither of it, falls on other pixels: its NL error is an independent draw as long as
no two of them share the pixels under the moment weight (a few native pixels around each centroid).
A PSF model that averages ``stars`` such images with equal weight then has the scatter
σ(metric)/√stars, and the answer holds for that model; with stars of different brightness, all taken
at the answer's (brightest) magnitude, it is an upper bound. A bias in the mean β is common to
every star, so averaging does not reduce it and ``stars`` applies to scatter mode only.

Slopes come from the shipped tables (``fidelity="table"``, microseconds) or from fresh simulations
(``linear``, ``monte_carlo``, ``polychromatic``); ``accuracy`` picks the cheapest level whose
measured error (``nlpsf tradeoff``) meets it.

Up-the-ramp exposures (``ramp``, see ``nlpsf.sim.ramps``; in a scene where ``ramps.check_scene``
allows): the saturation rule becomes Roman's (a star
is usable until its brightest pixel saturates in the resultant a slope needs -- the first, or the
second where one resultant gives no slope, as in romancal -- about 2.5 log10(T / t_k) mag brighter
than the final-frame rule, exactly ``Ramp.saturation_shift_mag(T, full well, beta0, background)``),
and the slopes come from the tables where the mapping is exact (quadratic NL, OLS fit, every
pixel keeping every resultant: the final frame at beta_eff = c_2 beta0,
c_2 = 1 + 1/N for N uniform reads, so c(m) = c_2 c_table(m; c_2 beta0)) and from fresh
linear-response simulations of the ramp otherwise (optimal fit, or a star bright enough that some
of its pixels drop saturated resultants). ``conditions["ramp_slopes_from"]`` says which.

Model part. Every answer says what it leaves out of a Roman scene (``model``) and adds it to its
``uncertainty`` (``uncertainty_model``): the scene effects it does not simulate, the spread over the
SCA when no position is given, and the pupil-mask scale rule. With ``accuracy`` they are measured at
the answer's point (``nlpsf.solve.impact``) and added in quadrature; otherwise they come from a shipped
measurement (``nlpsf/data/scene_model_uncertainty.json``: each effect's worst impact on SCA 1, 9
and 18 at two magnitudes) and are added up, since a Roman star has them all at once with signs often
alike. The pupil-scale rule and ``uncertainty_optical_model`` (the official-PSF comparison) both
measure the optical model's error, so the total counts the larger of the two, not both. The Roman
default's answers (its preset, with or without ``accuracy``) carry its own parts instead
(``model_part.roman_default_model``: the optics' vintage among them, so the official-PSF figure is
not added), an ``accuracy`` answer's left-out set beside them as a part of its own.
"""

from __future__ import annotations

import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, replace
from functools import lru_cache, partial

from nlpsf import defaults
from nlpsf.checks import InputError
from nlpsf.flags import Flag, FlagCode, make
from nlpsf.frozen import replaced
from nlpsf.request import shear
from nlpsf.request.resolve import SolveRequest
from nlpsf.sim import ramps
from nlpsf.slopes import fidelity as levels
from nlpsf.slopes import fieldgrid, providers, tables
from nlpsf.slopes.fidelity import choose_fidelity, fidelity_error
from nlpsf.slopes.source import Slopes as _Slopes

from . import conditions as answer_conditions
from . import model_part, quantity, sca_nodes
from .centroids import enough_centroids
from .over_field import grid_size, sca_range, worst_over_field
from .solution import Solution
from .validity import (
    _validity_flags,
    between_limits_note,
    component_flags,
    fresh_between_limits,
)

METRICS = defaults.METRICS
MODES = defaults.MODES
FIDELITIES = levels.LEVELS


def solve(
    band: str,
    sca: int = 18,
    metric: str = "size",
    mode: str = "bias",
    beta0: float = defaults.BETA0,
    exptime: float | None = None,
    precision: float | None = None,
    tolerance: float | None = None,
    magnitude: float | None = None,
    full_well: float = defaults.FULL_WELL_E,
    fidelity: str | None = None,
    accuracy: float | None = None,
    shear_m: float | None = None,
    shear_c: float | None = None,
    size_ratio: float | list | str | shear.SizeRatio | None = None,
    stars: int = 1,
    tables_set: tables.TableSet | None = None,
    ramp: ramps.Ramp | None = None,
    throughput: str | None = None,
    scene=None,
    pupil_scale: str | None = None,
    linearise_at: str | None = None,
    preset: str | None = None,
    residual_nl: str | None = None,
) -> Solution:
    """Give exactly two of ``precision`` (Δβ/β0, or σβ/β0 in scatter mode), ``tolerance`` (the PSF
    error allowed) and ``magnitude`` (AB); get the third. See the module docstring.

    A thin wrapper: ``answer(SolveRequest(...), tables_set)``. ``shear_m`` (size metric) or
    ``shear_c`` (e metrics), with ``size_ratio`` = R_gal/R_psf (a number, (ratio, weight) pairs, or
    a string ``nlpsf.request.shear.check_size_ratio`` reads), stands in for ``tolerance``. ``stars``
    (scatter mode): the PSF model averages that many independent star images (σ / √stars).

    ``ramp``: an up-the-ramp exposure (``ramps.Ramp``; e.g. ``ramps.Ramp.uniform(N, exptime)``)
    instead of the paper's single final frame. ``exptime`` stays what is given: for an MA table whose
    exposure is its last read, ``ramps.build(ma_table=...)`` returns both (as the CLI and the service do).

    ``throughput`` (``defaults.THROUGHPUTS``) is the photometry that turns the magnitude into
    electrons; None is the tables' own. Another one reads the tables relabelled
    (``tables.with_throughput``), and fresh simulations use it directly.

    ``scene`` (``nlpsf.sim.scene.SceneModel``) is what the star goes through; with ``accuracy`` the
    answer models only the effects whose measured impact at the point exceeds it (see
    :func:`nlpsf.solve.accuracy.select`) and its uncertainty gains a ``model`` part for those left out.

    ``pupil_scale`` (``roman.PUPIL_SCALE_RULES``) is the pupil-mask scale rule of fresh
    simulations; None is the preset's (roman: official; paper: the tables' own, galsim). Another
    rule than the tables' is not in them, so a table solve is then simulated (fidelity linear).

    The Roman default. ``scene`` None (or "roman") is the Roman star as observed
    (``nlpsf.request.presets``): its scene at the position, the HLWAS readout and exposure unless
    ``ramp`` / ``exptime`` are given, the official pupil scale and the corrected state
    (``linearise_at``); without a position the answer is the most demanding of the SCA's field-grid
    nodes, with the range in ``conditions["sca_range"]``. ``scene="paper"`` is the paper's
    idealised scene and final frame (the shipped tables, today's answers), ``"galsim-roman"``
    GalSim's Roman constants on it; ``preset`` names the base when ``scene`` is a ``SceneModel``.
    ``residual_nl`` (``experiment.correction.RESIDUAL_MODELS``): how a calibration error acts in the
    corrected state; None the default's (the correction on every resultant, as romancal applies it).
    """
    request = SolveRequest(
        band, sca, metric, mode, beta0, exptime, precision, tolerance, magnitude, full_well, fidelity, accuracy,
        shear_m, shear_c, size_ratio, stars, ramp, throughput, scene, pupil_scale, linearise_at, preset, residual_nl,
    )  # fmt: skip
    return answer(request, tables_set)


@dataclass(frozen=True)
class SolvePlan:
    """What a solve reads and what it simulates, and why (the notes, flags of the answer)."""

    #: The fidelity level the slopes come at ("table": read from the tables; else simulated).
    fidelity: str
    #: The scene the fresh simulations go through (None: the paper's, or nothing simulated).
    scene: object | None
    #: The tables read (the shipped SCA-centre set, or a corner field point's).
    tables: tables.TableSet
    #: What the answer leaves out of a Roman scene (measured with ``accuracy``, else shipped).
    model: dict
    notes: tuple[Flag, ...]
    #: Centroids of the fresh simulations (None: the tables' own; ``accuracy`` sets its own).
    realizations: int | None = None
    #: The Roman default's field grid the slopes are read from (None: tables or simulations).
    grid: object | None = None
    #: The provider that covers the request (``providers``: "field grid", "paper tables", "simulator").
    provider: str = providers.PaperTables.name
    #: Why the providers before it did not cover the request (empty where the first covered).
    refusals: tuple[providers.Refusal, ...] = ()
    #: Whether the answer may simulate a magnitude the grid turns out not to hold (a batch: no).
    simulate: bool = True

    @property
    def reads(self) -> str:
        return "tables" if self.fidelity == "table" else f"fresh simulations at fidelity {self.fidelity}"


def plan(
    request: SolveRequest, tables_set: tables.TableSet | None = None, simulate: bool = True, fresh_between_limits: bool = True
) -> SolvePlan:
    """Choose the fidelity, the scene to simulate and the tables to read for ``request``: the first
    provider (``nlpsf.slopes.providers``) that covers it. ``simulate`` False: the answer refuses
    (``providers.NeedsSimulation``) where it would simulate a magnitude the grid does not hold.
    ``fresh_between_limits`` False: the grid's plan even where the request's magnitude lies between
    the saturation limits at its position (the page's curves, which leave those magnitudes out)."""
    default = _measured_default(request)
    chosen, notes = choose_fidelity(request.fidelity, request.accuracy, request.band, request.metric, request.mode, default)
    model_info, simulated_scene, realizations = None, None, None
    if request.accuracy is not None:
        point = request.magnitude
        if point is None:
            # The effects are measured where the answer will be: a first, table-level pass finds it.
            first = answer(request.table_pass(), tables_set)
            point = first.magnitude if first.magnitude is not None else defaults.MAGNITUDE
        from .accuracy import select  # impacts measured inside the full scene; the simulator is loaded there

        selection = select(request, float(point), tables_set)
        chosen, simulated_scene, model_info, notes = selection.fidelity, selection.scene, selection.model, selection.notes
        realizations = selection.realizations
    elif request.scene is not None and not request.scene.no_effects:
        simulated_scene = request.scene
    tableset = tables_set or providers.PaperTables().tables_for(simulated_scene, request.sca)
    coverage, refusals = _cover(request, chosen, simulated_scene, tableset)
    between = between_limits_note(request, coverage.grid, request.magnitude) if fresh_between_limits else None
    if between is None:
        notes.extend(_coverage_notes(request, coverage, refusals, tableset))
    else:
        # Between the saturation limits the grid misses a fresh simulation: the position is simulated afresh.
        coverage = providers.Simulator().covers(request, chosen, tableset)
        notes.append(between[0])
        realizations = between[1]
        why = "between the saturation limits at this position the field grid misses a fresh simulation"
        refusals = [*refusals, providers.Refusal(providers.RefusalCode.FIDELITY, "magnitude", why)]
    if model_info is None:
        # No accuracy asked for: what the answer leaves out comes from the shipped measurement.
        table_rule = str(tableset.get(request.band, request.sca).settings["pupil_scale"])
        model_info = model_part.shipped_model(
            request.band, request.sca, request.metric, request.mode, simulated_scene, coverage.fidelity,
            default=default, pupil_scale=request.pupil_scale or table_rule, request=request,
        )  # fmt: skip
    breaking = simulated_scene.breaks_beta_q_scaling() if simulated_scene is not None else None
    if breaking:
        verb = "adds" if len(breaking) == 1 else "add"
        notes.append(make(FlagCode.BETA_Q_RULE_BROKEN, effects=", ".join(breaking), verb=verb, names=list(breaking)))
    return SolvePlan(
        coverage.fidelity, simulated_scene, tableset, model_info, tuple(notes), realizations=realizations,
        grid=coverage.grid, provider=coverage.provider, refusals=tuple(refusals), simulate=simulate,
    )  # fmt: skip


def _cover(request: SolveRequest, fidelity: str, scene, tableset) -> tuple[providers.Coverage, list[providers.Refusal]]:
    """The first provider that covers the request, and the refusals of those before it: the field
    grid (the Roman default's preset only), the paper tables, the simulator."""
    refusals = []
    candidates = [providers.FieldGrid()] if request.policy.field_grid else []
    for provider in candidates:
        got = provider.covers(request, fidelity)
        if isinstance(got, providers.Coverage):
            return got, refusals
        refusals.append(got)
    got = providers.PaperTables().covers(request, scene, fidelity, tableset)
    if isinstance(got, providers.Coverage):
        return got, refusals
    refusals.append(got)
    return providers.Simulator().covers(request, fidelity, tableset), refusals


def _coverage_notes(request: SolveRequest, coverage: providers.Coverage, refusals, tableset) -> list[Flag]:
    """The flags that say where the slopes come from: the grid at the position, or why a table-level
    request is simulated instead."""
    code = providers.RefusalCode
    if coverage.grid is not None and request.scene.position is not None:
        size = grid_size(coverage.grid, request)
        x, y = request.scene.position
        return [make(FlagCode.DEFAULT_FROM_GRID, grid=size, scheme="lagrange", x=x, y=y)]
    if coverage.provider != providers.Simulator.name or not refusals:
        return []
    last = refusals[-1]
    if last.code == code.SCENE:
        if request.policy.field_grid:
            return [make(FlagCode.DEFAULT_SIMULATED, why=refusals[0].why)]
        return [make(FlagCode.SCENE_SIMULATED)]
    if last.code == code.PUPIL_SCALE:
        table_rule = str(tableset.get(request.band, request.sca).settings["pupil_scale"])
        return [make(FlagCode.PUPIL_SCALE_SIMULATED, table_rule=table_rule, rule=request.pupil_scale)]
    if last.code == code.LINEARISED:
        return [make(FlagCode.LINEARISED_SIMULATED, state=request.linearise_at)]
    return []


def table_plan(request: SolveRequest, tables_set: tables.TableSet | None = None) -> SolvePlan:
    """The plan of ``request`` where the tables or the field grid cover it (``simulate=False``: a
    magnitude the grid does not hold is refused too); else ``providers.NeedsSimulation`` with the
    first refusal's code and field, raised before anything is simulated."""
    refusal = providers.Refusal
    code = providers.RefusalCode
    if request.accuracy is not None:
        why = f"an accuracy target is met by measuring the scene's effects in fresh simulations: {providers.REFUSAL}"
        raise providers.NeedsSimulation(refusal(code.ACCURACY, "accuracy", why))
    if not request.policy.field_grid and request.ramp is not None:
        # The paper's scene up the ramp maps onto the tables only for some fits and magnitudes.
        why = f"a ramp on the paper's scene is simulated where the tables do not map it exactly: {providers.REFUSAL}"
        raise providers.NeedsSimulation(refusal(code.READOUT, "ramp", why))
    the_plan = plan(request, tables_set, simulate=False)
    if the_plan.fidelity == "table":
        return the_plan
    first = the_plan.refusals[0] if the_plan.refusals else refusal(code.FIDELITY, "fidelity", "")
    simulated = {
        FlagCode.SCENE_SIMULATED,
        FlagCode.PUPIL_SCALE_SIMULATED,
        FlagCode.DEFAULT_SIMULATED,
        FlagCode.LINEARISED_SIMULATED,
        FlagCode.DEFAULT_BETWEEN_LIMITS,
    }
    notes = "; ".join(str(n) for n in the_plan.notes if getattr(n, "code", None) in simulated)
    why = f"it needs a fresh simulation ({notes or 'fidelity ' + the_plan.fidelity}): {providers.REFUSAL}"
    raise providers.NeedsSimulation(refusal(first.code, first.field, why))


def plan_at_node(base: SolvePlan, request: SolveRequest) -> SolvePlan:
    """``plan(request)`` from ``base``, the plan of the same request at another node of its SCA's
    field grid (the SCA range plans its first node, then answers its most demanding one in full):
    only the scene's position and the note naming it differ. The tables, the coverage, the model part
    and the other notes do not depend on the position, and a node is never between the saturation
    limits (``validity.between_limits``). ``tests/library/test_sca_nodes.py`` checks it equal to
    planning the node again."""
    if base.grid is None or base.scene is None or request.scene.position is None:
        raise ValueError("plan_at_node moves a field-grid plan from one node of an SCA to another")
    x, y = request.scene.position
    notes = tuple(
        _flag_of(FlagCode.DEFAULT_FROM_GRID, tuple({**note.values, "x": x, "y": y}.items()))
        if getattr(note, "code", None) == FlagCode.DEFAULT_FROM_GRID
        else note
        for note in base.notes
    )
    return replaced(base, scene=request.scene, notes=notes)


@lru_cache(maxsize=4096)
def _flag_of(code: FlagCode, values: tuple) -> Flag:
    """The flag of ``code`` quoting ``values`` ((name, value) pairs), made once: an SCA's nodes are
    few and its answers many, and a plan's flags are shared between answers already (the kept plans)."""
    return make(code, **dict(values))


def _measured_default(request: SolveRequest) -> str:
    """Which shipped measurement (fidelity errors, model part) an answer reads: the Roman default's
    for its preset ("roman"), the paper scene's otherwise (``fidelity.DEFAULT_SCENES``)."""
    return request.policy.measured_as


@dataclass(frozen=True)
class _Limits:
    """Saturation magnitudes: the rule in use and the single final frame's, and where they come from."""

    saturation: float
    final_frame: float
    #: Whose star the limits are of (``conditions["saturation_from"]``; None: the tables', unsaid).
    source: str | None = None


def _own_star(request: SolveRequest, the_plan: SolvePlan) -> bool:
    """Whether the answer's limits are the simulated scene's own star: a scene other than the
    paper's that is simulated (not held by tables or the grid). ``--scene paper`` keeps the tables'
    limits whatever it simulates (its answers stay bit for bit)."""
    scene = the_plan.scene
    return (
        not request.policy.tables_limits
        and scene is not None
        and not scene.no_effects
        and the_plan.grid is None
        and the_plan.fidelity != "table"
    )


def _limits(request: SolveRequest, the_plan: SolvePlan, slopes: _Slopes) -> _Limits:
    background = 0.0 if the_plan.scene is None else the_plan.scene.background_e
    if background >= request.full_well:
        raise InputError(
            "background", f"a background of {background:g} e- fills the full well ({request.full_well:g} e-) by itself"
        )
    grid, position = the_plan.grid, None if the_plan.scene is None else the_plan.scene.position
    ramp = request.ramp
    if grid is not None and position is not None:
        # The Roman default's own star (its peak through the default's optics and detector, with its
        # sky), recorded at every node by the grid's build: not the paper table's sharper star.
        saturation = grid.saturation_magnitude(request.band, request.sca, position)
        final = grid.final_frame_saturation_magnitude(request.band, request.sca, position)
        if final is not None:
            source = f"the Roman default's own star: its field grid's nodes ({fieldgrid.SHIPPED_NAME}), interpolated"
            return _Limits(saturation, final, source)
    # A ramp's star is usable until its brightest pixel keeps fewer resultants than a slope needs: exact
    # under the ramp's rules, at the raw beta0 (saturation is flagged before the NL is corrected).
    # (Not asked where the grid answers: its nodes recorded the ramp's limit itself.)
    shift = 0.0 if ramp is None else ramp.saturation_shift_mag(request.exptime, request.full_well, request.beta0, background)
    if _own_star(request, the_plan):
        # The star that is simulated (its optics, SED, blurs and sky), from its own prepared peak.
        final_frame, peak = slopes.own_final_frame_saturation()
        source = (
            f"the simulated scene's own star: its prepared peak ({peak:.6g} of the flux in the brightest fine pixel, "
            f"over every sub-pixel centroid) on top of {background:g} e- of background against the full well "
            f"{request.full_well:g} e-" + ("" if ramp is None else f"; the ramp's limit {shift:.4g} mag brighter")
        )
        return _Limits(final_frame - shift, final_frame, source)
    # A background fills part of the well: the star saturates where its peak reaches the rest.
    final_frame = slopes.table.saturation(request.exptime, request.full_well - background)
    source = None if request.policy.tables_limits else "the tables' star (the paper's scene at the tables' position)"
    return _Limits(final_frame - shift, final_frame, source)


def answer(
    request: SolveRequest,
    tables_set: tables.TableSet | None = None,
    simulate: bool = True,
    progress=None,
    crossing=None,
    node_plan: SolvePlan | None = None,
    node_read: tuple[float, float, float] | None = None,
) -> Solution:
    """The answer to a validated request: plan, slopes, the solved quantity with its uncertainty.
    ``simulate`` False: at table cost only (:func:`table_plan`; a batch's rows). ``progress(done,
    total, message)``: told as each node of an SCA range is answered (the Roman default without a
    position). ``crossing``: a magnitude solve's scan at this node and its crossing, found with the
    SCA's other nodes (``sca_nodes``; ``magnitude_scan.NodeScan``), not read or sought again. ``node_plan``: the
    plan of the same request at another node of the SCA's field grid (:func:`plan_at_node`), moved
    here rather than planned again. ``node_read``: (magnitude, slope, |error|) of this node's field-grid
    slope read with the SCA's other nodes (``sca_nodes``), not read again at that magnitude."""
    start = time.perf_counter()
    if request.policy.ranges_over_sca and request.scene.position is None and request.accuracy is None:
        # The Roman default depends on the position: without one, the range over the SCA. (With an
        # accuracy, the answer is for the SCA centre: nlpsf.solve.accuracy measures inside that full scene.)
        nodes = partial(_node_answers, tables_set=tables_set, simulate=simulate)
        return sca_range(partial(answer, simulate=simulate), request, tables_set, progress, nodes=nodes, start=start)
    if node_plan is not None:
        the_plan = plan_at_node(node_plan, request)
    else:
        the_plan = plan(request, tables_set) if simulate else table_plan(request, tables_set)
    slopes = _Slopes.for_request(request, the_plan)
    the_plan, slopes = enough_centroids(request, the_plan, slopes, _Slopes.for_request)
    if node_read is not None:
        slopes.read_with_others(*node_read)
    flags: list[str] = list(the_plan.notes)
    if "relabelled_from" in slopes.table.settings:
        flags.append(_relabel_flag(request, slopes))
    limits = _limits(request, the_plan, slopes)
    level = the_plan.model.get("level")  # an accuracy answer's level error, for the scene it simulates
    systematic, systematic_note = (
        (level["error"], None)
        if level
        else fidelity_error(the_plan.fidelity, request.band, request.metric, request.mode, _measured_default(request))
    )
    if systematic_note:
        flags.append(systematic_note)
    if request.solved_for == "magnitude":
        result = quantity.answer_magnitude(request, slopes, limits, the_plan.model, systematic, flags, crossing)
        between = None if result.binding != "nonlinearity" else between_limits_note(request, the_plan.grid, result.magnitude)
        if between is not None:
            # The grid's NL limit lies between the saturation limits: solved again on fresh simulations
            # (where saturation binds, the answer is the grid's limit itself, not the slope's).
            fresh = fresh_between_limits(partial(answer, tables_set=tables_set), request, simulate, between[0], result.magnitude)
            return replace(fresh, elapsed_s=time.perf_counter() - start)
    else:
        result = quantity.answer_at_magnitude(request, slopes, limits, the_plan.model, systematic, flags)
    return _solution(request, the_plan, slopes, limits, result, flags, start)


def _solution(
    request: SolveRequest,
    the_plan: SolvePlan,
    slopes: _Slopes,
    limits: _Limits,
    result: quantity.Answer,
    flags: list,
    start: float,
) -> Solution:
    """The answer's validity flags, conditions and shear budget around the solved quantity: the Solution."""
    flags += _validity_flags(slopes, result.magnitude, result.precision, request.beta0, request.full_well)
    flags += [f for f in component_flags(slopes, request.metric, result.magnitude, result.slope, result.slope_error)
              if f.code not in {getattr(g, "code", None) for g in flags}]  # fmt: skip
    flags += slopes.slope_quality_flags()
    if slopes.grid_misses:
        flags.append(make(FlagCode.DEFAULT_SIMULATED, why=f"m={min(slopes.grid_misses):.3g} is outside a node's magnitude grid"))
    conditions = answer_conditions.conditions(request, the_plan, slopes)
    conservative, ranges = model_part.answer_extras(request.solved_for, result, result.log_derivative)
    shear_answer = None
    if request.ratio is not None and result.tolerance is not None and math.isfinite(result.tolerance):
        statistical = result.parts.statistical if request.solved_for == "tolerance" else None
        shear_answer = quantity.shear_answer(request.metric, request.budget, request.ratio, result.tolerance, statistical)
        if request.metric != "size":
            flags.append(make(FlagCode.SHEAR_CROSS_TERM))
    if slopes.pupil_scale is not None and the_plan.fidelity != "table":
        conditions["pupil_scale"] = slopes.pupil_scale
    answer_conditions.add_simulation_conditions(conditions, the_plan, slopes)
    if limits.source is not None:
        conditions["saturation_from"] = limits.source
    return Solution(
        band=request.band,
        sca=request.sca,
        metric=request.metric,
        mode=request.mode,
        beta0=request.beta0,
        exptime=request.exptime,
        full_well=request.full_well,
        precision=result.precision,
        tolerance=result.tolerance,
        magnitude=result.magnitude,
        solved_for=request.solved_for,
        parts=result.parts,
        slope=result.slope,
        slope_uncertainty=result.slope_error,
        saturation_magnitude=limits.saturation,
        final_frame_saturation_magnitude=limits.final_frame,
        brightest_usable_magnitude=result.brightest,
        binding_limit=result.binding,
        nonlinearity_magnitude=result.m_nl,
        flags=flags,
        fidelity=the_plan.fidelity,
        conditions=conditions,
        elapsed_s=time.perf_counter() - start,
        stars=request.stars,
        applies_to=conditions["applies_to"],
        shear=shear_answer,
        model=result.model,
        conservative=conservative,
        ranges=ranges,
    )


def _node_answers(request: SolveRequest, positions, tables_set=None, simulate: bool = True):
    """Every node's value and uncertainty of the Roman default without a position, at once
    (``sca_nodes.answer_nodes``), where its field grid covers it; None: answer node by node."""
    first = request.at_position(positions[0])
    the_plan = _first_node_plan(first, simulate) if tables_set is None else None
    if the_plan is None:
        # A node is never between the saturation limits (``validity.between_limits``): not asked.
        the_plan = plan(first, tables_set, fresh_between_limits=False) if simulate else table_plan(first, tables_set)
    grid = the_plan.grid
    if grid is None or tables_set is not None or the_plan.scene.background_e >= request.full_well:
        return None
    if grid.final_frame_saturation_magnitude(request.band, request.sca, positions[0]) is None:
        return None  # the limits are then not the grid's own
    # Each node's own value (its interpolation weights are 0 and 1 there), in the positions' order.
    saturation = [float(m) for m in grid.saturation_magnitudes(request.band, request.sca).reshape(-1)]
    systematic = fidelity_error(the_plan.fidelity, request.band, request.metric, request.mode, _measured_default(request))[0]
    found = sca_nodes.answer_nodes(request, the_plan, saturation, systematic)
    return None if found is None else replace(found, plan=the_plan)


#: The plans of SCA ranges' first nodes (:func:`_first_node_plan`), least recently used dropped first.
_FIRST_NODE_PLANS: OrderedDict[tuple, SolvePlan] = OrderedDict()
_FIRST_NODE_PLANS_LOCK = threading.Lock()


def _first_node_plan(first: SolveRequest, simulate: bool) -> SolvePlan | None:
    """The plan of an SCA range's first node (no magnitude's place asked: a node is never between the
    saturation limits), kept by the request's conditions and the shipped grid: the answers over one SCA
    plan it once, whatever their numbers. Each gets the model part as its own copy. None where a
    condition is unhashable (the caller plans)."""
    try:
        key = (first.conditions_key(), simulate, fieldgrid.shipped_grid())
    except TypeError:
        return None
    with _FIRST_NODE_PLANS_LOCK:
        kept = _FIRST_NODE_PLANS.get(key)
        if kept is not None:
            _FIRST_NODE_PLANS.move_to_end(key)
    if kept is None:
        kept = plan(first, fresh_between_limits=False) if simulate else table_plan(first)
        with _FIRST_NODE_PLANS_LOCK:
            _FIRST_NODE_PLANS[key] = kept
            while len(_FIRST_NODE_PLANS) > 1024:
                _FIRST_NODE_PLANS.popitem(last=False)
    return replaced(kept, model=model_part.own_copy(kept.model))


def _relabel_flag(request: SolveRequest, slopes: _Slopes) -> Flag:
    size_error, e_error = tables.RELABEL_ERROR[request.band]
    return make(
        FlagCode.THROUGHPUT_RELABELLED,
        source=slopes.table.settings["relabelled_from"],
        throughput=request.throughput,
        shift=-slopes.relabel_shift,
        percent=100 * (size_error if request.metric == "size" else e_error),
    )


def solve_over_field(band: str, scas="all", scene=None, progress=None, filled_for: int | None = None, **request) -> Solution:
    """The answer for the worst position over the field (``nlpsf.solve.over_field.worst_over_field``):
    the Roman default's field-grid nodes, or another scene's centre and four corners, of the given
    SCAs (``"all"``: the 18 of the focal plane).
    ``filled_for``: the SCA whose Roman-default sky and read noise ``scene`` and ``ramp`` hold."""
    return worst_over_field(solve, band, scas, scene, progress, filled_for, **request)
