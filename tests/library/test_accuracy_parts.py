"""An ``accuracy`` answer of the Roman default carries the default's model parts, as its table and
grid answers do, with the accuracy's own level error and left-out set as separate parts.

The expected values are read from ``nlpsf/data/roman_model_uncertainty.json`` directly (json, not the
library's reader) and combined by hand by the documented rule: the standard parts (optics, jitter,
charge_diffusion) in quadrature, the shifts left out (diffusion_profile, brighter_fatter, nl_shape)
added linearly; a part at a magnitude is the larger |value| of the measured magnitudes either side
of it (the nearest end outside them)."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from importlib import resources

import pytest

from nlpsf.request import presets as roman_default
from nlpsf.request.resolve import SolveRequest
from nlpsf.solve import accuracy, model_part, solver

CHOICES = ("optics", "jitter", "charge_diffusion")
LEFT_OUT = ("diffusion_profile", "brighter_fatter", "nl_shape")
POSITION = (1000.0, 3000.0)


def _file_parts(band: str, sca: int, mode: str, metric: str) -> dict:
    data = json.loads((resources.files("nlpsf") / "data" / "roman_model_uncertainty.json").read_text())
    entry = data["per_band"][band][mode][metric]
    return (entry["per_sca"].get(str(sca)) or entry["worst"])["parts"]


def _at(rows: list, magnitude: float) -> float:
    points = sorted((row[0], abs(row[1])) for row in rows)
    below = [v for m, v in points if m <= magnitude]
    above = [v for m, v in points if m >= magnitude]
    return max(([below[-1]] if below else []) + ([above[0]] if above else []))


def _by_hand(parts: dict, magnitude: float, skip=()) -> float:
    choices = [_at(parts[n]["by_magnitude"], magnitude) for n in CHOICES if n not in skip]
    left = [_at(parts[n]["by_magnitude"], magnitude) for n in LEFT_OUT if n not in skip]
    return math.sqrt(sum(v * v for v in choices)) + sum(left)


def _default_scene(band: str, sca: int, **changes):
    """The Roman default at ``POSITION`` with its sky (a modified one keeps the sky)."""
    readout = roman_default.readout(band, sca)
    return replace(roman_default.scene(POSITION, readout.background_e), **changes)


def test_an_accuracy_answer_carries_the_default_parts_and_its_level_error():
    answer = solver.solve("H158", 18, magnitude=19.0, tolerance=1e-4, accuracy=0.01, scene=_default_scene("H158", 18))
    model = answer.model
    assert model["combine"] == "roman" and model["accuracy"] == 0.01
    assert [p["name"] for p in model["left_out"]] == [*CHOICES, *LEFT_OUT]
    relative = _by_hand(_file_parts("H158", 18, "bias", "size"), 19.0)
    assert answer.uncertainty_model == pytest.approx(relative * answer.precision, rel=1e-9)
    # The older official-PSF figure is not quoted: the optics' vintage is one of the parts.
    assert answer.uncertainty_optical_model == 0.0
    # The level's own measured error is its own part, as a table answer's level error is.
    assert answer.uncertainty_fidelity == pytest.approx(model["level"]["error"] * answer.precision, rel=1e-12)
    parts = (answer.uncertainty_statistical, answer.uncertainty_fidelity, answer.uncertainty_model)
    assert answer.uncertainty == pytest.approx(math.hypot(*parts), rel=1e-12)


def test_a_left_out_set_is_a_part_of_its_own_added_linearly():
    # K213 size at A = 2 %: the search leaves a set out (tests/library/test_accuracy.py).
    readout = roman_default.readout("K213", 7)
    scene = roman_default.scene((900.0, 3100.0), readout.background_e)
    request = SolveRequest(
        "K213", 7, magnitude=19.0, precision=0.01, accuracy=0.02, ramp=readout.ramp, exptime=readout.exptime_s, scene=scene
    )
    selection = accuracy.select(request, 19.0, search="always")
    own = next(p for p in selection.model["left_out"] if p["name"] == accuracy.LEFT_OUT_PART)
    assert own["members"] and own["impact"] == selection.model["left_out_impact"] != 0.0
    out = model_part.model_at(selection.model, None, 19.0)  # size: no component restating, no slopes read
    expected = _by_hand(_file_parts("K213", 7, "bias", "size"), 19.0) + abs(own["impact"])
    assert out["effects_relative"] == pytest.approx(expected, rel=1e-12)
    assert out["optical_model_included"]


def test_a_part_the_request_sets_is_dropped_with_its_reason():
    scene = _default_scene("H158", 18, jitter_arcsec=0.014)
    answer = solver.solve("H158", 18, magnitude=19.0, tolerance=1e-4, accuracy=0.01, scene=scene)
    assert "jitter" not in [p["name"] for p in answer.model["left_out"]]
    dropped = next(p for p in answer.model["included"] if p["name"] == "jitter" and "why" in p)
    assert dropped["why"].startswith("set by the request") and "jitter" in dropped["why"]
    relative = _by_hand(_file_parts("H158", 18, "bias", "size"), 19.0, skip=("jitter",))
    assert answer.uncertainty_model == pytest.approx(relative * answer.precision, rel=1e-9)


@pytest.mark.parametrize("rule", ["header", "galsim"])
def test_another_pupil_rule_moves_the_optics_part_by_its_own_scale(rule):
    answer = solver.solve(
        "H158", 18, magnitude=19.0, tolerance=1e-4, accuracy=0.01, scene=_default_scene("H158", 18), pupil_scale=rule
    )
    part = next(p for p in answer.model["left_out"] if p["name"] == "optics")
    assert rule in part["why"]
    # By hand from the file: the fitted (v, ln s) less the rule's own ln s, through the sensitivities.
    data = json.loads((resources.files("nlpsf") / "data" / "roman_model_uncertainty.json").read_text())
    fit, scale = data["optics_fit"]["H158"], data["pupil_log_scale"]["H158 18"][rule]
    entry = data["per_band"]["H158"]["bias"]["size"]["per_sca"]["18"]
    rows = []
    for m, sv, ss in entry["optics_sensitivity"]:
        offset = sv * fit["theta"][0] + ss * (fit["theta"][1] - scale)
        c = fit["covariance"]
        spread = sv * sv * c[0][0] + 2 * sv * ss * c[0][1] + ss * ss * c[1][1]
        rows.append([m, math.sqrt(offset**2 + spread)])
    parts = {**_file_parts("H158", 18, "bias", "size"), "optics": {"by_magnitude": rows}}
    assert answer.uncertainty_model == pytest.approx(_by_hand(parts, 19.0) * answer.precision, rel=1e-5)


def test_a_default_at_another_exposure_reads_the_parts_at_equal_charge():
    exposure = 300.0
    answer = solver.solve("H158", 18, magnitude=20.5, tolerance=1e-4, exptime=exposure, scene=_default_scene("H158", 18))
    assert answer.fidelity != "table" and "exposure 300 s" in answer.model["basis"]
    # The star of equal charge in the measured exposure (the MA table's last read) is brighter.
    shifted = 20.5 - 2.5 * math.log10(exposure / roman_default.exptime_s())
    parts = _file_parts("H158", 18, "bias", "size")
    bfe = next(p for p in answer.model["left_out"] if p["name"] == "brighter_fatter")
    assert bfe["impact"] == pytest.approx(_at(parts["brighter_fatter"]["by_magnitude"], shifted), rel=1e-12)
    assert bfe["impact"] > _at(parts["brighter_fatter"]["by_magnitude"], 20.5)  # brighter-fatter grows with charge
    assert answer.uncertainty_model == pytest.approx(_by_hand(parts, shifted) * answer.precision, rel=1e-9)


def test_a_change_to_the_default_scene_is_kept_when_the_request_fills_its_sky():
    # A caller's change to the default's scene (no sky given) is the star asked about: the request
    # adds the default's sky over the exposure and keeps the change (it once became the default's).
    scene = replace(roman_default.base_scene(), position=POSITION, jitter_arcsec=0.014)
    request = SolveRequest("H158", 18, magnitude=19.0, precision=0.01, scene=scene)
    assert request.scene.jitter_arcsec == 0.014
    assert request.scene.background_e == roman_default.readout("H158", 18).background_e
    plain = replace(roman_default.base_scene(), position=POSITION)
    unchanged = SolveRequest("H158", 18, magnitude=19.0, precision=0.01, scene=plain)
    assert unchanged.scene == _default_scene("H158", 18)


@pytest.mark.parametrize("accuracy_", [None, 0.01])
def test_e_component_parts_are_restated_with_the_answers_own_slopes(accuracy_):
    # The e1 parts are stated against |c_e| (the file's convention) and restated against c_e1 with
    # the answer's own slopes (the grid's, or the accuracy answer's simulation): at W146 SCA 6
    # (3000, 1200), m = 20.5, the default's |c_e| / |c_e1| is ~10.6, the paper table's ~3.0.
    readout = roman_default.readout("W146", 6)
    scene = roman_default.scene((3000.0, 1200.0), readout.background_e)
    given = {"magnitude": 20.5, "tolerance": 1e-4, "accuracy": accuracy_, "scene": scene}
    e1 = solver.solve("W146", 6, metric="e1", **given)
    e2 = solver.solve("W146", 6, metric="e2", **given)
    scale = math.hypot(e1.slope, e2.slope) / abs(e1.slope)
    assert scale > 5.0
    assert e1.model["component_scale"] == pytest.approx(scale, rel=1e-6)
    relative = _by_hand(_file_parts("W146", 6, "bias", "e1"), 20.5) * scale
    assert e1.uncertainty_model == pytest.approx(relative * e1.precision, rel=1e-6)
