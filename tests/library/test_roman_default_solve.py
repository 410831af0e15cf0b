"""The Roman default is what a request without a scene gets; ``scene="paper"`` is the paper's tables."""

import math
from dataclasses import replace
from importlib import resources

import pytest

from nlpsf.request import presets as roman_default
from nlpsf.request.resolve import SolveRequest
from nlpsf.sim import experiment, ramps
from nlpsf.solve import solver


def test_a_request_without_a_scene_is_the_roman_default():
    request = SolveRequest("H158", sca=7, magnitude=19.0, tolerance=1e-4)
    assert request.preset == "roman" and request.linearise_at == "corrected" and request.pupil_scale == "official"
    # The HLWAS readout (romanisim's table 4) fitted by likelihood, over its own exposure.
    assert request.ramp.table.name == "romanisim-4" and request.ramp.fit == "optimal"
    assert request.exptime == pytest.approx(ramps.load_ma_table("C2A_IMG_HLWAS").duration_s, rel=1e-12)
    scene = request.scene
    # Givans et al. 2022: sigma = sqrt((C11 + C22) / 2) with C11 = 0.1066, C22 = 0.1136 px^2.
    assert scene.charge_diffusion_px == pytest.approx(math.sqrt((0.1066 + 0.1136) / 2), abs=5e-4)
    assert scene.jitter_arcsec == 0.006 and scene.sed == "k0v" and scene.ipc is not None
    assert scene.position is None and scene.background_e > 0
    # A given exposure keeps the default's table (its last read must fall within it); a ramp given replaces it.
    assert SolveRequest("H158", magnitude=19.0, tolerance=1e-4, exptime=200.0).exptime == 200.0
    own = ramps.Ramp.uniform(4, 100.0)
    assert SolveRequest("H158", magnitude=19.0, tolerance=1e-4, ramp=own, exptime=100.0).ramp is own


def test_the_default_answer_names_every_value_and_its_source():
    # At a position: one simulation (no SCA range; fidelity linear, so the simulated conditions show
    # whether or not the shipped field grid is installed).
    scene = replace(roman_default.base_scene(), position=(1000.0, 3000.0))
    answer = solver.answer(SolveRequest("J129", sca=3, magnitude=19.5, precision=0.01, scene=scene, fidelity="linear"))
    conditions = answer.conditions
    assert conditions["scene_name"] == "roman" and conditions["linearise_at"] == "corrected"
    named = {v["name"]: v for v in conditions["roman_default"]}
    assert set(named) == {"optics", "pupil_scale", "sed", "jitter", "charge_diffusion", "ipc", "background", "readout",
                          "ramp_fit", "linearise_at", "residual_nl"}  # fmt: skip
    assert all(v["source"] for v in named.values())
    assert list(conditions["scene"]["position"]) == [1000.0, 3000.0]
    assert conditions["scene"]["jitter_arcsec"] == named["jitter"]["value"]
    assert conditions["ramp"]["ma_table"] == "romanisim-4" and conditions["ramp"]["fit"] == "optimal"
    # The SED is integrated over the band even at linear fidelity: more than one wavelength.
    assert answer.fidelity == "linear" and conditions["n_wavelengths"] > 1
    assert conditions["pupil_scale"] == "official"


def _paper_table_row(band: str, sca: int, magnitude: float):
    from astropy.table import Table

    path = resources.files("nlpsf") / "data" / "tables" / "slopes.ecsv"
    table = Table.read(str(path))
    rows = table[(table["band"] == band) & (table["sca"] == sca) & (abs(table["magnitude"] - magnitude) < 1e-9)]
    assert len(rows) == 1
    return rows[0], table.meta["settings"]


@pytest.mark.parametrize(("band", "metric", "column"), [("H158", "size", "bias_size"), ("Y106", "e1", "bias_e1")])
def test_scene_paper_is_the_paper_tables_answer(band, metric, column):
    # Independent truth: the shipped table read directly (astropy), T = |c| p beta0 at a grid node.
    row, settings = _paper_table_row(band, 18, 19.0)
    answer = solver.solve(band, metric=metric, magnitude=19.0, precision=0.01, scene="paper")
    assert answer.exptime == settings["exptime_s"] and answer.fidelity == "table"
    assert answer.tolerance == pytest.approx(abs(row[column]) * 0.01 * settings["beta0"], rel=1e-9)
    assert answer.conditions["scene_name"] == "paper" and answer.conditions["linearise_at"] == "beta0"


def _direct_tolerance(band: str, sca: int, position, magnitude: float, precision: float) -> float:
    """The default's slope at a position simulated here, without the solver: T = |c| p beta0."""
    request = SolveRequest(band, sca=sca, magnitude=magnitude, precision=precision)  # only to read the default's fill
    config = experiment.SimulationConfig.from_settings(
        {"band": band, "sca": sca, "realizations": 100, "seed": 1, "method": "linear"},
        exptime_s=request.exptime,
        scene=roman_default.scene(position, request.scene.background_e),
        ramp=request.ramp,
        pupil_scale="official",
    )
    result = experiment.slopes(config, [magnitude], beta0=5e-7, linearise_at="corrected")[0]
    slope, _ = result.slope("bias", ("dR_over_R",))
    return abs(slope) * precision * 5e-7


@pytest.mark.slow
def test_without_a_position_the_answer_is_the_range_over_the_sca():
    band, sca, magnitude, precision = "H158", 18, 19.0, 0.01
    answer = solver.solve(band, sca, magnitude=magnitude, precision=precision)
    span = answer.conditions["sca_range"]
    least, most = span["least_demanding"]["tolerance"], span["most_demanding"]["tolerance"]
    assert "sca_range" in answer.flags[0].code and answer.tolerance == most >= least
    assert len(span["nodes"]) == 9
    for position in ((2044.5, 2044.5), (1.0, 1.0)):
        direct = _direct_tolerance(band, sca, position, magnitude, precision)
        assert least * (1 - 1e-9) <= direct <= most * (1 + 1e-9)
