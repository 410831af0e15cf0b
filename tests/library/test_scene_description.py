"""The Roman default at a position describes itself alike however the position is given: a JSON
``scene.position`` (with or without ``"preset": "roman"``), the CLI's ``--position``, the library's
``roman_default.scene`` and the SCA range's node. A changed effect makes it another, unnamed scene."""

from __future__ import annotations

import json

import pytest

from nlpsf import cli
from nlpsf.request import presets as roman_default
from nlpsf.request.resolve import SolveRequest
from nlpsf.sim import scene as scenes
from nlpsf.solve import solver
from nlpsf.solve.over_field import range_positions

BODY = {"band": "H158", "magnitude": 19.0, "precision": 0.01}


def _json_answer(scene: dict) -> dict:
    return solver.answer(SolveRequest.from_json({**BODY, "scene": scene})).to_dict()


def _described(answer: dict) -> tuple[str, dict]:
    conditions = answer["conditions"]
    return conditions["scene_description"], json.loads(json.dumps(conditions["scene"]))


@pytest.fixture(scope="module")
def node() -> tuple[float, float]:
    """A field-grid node of H158 SCA 18 off the centre (the SCA range answers there too)."""
    request = SolveRequest.from_json(BODY)
    return next(p for p in range_positions(request) if p != (2044.5, 2044.5))


def test_every_way_of_giving_the_position_is_one_description(node, capsys):
    position = list(node)
    ways = {
        "json": _json_answer({"position": position}),
        "json preset": _json_answer({"preset": "roman", "position": position}),
    }
    sky = roman_default.fill(roman_default.NAME, "H158", 18, None, None, None, None).background_e
    ways["library"] = solver.solve(**BODY, scene=roman_default.scene(tuple(node), sky)).to_dict()
    assert cli.main(["solve", "--band", "H158", "--magnitude", "19", "--precision", "0.01", "--position",
                     f"{node[0]:g},{node[1]:g}", "--json"]) == 0  # fmt: skip
    ways["cli"] = json.loads(capsys.readouterr().out)
    described = {k: _described(v) for k, v in ways.items()}
    first = described["json"]
    assert first[0].startswith(f"{roman_default.NAME}: position ")
    assert first[1]["name"] == roman_default.NAME
    for way, value in described.items():
        assert value == first, way
    # The same numbers every way.
    assert len({v["tolerance"] for v in ways.values()}) == 1


def test_the_sca_range_node_describes_itself_as_the_position_request(node):
    ranged = solver.answer(SolveRequest.from_json(BODY)).to_dict()
    most = tuple(ranged["conditions"]["sca_range"]["most_demanding"]["position"])
    assert _described(ranged) == _described(_json_answer({"position": list(most)}))


def test_a_changed_effect_is_another_unnamed_scene(node):
    moved = scenes.from_request({"position": list(node)}, base=roman_default.base_scene())
    changed = scenes.from_request({"position": list(node), "jitter": 0.01}, base=roman_default.base_scene())
    assert moved.name == roman_default.NAME and changed.name is None
    assert not changed.describe().startswith(f"{roman_default.NAME}:")
    opts = scenes.from_options(roman_default.base_scene(), position=f"{node[0]:g},{node[1]:g}", jitter=0.01)
    assert opts.name is None and scenes.from_options(roman_default.base_scene(), position="100,200").name == roman_default.NAME
