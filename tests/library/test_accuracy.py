"""``accuracy`` keeps its promise (nlpsf.solve.accuracy): impacts measured inside the full scene, a
left-out set measured as a set, and the answer within A of an independent full-scene simulation."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from nlpsf import defaults
from nlpsf.flags import FlagCode, codes
from nlpsf.request import presets as roman_default
from nlpsf.request.resolve import SolveRequest
from nlpsf.sim import experiment
from nlpsf.sim import scene as scenes
from nlpsf.slopes import tables
from nlpsf.solve import accuracy, solver


def _roman_request(band, sca, metric, magnitude, position, accuracy_=0.01):
    """A request for the Roman default at ``position``, its readout and background."""
    readout = roman_default.readout(band, sca)
    scene = roman_default.scene(position, readout.background_e)
    return SolveRequest(
        band, sca, metric=metric, magnitude=magnitude, precision=0.01, accuracy=accuracy_,
        ramp=readout.ramp, exptime=readout.exptime_s, scene=scene,
    )  # fmt: skip


def _probe(request, seed=None, realizations=accuracy.PROBE_REALIZATIONS):
    table = tables.load_tables().get(request.band, request.sca)
    full = accuracy.full_scene(request, table)
    if not accuracy._measurement(full, request.band)[1]:
        # As select does: band-integrated only where the paper scene's measurement is read; the
        # Roman default's scene is measured as it is simulated (its own wavelengths).
        full = replace(full, scene=accuracy._with_band_integration(full.scene))
    probe = accuracy.Probe(request, full, table, request.magnitude, realizations=realizations)
    if seed is not None:
        probe.base = replace(probe.base, seed=seed)
    return probe


@pytest.mark.slow
def test_effects_that_share_a_sign_are_not_left_out_together():
    # K213 size (issue 17: four effects each under 1 %, same sign, 1.8 % together). In the Roman
    # default here the SED, IPC and jitter all lower the size slope (-2.26 %, -0.75 %, -0.07 % alone,
    # -3.1 % together); at A = 2.5 % each is below A alone. (A was 2 % while the sky's own NL stayed in
    # the image, when the SED alone was under 2 % here.)
    a = 0.025
    request = _roman_request("K213", 7, "size", 19.0, (900.0, 3100.0), a)
    probe = _probe(request)
    alone = {name: probe.impact([name])[0] for name in accuracy._removable(probe.full.scene)}
    under = [name for name, value in alone.items() if abs(value) <= a]
    shared = [name for name in ("sed", "ipc", "jitter") if name in under]
    assert len(shared) == 3 and all(alone[name] < 0 for name in shared), alone
    # The old rule (each effect alone against A) would leave all of them out; measured as a set they exceed A.
    assert abs(probe.impact(under)[0]) > a, (under, probe.impact(under))
    selection = accuracy.select(request, request.magnitude, search="always")
    left = next((p["members"] for p in selection.model["left_out"] if "members" in p), [])
    assert not set(shared) <= set(left), left
    assert selection.model["left_out_impact"] != 0.0 and set(left) < set(under)
    # The left-out set's impact, measured again on other centroids with more of them: within A.
    check = _probe(request, seed=977, realizations=40)
    value, error = check.impact(left)
    assert abs(value) + selection.model["level"]["error"] <= a + 2 * error, (left, value)
    # The centroid-sample noise of the measured impacts is far below A.
    assert all(e["uncertainty"] < a / 100 for e in selection.model["measured"])
    # Measured again on 40 other centroids, the set's impact agrees within 3 sigma of the two stated
    # uncertainties (each a bound on its standard error over centroid samples). (The 2.7e-4 this
    # re-measurement once moved by was the SED integrated over 8 wavelengths here against the
    # default's own in the selection: the levels, not the centroids.)
    stated = selection.model["left_out_impact_uncertainty"]
    assert abs(value - selection.model["left_out_impact"]) <= 3 * math.hypot(stated, error), (value, stated, error)
    assert FlagCode.ACCURACY_SCENE in codes(selection.notes)


@pytest.mark.slow
def test_interacting_effects_are_measured_inside_the_scene():
    # W146 e2 with only a position (issue 17: jitter and diffusion measured alone in the paper scene
    # were small and left out; with the SED on they move the slope far more).
    position = (3000.0, 1200.0)
    request = _roman_request("W146", 11, "e2", 20.5, position, 0.01)
    probe = _probe(request)
    in_scene = {name: probe.impact([name])[0] for name in ("jitter", "charge_diffusion")}
    # The same effects added alone to a scene that has only the position (the impact report's way).
    only_position = scenes.SceneModel(position=position)
    added = {}
    for name in ("jitter", "charge_diffusion"):
        with_it = replace(only_position, **{f: getattr(probe.full.scene, f) for f in scenes.REGISTRY[name].fields})
        (a, _), (b, _) = probe.slope(only_position), probe.slope(with_it)
        added[name] = a / b - 1.0  # slope without / with - 1: the error of leaving it out
    # SED x jitter: removing the jitter with the SED on and with it off differ.
    no_sed = probe.full.scene.without("sed")
    (a, _), (b, _) = probe.slope(no_sed.without("jitter")), probe.slope(no_sed)
    jitter_without_sed = a / b - 1.0
    assert abs(in_scene["jitter"] - jitter_without_sed) > 0.2 * abs(in_scene["jitter"]), (in_scene, jitter_without_sed)
    for name in in_scene:
        assert abs(in_scene[name] - added[name]) > 0.2 * abs(in_scene[name]), (name, in_scene, added)
    # Whatever is left out, its set's impact inside the full scene is within A.
    selection = accuracy.select(request, request.magnitude, search="always")
    left = next((p["members"] for p in selection.model["left_out"] if "members" in p), [])
    for name, value in in_scene.items():
        if abs(value) > 0.01:
            assert name not in left
    value, error = _probe(request, seed=977, realizations=40).impact(left) if left else (0.0, 0.0)
    assert abs(value) + selection.model["level"]["error"] <= 0.01 + 2 * error


def test_nothing_is_left_out_where_the_full_scene_is_affordable():
    request = _roman_request("H158", 18, "size", 19.0, None, 0.01)
    selection = accuracy.select(request, 19.0)
    assert selection.fidelity == "linear" and selection.model["left_out_impact"] == 0.0
    assert selection.model["probe"] is None  # no impact measured: simulating everything is cheapest
    # The request's scene is the Roman default's: its own fidelity measurement is read, of the levels
    # as the default runs them, so the scene is simulated as it is (no forced band integration).
    assert selection.model["full_scene"]["source"] == "roman default"
    assert FlagCode.FIDELITY_FROM_PAPER not in codes(selection.notes)
    assert selection.scene == request.scene


def test_without_a_scene_the_full_scene_is_the_roman_default():
    readout = roman_default.readout("J129", 4)
    request = SolveRequest(
        "J129", 4, metric="e", magnitude=20.0, precision=0.01, accuracy=0.01, ramp=readout.ramp, exptime=readout.exptime_s
    )
    selection = accuracy.select(request, 20.0)
    assert selection.model["full_scene"]["source"] == "roman default"
    expected = roman_default.scene(None, readout.background_e)
    assert replace(selection.scene, n_wavelengths=None) == expected
    # The SCA centre stands for the position: named, not measured; beside it the default's own
    # parts (tests/library/test_accuracy_parts.py), its pupil part header against the official rule used.
    assert selection.model["full_scene"]["pupil_scale"] == "official"
    unmeasured = {p["name"] for p in selection.model["left_out"] if "by_magnitude" not in p}
    assert unmeasured == {"position"}


def _full_scene_reference(request, realizations=30, seed=4242):
    """An independent, fresh full-scene simulation at the most exact level: Monte Carlo on the PSF
    integrated over 16 wavelengths, other centroids than the solver's, with the request's pupil rule
    (the Roman default's: official)."""
    table = tables.load_tables().get(request.band, request.sca)
    pupil = request.pupil_scale or str(table.settings["pupil_scale"])
    config = experiment.SimulationConfig.from_table(
        table.settings, band=request.band, sca=request.sca, exptime_s=request.exptime, throughput=table.throughput,
        method="monte_carlo", n_wavelengths=16, realizations=realizations, seed=seed, pupil_scale=pupil,
        scene=replace(request.scene, n_wavelengths=16), ramp=request.ramp, full_well_e=request.full_well,
    )  # fmt: skip
    state = getattr(request, "linearise_at", None) or "beta0"  # the state the solver linearises at
    result = experiment.slopes(config, [request.magnitude], beta0=request.beta0, linearise_at=state)[0]
    return result.slope(request.mode, defaults.METRIC_COLUMNS[request.metric])


@pytest.mark.parametrize(
    ("band", "sca", "metric", "magnitude", "position"),
    [
        ("J129", 9, "size", 19.5, (1500.0, 2600.0)),
        ("Z087", 12, "e1", 20.0, (700.0, 900.0)),
        # issue 17's misses: W146 e2 with a position (+13.6 %), K213 size (-1.96 %), H158 e2 (+1.46 %)
        ("W146", 6, "e2", 20.5, (3000.0, 1200.0)),
        ("K213", 17, "size", 19.0, (900.0, 3100.0)),
        ("H158", 18, "e2", 19.5, (2500.0, 800.0)),
    ],
)
def test_accuracy_answer_lands_within_a_of_the_full_scene(band, sca, metric, magnitude, position):
    request = _roman_request(band, sca, metric, magnitude, position, 0.01)
    answer = solver.answer(request)
    reference, reference_error = _full_scene_reference(request)
    statistical = abs(answer.slope_uncertainty / answer.slope) + abs(reference_error / reference)
    assert abs(answer.slope / reference - 1.0) <= 0.01 + 2 * statistical, (answer.slope, reference, statistical)


def test_a_roman_default_fidelity_entry_is_read_when_shipped(monkeypatch):
    from nlpsf.slopes import fidelity

    shipped = fidelity.measured()
    readout = roman_default.readout("H158", 18)
    ramp = {"ramp": readout.ramp, "exptime": readout.exptime_s}
    request = SolveRequest("H158", 18, magnitude=19.0, precision=0.01, accuracy=0.01, **ramp)
    # Without a Roman-default entry, the paper scene's measurement is used, and the answer says so.
    paper_only = {k: v for k, v in shipped.items() if k != "roman"}
    monkeypatch.setattr(fidelity, "measured", lambda: paper_only)
    before = accuracy.select(request, 19.0)
    assert FlagCode.FIDELITY_FROM_PAPER in codes(before.notes)
    # A Roman-default measurement where the linear level misses 1 % and Monte Carlo meets it.
    errors = {"linear": 0.02, "monte_carlo": 0.004, "polychromatic": 0.001}
    roman = {"date": "test", "errors": {"H158": {"bias": {"size": errors}}}}
    monkeypatch.setattr(fidelity, "measured", lambda: {**paper_only, "roman": roman})
    after = accuracy.select(request, 19.0, search="never")
    assert FlagCode.FIDELITY_FROM_PAPER not in codes(after.notes)
    assert after.fidelity == "monte_carlo" and after.model["level"]["error"] == 0.004
