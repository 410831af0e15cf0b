"""The impact report: its contract, and its linear-response numbers against Monte Carlo."""

import functools
import json
import math
from dataclasses import replace

import pytest

from nlpsf.checks import InputError
from nlpsf.flags import FlagCode
from nlpsf.sim import experiment
from nlpsf.sim import scene as scenes
from nlpsf.solve import impact, over_field, solver

# The paper's scene and tables (the default is the Roman star's): preset "paper" also underlies a scene given.
paper_solve = functools.partial(solver.solve, preset="paper")


@pytest.fixture(scope="module")
def paper_report():
    return impact.impact("H158", 18, 18.3, realizations=20)


def test_report_names_every_effect_in_order_with_its_impact(paper_report):
    json.dumps(paper_report)
    assert [e["name"] for e in paper_report["effects"]] == list(scenes.EFFECTS)
    for effect in paper_report["effects"]:
        assert set(effect["impact"]) == {"size", "e1", "e2", "e"}
        assert effect["on"] is False
        assert {"name", "on", "impact", "cost_s"} <= set(effect)
    bfe = next(e for e in paper_report["effects"] if e["name"] == "brighter_fatter")
    assert bfe["impact"]["size"] is None and "no default" in bfe["note"]
    assert paper_report["conditions"]["band"] == "H158" and paper_report["conditions"]["magnitude"] == 18.3


def test_an_effect_that_is_on_is_measured_at_the_scene_value():
    model = scenes.SceneModel(jitter_arcsec=0.03, bfe_coefficient=1e-7)
    report = impact.impact("H158", 18, 19.0, scene=model, realizations=10)
    jitter = next(e for e in report["effects"] if e["name"] == "jitter")
    assert jitter["on"] and jitter["value"] == 0.03
    bfe = next(e for e in report["effects"] if e["name"] == "brighter_fatter")
    assert bfe["on"] and bfe["impact"]["size"] is not None
    assert report["conditions"]["beta_q_scaling_broken_by"] == ["brighter_fatter"]


@pytest.mark.slow
@pytest.mark.parametrize("effect", ["jitter", "ipc", "nl_polynomial"])
def test_linear_impact_agrees_with_monte_carlo_with_and_without_the_effect(effect):
    # Monte Carlo (the paper's finite differences) with and without the effect, on the same
    # centroids; the linear-response impact must fall within the Monte Carlo's error.
    realizations, magnitude = 100, 18.3
    report = impact.impact("H158", 18, magnitude, realizations=realizations)
    linear = next(e for e in report["effects"] if e["name"] == effect)["impact"]
    with_scene = scenes.SceneModel().with_nominal(effect)
    runs = {}
    for label, model in (("with", with_scene), ("without", scenes.SceneModel())):
        config = experiment.SimulationConfig(realizations=realizations, scene=model)
        runs[label] = experiment.slopes(config, [magnitude])[0]
    for metric, name in (("size", "dR_over_R"), ("e1", "de1"), ("e2", "de2")):
        a, b = runs["with"].bias[name], runs["without"].bias[name]
        mc = a.mean / b.mean - 1
        error = abs(a.mean / b.mean) * math.hypot(a.stderr / a.mean, b.stderr / b.mean)
        assert abs(linear[metric] - mc) <= 3 * error + 2e-3, (metric, linear[metric], mc, error)


def test_accuracy_splits_effects_at_the_requested_level(paper_report):
    for accuracy in (1e-3, 1e-2, 1e-1):
        include, leave = impact.left_out(paper_report, accuracy)
        assert all(abs(e["impact"]["size"]) > accuracy for e in include)
        assert all(e["impact"]["size"] is None or abs(e["impact"]["size"]) <= accuracy for e in leave)
        assert len(include) + len(leave) == len(scenes.EFFECTS)


def test_bad_requests_are_refused_by_name():
    with pytest.raises(InputError, match="metric"):
        impact.impact(metric="shear")
    with pytest.raises(InputError, match="band"):
        impact.impact(band="X1")
    with pytest.raises(InputError, match="magnitude"):
        impact.impact(magnitude=float("nan"))


@pytest.mark.slow
def test_accuracy_switches_effects_on_and_its_uncertainty_covers_the_full_scene():
    import numpy as np

    full = scenes.SceneModel()
    for name in ("sed", "jitter", "charge_diffusion", "ipc", "nl_polynomial", "background"):
        full = full.with_nominal(name)
    full = replace(full, n_wavelengths=24)  # the band integrated finer than any answer below
    rng = np.random.default_rng(8)
    points = [("H158", 18, float(18.3 + rng.uniform(0, 2))), ("J129", int(rng.integers(1, 19)), float(19 + rng.uniform(0, 2)))]
    for band, sca, magnitude in points:
        reference = paper_solve(band, sca, magnitude=magnitude, tolerance=1e-4, fidelity="monte_carlo", scene=full)
        included = []
        for accuracy in (0.1, 0.01, 0.002):
            # Held to this test's full scene (without a scene, accuracy is held to the Roman default's).
            answer = paper_solve(band, sca, magnitude=magnitude, tolerance=1e-4, accuracy=accuracy, scene=full)
            included.append({e["name"] for e in answer.model["included"]})
            left = [p for p in answer.model["left_out"] if p["impact"] is not None]
            assert all(abs(p["impact"]) <= accuracy for p in left if p["name"] not in ("position", "pupil_scale"))
            # Coverage by the parts that are about this scene (the pupil rule is a model choice the
            # full scene shares, so it is left out of this check).
            relative = math.sqrt(sum(p["impact"] ** 2 for p in left if p["name"] != "pupil_scale"))
            spread = math.hypot(answer.uncertainty_statistical, answer.uncertainty_fidelity or 0.0, answer.precision * relative)
            assert abs(answer.precision - reference.precision) <= 3 * spread + 1e-3 * reference.precision, (
                band,
                accuracy,
                answer.precision,
                reference.precision,
                spread,
            )
            assert answer.uncertainty >= spread
        # A tighter accuracy never leaves out more (nlpsf.solve.accuracy: where the full scene is affordable,
        # every accuracy simulates all of it).
        assert included[0] <= included[1] <= included[2]


def test_over_field_answers_for_the_worst_field_point():
    from nlpsf.solve import solver

    worst = solver.solve_over_field("H158", [18], metric="e1", magnitude=18.3, tolerance=1e-4, preset="paper")
    points = worst.conditions["over_field"]
    assert len(points) == 5 and {tuple(p["position"]) for p in points} == set(over_field.field_points(18))
    assert worst.precision == min(p["precision"] for p in points)
    assert worst.flags[0].code == FlagCode.WORST_OVER_FIELD and worst.flags[0].values["points"] == 5
    # Read from the tables (centre and field-point): each point is the plain solve at its position,
    # which finds that corner's shipped table by itself.
    assert worst.conditions["fidelity"] == "table"
    corner = points[1]
    direct = paper_solve("H158", 18, "e1", magnitude=18.3, tolerance=1e-4, scene=scenes.SceneModel(position=corner["position"]))
    assert direct.precision == corner["precision"] and direct.conditions["fidelity"] == "table"
    # Elsewhere on the SCA no table holds the star: it is simulated.
    between = paper_solve("H158", 18, "e1", magnitude=18.3, tolerance=1e-4, scene=scenes.SceneModel(position=(1000.0, 1000.0)))
    assert between.conditions["fidelity"] == "linear"
    # A point's position is given, so its spread over the SCA is not in the model uncertainty.
    assert "position" not in {part["name"] for part in direct.model["left_out"]}
    # Simulating every point instead (linear response, same centroids) gives the same answers
    # within the tables' own statistical + interpolation error.
    simulated = solver.solve_over_field(
        "H158", [18], metric="e1", magnitude=18.3, tolerance=1e-4, fidelity="linear", preset="paper"
    )
    for tabulated, fresh in zip(points, simulated.conditions["over_field"], strict=True):
        assert tabulated["position"] == fresh["position"]
        here = scenes.SceneModel(position=tabulated["position"])
        at = paper_solve("H158", 18, "e1", magnitude=18.3, tolerance=1e-4, scene=here)
        assert abs(tabulated["precision"] - fresh["precision"]) <= 3 * at.uncertainty_statistical
    with pytest.raises(InputError, match="position"):
        solver.solve_over_field("H158", [18], scene=scenes.SceneModel(position=(5.0, 5.0)), magnitude=18.3, tolerance=1e-4)


def test_background_moves_the_saturation_limit_and_stops_the_table_rescaling():
    import math

    plain = paper_solve("H158", magnitude=19.0, tolerance=1e-4)
    with_background = paper_solve("H158", magnitude=19.0, tolerance=1e-4, scene=scenes.SceneModel(background_e=5e4))
    # The star saturates where its peak reaches the well minus the background: a flux ratio.
    shift = with_background.saturation_magnitude - plain.saturation_magnitude
    assert shift == pytest.approx(2.5 * math.log10(1.1e5 / 6e4), rel=1e-9)
    assert with_background.fidelity == "linear"
    assert any(f.code == FlagCode.BETA_Q_RULE_BROKEN and f.values["names"] == ["background"] for f in with_background.flags)
    with pytest.raises(InputError, match="background"):
        paper_solve("H158", magnitude=19.0, tolerance=1e-4, scene=scenes.SceneModel(background_e=2e5))


def test_a_capped_sed_says_it_has_fewer_wavelengths_than_its_accuracy_needs():
    from nlpsf.solve import impact as impact_module

    wanted = scenes.SceneModel().with_nominal("sed").wavelengths("H158", 1, 18)
    assert wanted > 2
    report = impact_module.impact("H158", realizations=4, max_wavelengths=2)
    sed = next(e for e in report["effects"] if e["name"] == "sed")
    assert f"with 2 wavelengths, fewer than the {wanted} its accuracy needs" in sed["note"]
    # Only the SED is capped.
    assert all("fewer than" not in e["note"] for e in report["effects"] if e["name"] != "sed")
    uncapped = impact_module.impact("H158", realizations=4)["effects"]
    assert "fewer than" not in next(e for e in uncapped if e["name"] == "sed")["note"]
