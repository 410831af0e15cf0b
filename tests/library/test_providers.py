"""The slope providers: each covers a request or refuses it with a code and the field at fault,
and the plan is the first that covers (``nlpsf.slopes.providers``, ``solver.plan``)."""

from __future__ import annotations

import pytest

from nlpsf import SolveRequest, roman
from nlpsf.slopes import fieldgrid, providers
from nlpsf.slopes.providers import NeedsSimulation, RefusalCode
from nlpsf.slopes.source import Slopes
from nlpsf.solve import solver

BASE = {"band": "H158", "sca": 18, "magnitude": 19.0, "tolerance": 1e-4}
needs_grid = pytest.mark.skipif(fieldgrid.shipped_grid() is None, reason="the Roman default's field grid is not installed")


def request(**changes) -> SolveRequest:
    return SolveRequest.from_json({**BASE, **changes})


@needs_grid
def test_the_roman_default_at_a_position_is_the_field_grids():
    the_plan = solver.plan(request(scene={"position": [1000.0, 3000.0]}))
    assert the_plan.provider == providers.FieldGrid.name and the_plan.grid is not None and the_plan.refusals == ()


@pytest.mark.parametrize(
    ("changes", "code", "field"),
    [
        ({"beta0": 6e-7}, RefusalCode.SETTING, "beta0"),
        ({"full_well": 9e4}, RefusalCode.SETTING, "full_well"),
        ({"exptime": 200.0}, RefusalCode.EXPOSURE, "exptime"),
        ({"pupil_scale": "header"}, RefusalCode.SETTING, "pupil_scale"),
        ({"linearise_at": "beta0"}, RefusalCode.SETTING, "linearise_at"),
        ({"fidelity": "linear"}, RefusalCode.FIDELITY, "fidelity"),
        ({"scene": {"position": [1000.0, 3000.0], "jitter": 0.01}}, RefusalCode.SCENE, "scene"),
    ],
)
@needs_grid
def test_the_grid_refuses_what_it_does_not_hold_naming_the_field(changes, code, field):
    changes = {"scene": {"position": [1000.0, 3000.0]}, **changes}
    got = providers.FieldGrid().covers(request(**changes), changes.get("fidelity", "table"))
    assert isinstance(got, providers.Refusal) and (got.code, got.field) == (code, field)
    the_plan = solver.plan(request(**changes)) if field != "fidelity" else None
    if the_plan is not None:  # the plan then falls to the simulator, with the grid's refusal first
        assert the_plan.provider == providers.Simulator.name and the_plan.refusals[0] == got


def test_the_paper_tables_are_one_store_keyed_by_position():
    store = providers.PaperTables()
    middle = store.at(None, 7).get("H158", 7).position_pixels
    assert store.at(middle, 7).get("H158", 7).position_pixels == middle
    if providers.field_tables() is None:
        pytest.skip("no field-point tables installed")
    for point, position in enumerate(roman.field_points(7)[1:], start=1):
        held = store.at(position, 7)
        assert held.meta["field_point"] == point and held.get("H158", 7).position_pixels == pytest.approx(position)
    assert store.at((2000.0, 100.0), 7) is None


def test_the_paper_tables_cover_their_own_positions_and_refuse_others_with_a_code():
    corner = list(roman.field_points(7)[2])
    covered = solver.plan(request(sca=7, scene={"preset": "paper", "position": corner}))
    expected = providers.PaperTables.name if providers.field_tables() is not None else providers.Simulator.name
    assert covered.provider == expected
    elsewhere = solver.plan(request(sca=7, scene={"preset": "paper", "position": [2000.0, 100.0]}))
    assert elsewhere.provider == providers.Simulator.name and elsewhere.refusals[-1].code == RefusalCode.SCENE
    pupil = solver.plan(request(scene="paper", pupil_scale="header"))
    assert pupil.refusals[-1].code == RefusalCode.PUPIL_SCALE and pupil.fidelity == "linear"


@needs_grid
def test_at_table_cost_a_refusal_is_raised_before_anything_is_simulated():
    with pytest.raises(NeedsSimulation) as raised:
        solver.table_plan(request(beta0=6e-7))
    assert raised.value.refusal.code == RefusalCode.SETTING and raised.value.argument == "beta0"
    with pytest.raises(NeedsSimulation) as raised:
        solver.table_plan(request(accuracy=0.01))
    assert raised.value.refusal.code == RefusalCode.ACCURACY
    # During the answer: a magnitude the grid does not hold is refused by the slopes themselves.
    the_plan = solver.table_plan(request(scene={"position": [1000.0, 3000.0]}))
    slopes = Slopes.for_request(request(scene={"position": [1000.0, 3000.0]}), the_plan)
    with pytest.raises(NeedsSimulation) as raised:
        slopes._simulated(10.0)
    assert raised.value.refusal.code == RefusalCode.MAGNITUDE and raised.value.argument == "magnitude"
