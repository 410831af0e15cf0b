"""The sky's own NL is removed as a local sky estimate removes it (``experiment.sky``, docs/ramps.md).

Independent checks: a read-by-read brute force of a star-free pixel, the linear-regime scaling law
(faint stars' slopes proportional to the flux once the sky's NL is gone), and the paper's scene
(no sky) untouched.
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
    # In the linear regime the NL image is beta Q^2: the moments' slope is proportional to the flux, so
    # 2 mag fainter is 10^(-0.8) of the slope. A sky NL left in the image would add a term growing as
    # 1 / flux and turn the slope's sign (K213 near m = 21 before the change). The law is not exact up the
    # ramp: the likelihood fit's weights depend on each pixel's rate, so its ramp factors drift between the
    # read-noise- and the Poisson-dominated regime, by up to 1.0 % per 2 mag at m = 22-24 with no sky at all
    # (H158, the per-resultant correction; 0.9 % under the per-read residual): 1.5 % leaves that room, and a
    # pedestal left in moves the ratio by orders of magnitude.
    scene = replace(roman_default.base_scene(), position=(2000.0, 2000.0))
    slopes = [solve(band, 18, "size", magnitude=m, precision=0.01, fidelity="linear", scene=scene).slope for m in (22, 24, 26)]
    assert slopes[0] > 0 and slopes[1] > 0 and slopes[2] > 0
    for bright, faint in itertools.pairwise(slopes):
        assert faint / bright == pytest.approx(10**-0.8, rel=0.015)
