"""The sky's own NL is removed as a local sky estimate removes it (``experiment.sky``, docs/ramps.md).

Independent checks: a read-by-read brute force of a star-free pixel, the linear-regime scaling law
(faint stars' slopes proportional to the flux once the sky's NL is gone: exact with an OLS ramp fit; the
likelihood fit's departure from it against a read-by-read brute force), and the paper's scene (no sky)
untouched.
"""

import itertools
from dataclasses import replace

import numpy as np
import pytest

from nlpsf import solve
from nlpsf.request import presets as roman_default
from nlpsf.sim import experiment, ramps
from nlpsf.sim.experiment import sky
from nlpsf.sim.scene import ROMAN_IPC_KERNEL, SceneModel

from .test_ramps_readout import brute_force

BETA = 5e-7


@pytest.fixture(scope="module")
def sky_scene():
    model = SceneModel(ipc=ROMAN_IPC_KERNEL, ipc_label="roman", background_e=300.0, nl_coefficients=(2e-12,))
    config = experiment.SimulationConfig(realizations=4, scene=model, exptime_s=168.1)
    return config, experiment.prepare(config)


def test_a_star_free_pixels_final_frame_level_is_its_polynomial_nl(sky_scene):
    # Final frame: the star-free pixel reads S(B) = B - b2 B^2 - b3 B^3; IPC spreads a uniform level into
    # itself times the kernel's sum.
    _, scene = sky_scene
    scale = 1e5
    level, derivative = sky.star_free_level(scene, scale, BETA, up_the_ramp=False)
    B, b3, ksum = 300.0, 2e-12, float(np.sum(ROMAN_IPC_KERNEL))
    assert level * scale == pytest.approx(-(BETA * B**2 + b3 * B**3) * ksum, rel=1e-12)
    assert derivative * scale == pytest.approx(-(B**2) * ksum, rel=1e-12)


@pytest.mark.parametrize("fit", ["ols", "optimal"])
def test_a_star_free_pixels_ramp_level_is_the_read_by_read_fit(sky_scene, fit):
    config, scene = sky_scene
    table = ramps.load_ma_table("C2A_IMG_HLWAS")
    ramp = ramps.Ramp(table, fit, 9.3, saturation="signal", single_resultant="unusable")
    ramped = experiment.SimulationConfig(
        realizations=4, scene=replace(config.scene, ipc=None), exptime_s=table.duration_s, ramp=ramp
    )
    scene = experiment.Scene(ramped, scene.psf, scene.offsets, scene.stamps, scene.reference, 0.0)
    level, _ = sky.star_free_level(scene, 1.0, BETA, up_the_ramp=True)
    expected, _ = brute_force(0.0, table, table.duration_s, (BETA, 2e-12), 300.0, fit, 9.3, "signal", "unusable")
    # the brute force returns the fitted charge of the pixel; its NL is what is left beyond B
    assert level == pytest.approx(expected - 300.0, rel=1e-10)


def test_far_from_the_star_the_nl_is_the_skys_gain_change_only(sky_scene):
    # Where the star is faint against the sky, S(s psi + B) - S(B) = S'(B) s psi to first order: what is
    # left is the sky's local gain change times the star's own image. A pedestal left in would be
    # -b2 B^2 / (s psi) times larger than that, about 10^3 at the edge here.
    _, scene = sky_scene
    scale = 2e5
    stamps, _, perturbation, _ = experiment.nl_images(scene, scale, BETA)
    B, b3 = 300.0, 2e-12
    gain_change = -(2 * BETA * B + 3 * b3 * B**2)
    edge = (slice(None), 0, slice(None))
    assert np.allclose(perturbation[edge] / stamps[edge], gain_change, rtol=2e-2)


@pytest.mark.parametrize("band", ["K213", "H158"])
def test_faint_roman_default_slopes_scale_as_the_flux(band):
    # In the linear regime the calibration residual -Delta_beta Q*^2 of a pixel at Q* = (s psi + B) tau is
    # s^2 psi^2 + 2 s psi B + B^2 (times the fit's ramp factor): the sky removal takes B^2, the moments do
    # not see 2 s psi B (the star's own image, scaled), and their gradient goes as 1 / s -- so the slope is
    # proportional to the flux and 2 mag fainter is 10^(-0.8) of it, exactly where the fit's weights do not
    # depend on the rate: an OLS fit on the default's HLWAS readout (what is left is the O(beta s psi)
    # curvature of the corrected levels, ~2e-5 at m = 22, itself falling as the flux). A sky NL left in
    # the image would add a term growing as 1 / flux and turn the slope's sign (K213 near m = 21 before
    # the change). The likelihood fit's weights do depend on the rate: its drift is checked below.
    scene = replace(roman_default.base_scene(), position=(2000.0, 2000.0))
    ramp, exptime = ramps.build(ma_table=roman_default.MA_TABLE, fit="ols", sca=18)
    slopes = [
        solve(band, 18, "size", magnitude=m, precision=0.01, fidelity="linear", scene=scene, ramp=ramp, exptime=exptime)
        for m in (22, 24, 26)
    ]
    assert all(s.conditions["ramp"]["fit"] == "ols" for s in slopes)
    values = [s.slope for s in slopes]
    assert values[0] > 0 and values[1] > 0 and values[2] > 0
    for bright, faint in itertools.pairwise(values):
        assert faint / bright == pytest.approx(10**-0.8, rel=1e-4)


def test_the_likelihood_fits_departure_from_the_flux_law_is_its_weights():
    # The default's likelihood fit weights each resultant by the pixel's own read and Poisson noise, so its
    # ramp factor sum_j w_j(rate) tau_j^2 changes between the read-noise- and the Poisson-dominated regime
    # and the flux law above is no longer exact. That departure is physics, not an error: a read-by-read
    # brute force (every read's charge, IPC, resultants, stcal's linearity correction, the GLS slope with
    # its covariance built read by read, the sky removed as a star-free pixel's own fit, the moments'
    # finite difference; ``test_residual_correction.brute_force_image``) has the same ratios of slopes, to
    # 1e-6 (measured 5e-8), while they miss 10^(-0.8) by 1e-2 (H158 m = 22 -> 24) and 2e-3 (24 -> 26).
    pytest.importorskip("stcal")
    from nlpsf.sim import moments
    from nlpsf.slopes import tablebuild

    from .test_residual_correction import _metrics, brute_force_image

    settings = tablebuild.TableSettings.roman(realizations=3, stamp=48)
    config = settings.config("H158", 18, position=(2000.0, 2000.0))
    assert config.ramp.fit == "optimal"
    scene = experiment.prepare(config)
    magnitudes = (22.0, 24.0, 26.0)
    brute, ours = [], []
    for m in magnitudes:
        scale = float(config.electrons(m)) * config.oversampling**2
        reference = moments.fit(scale * scene.stamps, config.moment_settings)
        h = 2e-9 * 10 ** (0.4 * (m - 19))  # the same relative step at every flux
        plus, _ = brute_force_image(scene, scale, h)
        minus, _ = brute_force_image(scene, scale, -h)
        size = (_metrics(plus, reference, config.moment_settings) - _metrics(minus, reference, config.moment_settings))[0]
        brute.append(float(np.mean(size / (2 * h))))
        ours.append(experiment.slopes(config, [m], scene=scene, linearise_at="corrected")[0].bias["dR_over_R"].mean)
    for k in range(2):
        law = 10**-0.8
        brute_departure = brute[k + 1] / brute[k] / law - 1
        our_departure = ours[k + 1] / ours[k] / law - 1
        assert our_departure == pytest.approx(brute_departure, abs=1e-6), k
        assert abs(brute_departure) > 1e-3, k  # the check has teeth: the departure is 1e3 times its tolerance
