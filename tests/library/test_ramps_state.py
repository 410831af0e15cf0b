"""The slope a calibration error acts through: linearised at the uncorrected beta0 (the paper) or at the
corrected detector (a residual NL), with a ramp's saturation flags set by the raw beta0 either way."""

import pytest

from nlpsf import experiment, ramps
from nlpsf.experiment import SimulationConfig, simulate, slopes

BETA0 = 5e-7


@pytest.fixture(scope="module")
def h158():
    config = SimulationConfig(band="H158", realizations=12)
    return config, experiment.prepare(config)


def test_the_corrected_state_is_the_first_order_slope_at_vanishing_nl(h158):
    # Independent of the finite difference: metric(b) / b at b = 1e-4 beta0 is the slope at beta -> 0 to
    # 1e-4 of its curvature; the corrected state (residual 1e-2 beta0) must sit within 1e-2 of the 3.4 %
    # that separates the two states, and the paper state must not.
    config, scene = h158
    tiny = 1e-4 * BETA0
    first_order = simulate(config, [18.3], [tiny], scene=scene)[0].dR_over_R.mean / tiny
    corrected = slopes(config, [18.3], scene=scene, linearise_at="corrected")[0]
    paper = slopes(config, [18.3], scene=scene)[0]
    assert corrected.bias["dR_over_R"].mean == pytest.approx(first_order, rel=1e-3)
    assert paper.bias["dR_over_R"].mean / first_order - 1 > 0.02
    assert corrected.conditions["linearised_at"]["state"] == "corrected"


def test_a_ramp_keeps_the_raw_saturation_flags_in_the_corrected_state(h158):
    _config, scene = h158
    table = ramps.load_ma_table("romanisim-110")
    ramp = ramps.Ramp(table, "ols", 10.0, saturation="signal", single_resultant="unusable")
    cfg = SimulationConfig(band="H158", realizations=12, exptime_s=table.duration_s, ramp=ramp)
    prepared = experiment.Scene(cfg, scene.psf, scene.offsets, scene.stamps, scene.reference, 0.0)
    magnitude = 16.0  # between the limits: the core drops resultants
    paper = slopes(cfg, [magnitude], scene=prepared)[0]
    corrected = slopes(cfg, [magnitude], scene=prepared, linearise_at="corrected")[0]
    assert paper.extras["ramp"]["fitted_on_fewer"] > 0
    assert corrected.extras["ramp"] == paper.extras["ramp"]
    # Flagging at the residual instead (what the raw detector does not do) keeps more resultants.
    residual = simulate(cfg, [magnitude], [1e-2 * BETA0], scene=prepared)[0]
    assert residual.extras["ramp"]["pixels_by_resultants"] != paper.extras["ramp"]["pixels_by_resultants"]
