"""The Roman default without a position, every node answered at once (``nlpsf.solve.sca_nodes``),
is the answer node by node: the same most demanding node and answer, every node's value to the
last bit and its uncertainty to 1e-12 (the field interpolation's term is read once for all nodes)."""

from __future__ import annotations

import dataclasses
import json
import random

import pytest

from nlpsf import InputError, SolveRequest
from nlpsf.slopes import fieldgrid
from nlpsf.solve import over_field, solver

from .test_stored_answers import differences

pytestmark = pytest.mark.skipif(fieldgrid.shipped_grid() is None, reason="the Roman default's field grid is not installed")
BANDS = ("R062", "Z087", "Y106", "J129", "H158", "F184", "W146", "K213")


def requests(count: int, seed: int = 11) -> list[SolveRequest]:
    draw, out = random.Random(seed), []
    while len(out) < count:
        body = {"band": draw.choice(BANDS), "sca": draw.randint(1, 18), "metric": draw.choice(("size", "e1", "e2", "e"))}
        body["mode"] = draw.choice(("bias", "scatter"))
        solved = draw.choice(("precision", "tolerance", "magnitude"))
        if solved != "precision":
            body["precision"] = 10 ** draw.uniform(-3.0, -1.0)
        if solved != "tolerance":
            body["tolerance"] = 10 ** draw.uniform(-5.0, -2.5)
        if solved != "magnitude":
            body["magnitude"] = round(draw.uniform(15.0, 26.0), 3)
        try:
            out.append(SolveRequest.from_json(body))
        except InputError:
            continue
    return out


def as_json(solution) -> dict:
    out = solution.to_dict()
    out.pop("elapsed_s")
    return json.loads(json.dumps(out))


def test_every_node_at_once_is_the_answer_node_by_node():
    at_once = 0
    for request in requests(36):
        alone = as_json(over_field.sca_range(solver.answer, request, nodes=None))
        found = solver._node_answers(request, over_field.range_positions(request))
        together = as_json(over_field.sca_range(solver.answer, request, nodes=solver._node_answers))
        at_once += found is not None
        assert differences(alone, together, 1e-12) == [], request
        if found is not None:
            nodes = alone["conditions"]["sca_range"]["nodes"]
            assert [n[request.solved_for] for n in nodes] == [
                n[request.solved_for] for n in together["conditions"]["sca_range"]["nodes"]
            ]
    assert at_once >= 30  # the common case is the one answered at once


def test_every_nodes_uncertainty_at_once_is_its_own_answers():
    # The uncertainty of each node read at once (its model parts combined in arrays) against the
    # node's own answer (the scalar rule, roman_uncertainty.combine): a part dropped or combined by
    # another rule shows here.
    checked = 0
    for request in requests(12, seed=5):
        positions = over_field.range_positions(request)
        found = solver._node_answers(request, positions)
        if found is None:
            continue
        for position, value, uncertainty in zip(positions, found.values, found.uncertainties, strict=True):
            own = solver.answer(request.at_position(position))
            assert value == pytest.approx(getattr(own, request.solved_for), rel=1e-12, abs=0.0), (request, position)
            if uncertainty is not None and own.uncertainty is not None:
                assert uncertainty == pytest.approx(own.uncertainty, rel=1e-12), (request, position)
                checked += 1
    assert checked >= 50


def test_every_nodes_slope_read_with_the_others_is_its_own_answers_slope():
    """The most demanding node's answer takes its slope from the read of every node at once
    (``NodeAnswers.read_of``, ``Slopes.read_with_others``) instead of reading the grid again: at each
    node, that read is the node's own answer's slope to the last bit and its error to 1e-12, wherever
    the node's answer reads the slope at that magnitude (not where saturation binds)."""
    checked = 0
    for request in requests(12, seed=23):
        positions = over_field.range_positions(request)
        found = solver._node_answers(request, positions)
        if found is None or found.reads is None:
            continue  # answered node by node, or saturation binds at every node (no slope read)
        for k, position in enumerate(positions):
            magnitude, slope, error = found.read_of(k)
            own = solver.answer(request.at_position(position))
            if own.binding_limit == "saturation":
                continue
            read_at = own.nonlinearity_magnitude if request.solved_for == "magnitude" else request.magnitude
            assert magnitude == read_at and slope == own.slope, (request, position)
            assert error == pytest.approx(own.slope_uncertainty, rel=1e-12, abs=0.0), (request, position)
            checked += 1
    assert checked >= 100


def test_a_slope_read_with_the_others_answers_only_its_own_magnitude():
    from nlpsf.slopes.source import Slopes

    request = SolveRequest.from_json({"band": "H158", "sca": 7, "precision": 0.01, "magnitude": 20.0})
    node = request.at_position(over_field.range_positions(request)[3])
    the_plan = solver.plan(node)
    grid_read = Slopes.for_request(node, the_plan).at(20.0)
    told = Slopes.for_request(node, the_plan)
    told.read_with_others(20.0, 1.5, 0.25)  # not the grid's numbers: shows which is answered
    assert told.at(20.0) == (1.5, 0.25, 0) and "grid" in told.ramp_bases
    assert told.at(20.5) == Slopes.for_request(node, the_plan).at(20.5)  # another magnitude: the grid read
    unknown = Slopes.for_request(node, the_plan)
    unknown.read_with_others(20.0, float("nan"), 0.25)  # not finite: ignored, the grid read as ever
    assert unknown.at(20.0) == grid_read


def test_a_nodes_plan_moved_from_another_node_is_its_own_plan():
    """The most demanding node's answer moves the first node's plan there (``solver.plan_at_node``)
    instead of planning again: the same plan, field by field (notes, model part, tables, coverage)."""
    for request in requests(12, seed=5):
        positions = over_field.range_positions(request)
        first = solver.plan(request.at_position(positions[0]))
        for position in positions[1:]:
            at = request.at_position(position)
            assert solver.plan_at_node(first, at) == solver.plan(at), (request, position)
            assert [getattr(n, "values", None) for n in solver.plan_at_node(first, at).notes] == [
                getattr(n, "values", None) for n in solver.plan(at).notes
            ]


def test_a_range_states_its_own_scenes_name_after_an_equal_scene_without_one():
    # Scenes compare without their names: the Roman default's scene given by hand, unnamed, is equal
    # to the preset's. Each answer over the SCA states its own scene, whichever came first.
    from dataclasses import replace

    named = SolveRequest(band="H158", sca=7, precision=0.01, magnitude=20.0)
    unnamed = SolveRequest(band="H158", sca=7, precision=0.01, magnitude=20.0, scene=replace(named.scene, name=None))
    assert unnamed.scene == named.scene
    first = solver.answer(unnamed)
    second = solver.answer(named)
    assert first.conditions["scene"]["name"] is None and not first.conditions["scene_description"].startswith("roman:")
    assert second.conditions["scene"]["name"] == "roman" and second.conditions["scene_description"].startswith("roman:")


def test_where_saturation_binds_at_every_node_each_node_is_its_own_answer():
    # A tolerance no star on the SCA reaches: every node's answer is its saturation magnitude (read
    # at once without a slope), as answering the node alone gives it, uncertainty and all.
    checked = 0
    for band, sca, metric in (("H158", 7, "size"), ("W146", 3, "e1"), ("K213", 12, "e")):
        request = SolveRequest.from_json({"band": band, "sca": sca, "metric": metric, "precision": 1e-3, "tolerance": 0.05})
        positions = over_field.range_positions(request)
        found = solver._node_answers(request, positions)
        assert found is not None
        for position, value, uncertainty in zip(positions, found.values, found.uncertainties, strict=True):
            own = solver.answer(request.at_position(position))
            assert own.binding_limit == "saturation" and value == own.magnitude == own.saturation_magnitude
            assert uncertainty == own.uncertainty, (request, position)
            checked += 1
    assert checked >= 27


def test_a_kept_first_node_plan_is_the_plan_of_every_request_with_its_conditions():
    # The answers over one SCA plan its first node once (``solver._first_node_plan``, kept by the
    # request's conditions): other numbers at the same conditions get the plan planned afresh; other
    # conditions (a scene's name, its background, the SCA, beta0) get their own.
    base = {"band": "J129", "sca": 4, "metric": "e1", "precision": 0.02}
    kinds = [{"tolerance": 1e-4}, {"tolerance": 3e-3}, {"magnitude": 19.5}, {"magnitude": 23.25}]
    kept = []
    for numbers in kinds:
        request = SolveRequest.from_json({**base, **numbers})
        first = request.at_position(over_field.range_positions(request)[0])
        plan = solver._first_node_plan(first, True)
        assert plan == solver.plan(first, fresh_between_limits=False), numbers
        kept.append(first.conditions_key())
    assert len(set(kept)) == 1
    others = [
        {**base, "tolerance": 1e-4, "sca": 5},
        {**base, "tolerance": 1e-4, "beta0": 1e-6},
        {**base, "tolerance": 1e-4, "scene": {"background": 0}},
    ]
    for body in others:
        assert SolveRequest.from_json(body).conditions_key() not in kept, body
    named = SolveRequest(band="H158", sca=7, precision=0.01, magnitude=20.0)
    unnamed = SolveRequest(band="H158", sca=7, precision=0.01, magnitude=20.0, scene=dataclasses.replace(named.scene, name=None))
    assert named.conditions_key() != unnamed.conditions_key()


def test_an_answers_model_part_is_its_own_when_its_plan_is_kept():
    # A caller who edits one answer's model part (a dict of parts) changes no later answer's.
    request = SolveRequest.from_json({"band": "H158", "sca": 2, "metric": "size", "precision": 0.01, "magnitude": 21.0})
    assert request.scene.position is None  # the SCA's range: its first node's plan is kept
    before = as_json(solver.answer(request))
    edited = solver.answer(request)
    for name in ("included", "left_out"):
        for part in edited.model[name]:
            part["name"] = "edited"
        edited.model[name].append({"name": "added"})
    assert differences(before, as_json(solver.answer(request)), 0.0) == []
