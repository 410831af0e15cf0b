"""A solve is a request, a plan and an answer: the request validates once and names the field at
fault, the plan says what is read and what simulated, the uncertainty combines its parts by one rule."""

import math

import pytest

from nlpsf.checks import InputError
from nlpsf.request.resolve import SolveRequest
from nlpsf.solve import solver
from nlpsf.solve.solution import Uncertainty


def test_from_mapping_names_the_field_at_fault():
    with pytest.raises(InputError) as unknown:
        SolveRequest.from_mapping({"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "colour": "red"})
    assert unknown.value.argument == "colour"
    with pytest.raises(InputError) as three:
        SolveRequest.from_mapping({"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "precision": 0.01})
    assert three.value.argument == "magnitude"
    with pytest.raises(InputError) as budget:
        SolveRequest.from_mapping({"band": "H158", "magnitude": 18.3, "shear_m": 2e-3, "size_ratio": 1.5, "precision": 0.01})
    assert budget.value.argument == "shear_m"
    with pytest.raises(InputError) as band:
        SolveRequest.from_mapping({"magnitude": 18.3, "tolerance": 1e-4})
    assert band.value.argument == "band"


def test_the_budget_sets_the_tolerance_the_shear_relation_gives():
    # Delta R / R = |m| rho^2 / 2 (nlpsf.request.shear): the request's tolerance is the budget's.
    request = SolveRequest("H158", magnitude=18.3, shear_m=2e-3, size_ratio=1.5)
    assert request.tolerance is None and request.target_tolerance == pytest.approx(2e-3 * 1.5**2 / 2, rel=1e-12)
    assert request.solved_for == "precision"


def test_the_plan_says_what_is_read_and_what_is_simulated():
    table = solver.plan(SolveRequest("H158", magnitude=18.3, tolerance=1e-4, scene="paper"))
    assert table.fidelity == "table" and table.reads == "tables" and table.scene is None and not table.notes
    other_rule = solver.plan(SolveRequest("H158", magnitude=18.3, tolerance=1e-4, pupil_scale="header", scene="paper"))
    assert other_rule.fidelity == "linear" and [n.code for n in other_rule.notes] == ["pupil_scale_simulated"]


def test_the_uncertainty_rule_counts_the_larger_optical_part_once():
    parts = Uncertainty(statistical=3.0, fidelity=4.0, optical_model=1.0, effects=0.0, pupil_scale=12.0)
    assert parts.total == pytest.approx(13.0)  # hypot(3, 4, 0, max(1, 12))
    assert parts.model == pytest.approx(12.0)
    assert Uncertainty.none().total is None and Uncertainty.none().model is None
    s = solver.solve("H158", magnitude=18.3, tolerance=1e-4, scene="paper")
    p = s.parts
    expected = math.hypot(p.statistical, p.fidelity, p.effects, max(p.optical_model, p.pupil_scale))
    assert s.uncertainty == pytest.approx(expected, rel=1e-15)


def test_accuracy_with_a_shear_budget_solves_for_the_magnitude():
    # Was refused: the first, table-level pass got both the budget's tolerance and the budget.
    budget = solver.solve("H158", precision=0.01, shear_m=2e-3, size_ratio=1.5, accuracy=0.05, scene="paper")
    direct = solver.solve("H158", precision=0.01, tolerance=2e-3 * 1.5**2 / 2, accuracy=0.05, scene="paper")
    assert budget.magnitude == pytest.approx(direct.magnitude, abs=1e-9)


def test_a_json_body_builds_the_same_request_as_the_python_call():
    from nlpsf.sim import ramps

    body = {"band": "J129", "precision": 0.01, "tolerance": 1e-4, "ma_table": "romanisim-110", "scene": "paper"}
    ramp, exptime = ramps.build(ma_table="romanisim-110")
    by_json = solver.answer(SolveRequest.from_json(body))
    by_call = solver.solve("J129", precision=0.01, tolerance=1e-4, ramp=ramp, exptime=exptime, scene="paper")
    assert by_json.magnitude == by_call.magnitude and by_json.exptime == exptime
    # The MA table's exposure is its last read unless the body gives one.
    assert SolveRequest.from_json({**body, "exptime": 300.0}).exptime == 300.0
    with pytest.raises(InputError) as scene:
        SolveRequest.from_json({"band": "H158", "magnitude": 18.3, "tolerance": 1e-4, "scene": {"jitter": "x", "colour": 1}})
    assert scene.value.argument.startswith("scene")
    # A ramp reads out the Roman preset (IPC, background, polynomial NL: ramps.check_scene) but not
    # brighter-fatter, whose charge moves by an amount quadratic in the charge collected up the ramp.
    assert SolveRequest.from_json({**body, "scene": {"preset": "roman"}}).scene.effects_on()["ipc"]
    with pytest.raises(InputError) as both:
        SolveRequest.from_json({**body, "scene": {"bfe": 1e-7}})
    assert both.value.argument == "scene" and "brighter_fatter" in both.value.reason


@pytest.mark.parametrize("scene", [{"background": 0}, {"position": [300, 3500], "background": 0.0}, {"background": 12.5}])
def test_a_background_given_to_the_default_is_the_callers_own(scene):
    # The Roman default's scene object: a background left out is the sky over the exposure, one given
    # (0 included: no sky) is what the caller asked for, and it is not the scene the field grid holds.
    from nlpsf.request import presets
    from nlpsf.roman import backgrounds
    from nlpsf.slopes.providers import NeedsSimulation

    body = {"band": "J129", "sca": 5, "magnitude": 19.0, "tolerance": 1e-3}
    sky = backgrounds.background(presets.BACKGROUND, "J129", 5, presets.exptime_s()).total_e
    assert sky > 10  # zodiacal light, thermal and dark over the HLWAS exposure: not a small number
    left_out = SolveRequest.from_json(
        {**body, "scene": {k: v for k, v in scene.items() if k != "background"} or {"preset": "roman"}}
    )
    assert left_out.scene.background_e == pytest.approx(sky, rel=1e-12)
    given = SolveRequest.from_json({**body, "scene": scene})
    assert given.scene.background_e == scene["background"]
    with pytest.raises(NeedsSimulation):
        solver.table_plan(given)  # another sky than the default's: simulated, as the CLI's --background is
