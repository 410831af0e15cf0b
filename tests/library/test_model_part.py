"""The model part of answers without ``accuracy``: the shipped measurement, and what it covers.

A table answer is exact for the paper's idealised scene. Its ``uncertainty_model`` says what a Roman
scene changes (scene effects at their nominal values, the spread over the SCA, the pupil-scale
rule), from ``nlpsf/data/scene_model_uncertainty.json`` (``scripts/model_uncertainty.py``). Checked
here: the file is what the script measures, the solver reads it as documented, and the quoted
uncertainty covers a full Roman-scene simulation at random points.
"""

from __future__ import annotations

import functools
import importlib.util
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from nlpsf import roman
from nlpsf.sim import scene as scenes
from nlpsf.solve import impact, over_field, solver

# The paper's scene and tables (the default is the Roman star's): preset "paper" also underlies a scene given.
paper_solve = functools.partial(solver.solve, preset="paper")

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "model_uncertainty.py"


@pytest.fixture(scope="module")
def script():
    spec = importlib.util.spec_from_file_location("model_uncertainty_script", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def shipped():
    return scenes.shipped_model_uncertainty()


@pytest.mark.slow
def test_the_shipped_numbers_are_what_the_script_measures(script, shipped):
    conditions = shipped["conditions"]
    assert conditions["realizations"] == script.REALIZATIONS and conditions["seed"] == script.SEED
    assert conditions["scas"] == list(script.SCAS)
    # The summary is the worst over the stored points ...
    assert script.summarise(shipped["points"]) == shipped["per_band"]
    # ... and one point, measured again, gives the stored values.
    point = next(p for p in shipped["points"] if p["band"] == "J129" and p["sca"] == 1 and p["mode"] == "bias")
    assert point["magnitude"] == script.magnitudes("J129", 1)[0]
    again = impact.model_point("J129", 1, point["magnitude"], "bias", realizations=script.REALIZATIONS, seed=script.SEED)
    for name, values in point["effects"].items():
        if values is None:
            assert again["effects"][name] is None
            continue
        for metric, value in values.items():
            assert again["effects"][name][metric] == pytest.approx(value, rel=1e-6, abs=1e-9), (name, metric)
    for metric, value in point["pupil_scale"].items():
        assert again["pupil_scale"][metric] == pytest.approx(value, rel=1e-6, abs=1e-9), metric


def test_every_band_mode_and_metric_is_shipped_with_brighter_fatter_unmeasured(shipped):
    for band in roman.BANDS:
        for mode in solver.MODES:
            for metric in impact.MODEL_METRICS:
                entry = shipped["per_band"][band][mode][metric]
                assert entry["not_measured"] == ["brighter_fatter"]
                assert set(entry["effects"]) == set(scenes.EFFECTS) - {"brighter_fatter"}
                assert entry["effects_sum"] == pytest.approx(math.sqrt(sum(v**2 for v in entry["effects"].values())))
                assert entry["effects_bound"] == pytest.approx(sum(entry["effects"].values()))
                for own in entry["per_sca"].values():
                    assert all(own["effects"][k] <= entry["effects"][k] for k in own["effects"])


def test_a_table_answer_carries_the_shipped_model_part(shipped):
    answer = paper_solve("H158", 18, "size", magnitude=20.0, precision=0.01)
    entry = shipped["per_band"]["H158"]["bias"]["size"]["per_sca"]["18"]
    model = answer.model
    # The effects left out add up (a Roman star has them all at once): their plain sum.
    assert model["effects_relative"] == pytest.approx(entry["effects_bound"], rel=1e-12)
    assert model["pupil_scale_relative"] == pytest.approx(entry["pupil_scale"], rel=1e-12)
    assert answer.uncertainty_model == pytest.approx(answer.tolerance * math.hypot(entry["effects_bound"], entry["pupil_scale"]))
    assert "shipped measurement" in model["basis"] and "SCA 18" in model["basis"]
    named = {p["name"]: p for p in model["left_out"]}
    assert set(named) == {*scenes.EFFECTS, "pupil_scale"}
    assert named["brighter_fatter"]["impact"] is None and "not measured" in named["brighter_fatter"]["why"]
    # The pupil rule and the official-PSF comparison both describe the optics: the larger counts.
    effects = answer.tolerance * entry["effects_bound"]
    optics = max(answer.uncertainty_optical_model, answer.tolerance * entry["pupil_scale"])
    expected = math.hypot(answer.uncertainty_statistical, answer.uncertainty_fidelity, effects, optics)
    assert answer.uncertainty == pytest.approx(expected, rel=1e-12)
    # An SCA the measurement does not cover reads the worst over those it does.
    other = paper_solve("H158", 5, "size", magnitude=20.0, precision=0.01).model
    worst = shipped["per_band"]["H158"]["bias"]["size"]
    assert other["effects_relative"] == pytest.approx(worst["effects_bound"]) and "SCA 5 is not measured" in other["basis"]


def test_e_components_are_scaled_from_the_modulus_as_the_optical_part_is():
    answer = paper_solve("H158", 18, "e1", magnitude=20.0, precision=0.01)
    ratio = answer.uncertainty_optical_model / (answer.tolerance * roman.optical_model_uncertainty("H158", "e1"))
    assert answer.model["component_scale"] == pytest.approx(ratio, rel=1e-12) and ratio > 1


def test_effects_the_scene_simulates_are_not_left_out():
    given = scenes.SceneModel(jitter_arcsec=0.014, position=(100.0, 200.0))
    answer = paper_solve("H158", 18, "size", magnitude=20.0, precision=0.01, scene=given)
    names = {p["name"] for p in answer.model["left_out"]}
    assert "jitter" not in names and "position" not in names and "ipc" in names
    assert {e["name"] for e in answer.model["included"]} == {"jitter", "position"}
    poly = paper_solve("H158", 18, "size", magnitude=20.0, precision=0.01, fidelity="polychromatic")
    assert "sed" not in {p["name"] for p in poly.model["left_out"]}


def test_a_magnitude_answer_divides_by_the_log_slope():
    answer = paper_solve("H158", 18, "size", precision=0.01, tolerance=1e-4)
    assert answer.binding_limit == "nonlinearity"
    # |d ln c / dm| = statistical part's ratio (relative slope error / magnitude error).
    log_derivative = (answer.slope_uncertainty / abs(answer.slope)) / answer.uncertainty_statistical
    expected = math.hypot(answer.model["effects_relative"], answer.model["pupil_scale_relative"]) / log_derivative
    assert answer.uncertainty_model == pytest.approx(expected, rel=1e-9)


#: The full Roman scene of the coverage check: every effect with a nominal Roman value that acts on
#: the optics and the pixels (flat-f_nu SED, jitter, charge diffusion, IPC after the NL).
ROMAN = replace(
    scenes.SceneModel().with_nominal("sed").with_nominal("jitter").with_nominal("charge_diffusion").with_nominal("ipc"),
    n_wavelengths=16,
)


@pytest.mark.slow
def test_a_table_answers_uncertainty_covers_the_full_roman_scene():
    # The tolerance T = |c| p beta0 is linear in the slope, so a relative change of c maps one to one
    # onto T: the check is free of the linearisation a precision or magnitude answer adds. The pupil
    # rule (and the official-PSF part) are shared by the table and the simulated scene, so coverage is
    # asked of the statistical, fidelity and left-out-effects parts only.
    rng = np.random.default_rng(2026)
    checked = 0
    for _ in range(4):
        band = str(rng.choice(roman.BANDS))
        sca = int(rng.choice([18, int(rng.integers(1, 19))]))
        metric, mode = str(rng.choice(solver.METRICS)), str(rng.choice(solver.MODES))
        saturation = solver.tables.load_tables().get(band, sca).saturation(168.1, 1.1e5)
        magnitude = float(saturation + 0.5 + rng.uniform(0, 3))
        table = paper_solve(band, sca, metric, mode, magnitude=magnitude, precision=0.01)
        parts = math.hypot(
            table.uncertainty_statistical, table.uncertainty_fidelity or 0.0, table.tolerance * table.model["effects_relative"]
        )
        assert table.uncertainty >= parts
        corner = over_field.field_points(sca)[int(rng.integers(1, 5))]
        for position in (None, corner):
            scene = replace(ROMAN, position=position)
            full = paper_solve(band, sca, metric, mode, magnitude=magnitude, precision=0.01, fidelity="linear", scene=scene)
            spread = math.hypot(parts, full.uncertainty_statistical)
            where = (band, sca, metric, mode, round(magnitude, 2), position)
            assert abs(full.tolerance - table.tolerance) <= spread, (where, table.tolerance, full.tolerance, spread)
            checked += 1
    assert checked == 8


def test_the_roman_default_model_part_is_kept_and_each_answer_gets_its_own_parts():
    """The Roman default's model part is built once per set of what decides it (kept between
    answers); an answer that changes its own parts' lists changes no other answer's."""
    from nlpsf.solve import model_part

    first = model_part.roman_default_model("H158", 7, "e1", "bias", None)
    again = model_part.roman_default_model("H158", 7, "e1", "bias", None)
    assert first == again and first is not again and first["left_out"] is not again["left_out"]
    first["left_out"].clear()
    first["included"].append({"name": "changed"})
    first["ranges"].clear()
    assert model_part.roman_default_model("H158", 7, "e1", "bias", None) == again
    assert again["left_out"]
