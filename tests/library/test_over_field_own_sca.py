"""An over-field answer of the Roman default gives every SCA its own sky and read noise: each SCA's
nodes are answered as a single solve on that SCA answers them (the request built independently,
``SolveRequest.from_json`` for that SCA), not with the sky and read noise of the SCA the request
was filled for."""

from dataclasses import fields, replace

import pytest

from nlpsf.request import presets as roman_default
from nlpsf.request.resolve import SolveRequest
from nlpsf.roman import backgrounds
from nlpsf.slopes import fieldgrid
from nlpsf.solve import solver
from nlpsf.solve.over_field import own_conditions

BODY = {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}


def _arguments(request: SolveRequest) -> dict:
    """The filled request as ``solve_over_field``'s keyword arguments (as the service passes it)."""
    out = {f.name: getattr(request, f.name) for f in fields(request) if f.init}
    out.pop("band"), out.pop("sca")
    return out


def _single(sca: int, position, scene: dict | None = None):
    body = {**BODY, "sca": sca, "scene": {**(scene or {}), "position": list(position)}}
    return solver.answer(SolveRequest.from_json(body))


def test_the_scas_differ_in_sky_and_read_noise():
    # Otherwise the tests below could not tell one SCA's conditions from another's.
    exposure = roman_default.exptime_s()
    sky = [backgrounds.background_electrons(roman_default.BACKGROUND, "H158", s, exposure) for s in (3, 18)]
    assert abs(sky[0] - sky[1]) > 1e-3 * sky[1]
    assert abs(backgrounds.read_noise(3) - backgrounds.read_noise(18)) > 1e-3 * backgrounds.read_noise(18)


@pytest.mark.skipif(fieldgrid.shipped_grid() is None, reason="the Roman default's field grid is not installed")
def test_each_sca_of_the_default_over_field_is_its_own_single_solve():
    # The request as the service builds it: filled for SCA 18 (its sky, its read noise).
    filled = SolveRequest.from_json({**BODY, "sca": 18})
    answer = solver.solve_over_field("H158", [3], filled_for=18, **_arguments(filled))
    nodes = answer.conditions["over_field"]
    assert len(nodes) == 9 and {n["sca"] for n in nodes} == {3}
    for node in nodes:
        single = _single(3, node["position"])
        assert single.fidelity == "table"  # SCA 3's own default: read from the grid, not simulated
        assert node["precision"] == single.precision and node["uncertainty"] == single.uncertainty, node
    # The worst node's whole answer: SCA 3's default (filled for SCA 3 alone) at that position.
    where = tuple(nodes[[n["precision"] for n in nodes].index(answer.precision)]["position"])
    own = SolveRequest.from_json({**BODY, "sca": 3})
    worst = solver.answer(own.with_changes(scene=replace(own.scene, position=where)))
    conditions = {k: v for k, v in answer.conditions.items() if k != "over_field"}
    assert conditions == worst.conditions and answer.uncertainty == worst.uncertainty


@pytest.mark.slow
def test_a_changed_default_over_the_field_keeps_each_scas_sky_and_read_noise():
    # A changed default (jitter) is simulated at every node; its sky and read noise are still the SCA's own.
    change = {"jitter": 0.01}
    filled = SolveRequest.from_json({**BODY, "sca": 18, "scene": change})
    answer = solver.solve_over_field("H158", [3], filled_for=18, **_arguments(filled))
    for node in answer.conditions["over_field"]:
        single = _single(3, node["position"], change)
        assert node["precision"] == single.precision and node["uncertainty"] == single.uncertainty, node


def test_what_the_caller_gave_stays_on_every_sca():
    readout = {"ma_table": roman_default.MA_TABLE, "ramp_fit": roman_default.RAMP_FIT, "read_noise": 7.5}
    given = SolveRequest.from_json({**BODY, **readout, "sca": 18, "scene": {"background": 40.0, "jitter": 0.01}})
    arguments = _arguments(given)
    scene, request = own_conditions(given.scene, arguments, "H158", 18, 3)
    assert scene.background_e == 40.0 and request["ramp"].read_noise_e == 7.5
    # What the default filled for SCA 18 becomes SCA 3's, exactly as a request for SCA 3 fills it.
    filled = SolveRequest.from_json({**BODY, "sca": 18, "scene": {"jitter": 0.01}})
    scene, request = own_conditions(filled.scene, _arguments(filled), "H158", 18, 3)
    own = SolveRequest.from_json({**BODY, "sca": 3, "scene": {"jitter": 0.01}})
    assert scene == own.scene and request["ramp"] == own.ramp
    assert request["ramp"].read_noise_source == own.ramp.read_noise_source
