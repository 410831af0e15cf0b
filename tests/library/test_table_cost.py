"""The shortcuts that make a Roman-default table cheaper give the numbers of the direct computations.

Each shortcut is checked against the plain computation it replaces, written out here: the pixels whose
coupled signal can reach a threshold (``CoupledPowers.may_reach``) against testing every pixel, IPC
in blocks against the nine-tap sum on the whole stack, the interpolation estimate of several columns
against one column at a time, and the ramp factors on the weight region against the whole core.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import CubicSpline

from nlpsf.sim import experiment, ramps
from nlpsf.sim.scene.kernels import apply_ipc
from nlpsf.slopes import tablebuild

KERNEL = ((0.002, 0.015, 0.001), (0.013, 0.938, 0.015), (0.001, 0.015, 0.002))


def _unit_stamps(count: int = 5, n: int = 30, seed: int = 3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[:n, :n] - (n - 1) / 2
    centres = rng.uniform(-1.5, 1.5, (count, 2))
    stamps = np.exp(-((x - centres[:, 0, None, None]) ** 2 + (y - centres[:, 1, None, None]) ** 2) / (2 * 2.5**2))
    return stamps / stamps.sum(axis=(1, 2), keepdims=True)


def test_pixels_that_may_reach_a_threshold_hold_every_pixel_whose_signal_does():
    unit = _unit_stamps()
    powers = ramps.CoupledPowers(unit, KERNEL, 3)
    background, state = 80.0, (5e-7,)
    measured_unit = apply_ipc(unit, KERNEL, 3)
    for scale in (1e5, 1e6, 3e6, 2e7):
        for threshold in (3e4, 6e4):
            pixels = powers.may_reach(scale, background, threshold, slice(None), state)
            # The direct test: every pixel's measured charge (the largest of its reads' signals).
            measured = scale * measured_unit + background * np.sum(KERNEL)
            reaching = np.flatnonzero(measured.ravel() >= threshold * (1 - 1e-12))
            assert set(reaching) <= set(pixels)
            assert pixels.size <= reaching.size + 0.01 * unit.size  # a bound, not every pixel


def test_pixels_cannot_be_bounded_with_a_negative_coefficient_or_kernel():
    powers = ramps.CoupledPowers(_unit_stamps(), KERNEL, 3)
    assert powers.may_reach(1e6, 80.0, 6e4, slice(None), (-5e-7,)) is None
    negative = ramps.CoupledPowers(_unit_stamps(), ((0, -0.01, 0), (0, 1.02, 0), (0, -0.01, 0)), 3)
    assert negative.may_reach(1e6, 80.0, 6e4, slice(None), (5e-7,)) is None


def test_ipc_in_blocks_is_the_nine_tap_sum_on_the_whole_stack():
    images = np.random.default_rng(5).random((23, 33, 33))
    n = 3
    padded = np.pad(images, [(0, 0), (n, n), (n, n)], mode="edge")
    direct = np.zeros(images.shape)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            direct += KERNEL[1 + dy][1 + dx] * padded[:, n + dy * n : n + dy * n + 33, n + dx * n : n + dx * n + 33]
    assert np.array_equal(apply_ipc(images, KERNEL, n), direct)
    assert np.array_equal(apply_ipc(images[0], KERNEL, n), direct[0])


def test_interpolation_estimate_of_several_columns_is_each_column_alone():
    flux = np.geomspace(1e3, 1e7, 40)[::-1]  # any order
    columns = np.stack([np.sin(np.log(flux)) * flux, 1e-3 * flux**1.2, np.log(flux)], axis=-1)
    together = tablebuild.interpolation_error_estimate(flux, columns)
    for k in range(columns.shape[1]):
        order = np.argsort(flux)
        x, q = flux[order], columns[order, k] / flux[order]
        alone = np.zeros_like(q)
        for i in range(1, q.size - 1):
            keep = np.arange(q.size) != i
            alone[i] = abs(CubicSpline(x[keep], q[keep])(x[i]) - q[i]) / 16.0
        alone[0], alone[-1] = alone[1], alone[-2]
        expected = np.empty_like(alone)
        expected[order] = alone * x
        assert np.allclose(together[:, k], expected, rtol=1e-13, atol=0)


@pytest.mark.slow
def test_ramp_factors_on_the_weight_region_give_the_slopes_of_the_whole_core(monkeypatch):
    settings = tablebuild.TableSettings.roman(realizations=6)
    config = settings.config("K213", 4, position=(3000.0, 900.0))
    magnitudes = [13.2, 15.0, 19.0, 24.0]  # resultants dropped in the core, and none
    scene = experiment.prepare(config)
    assert scene.factor_region is not None
    assert scene.factor_region.sum() < 0.8 * scene.factor_region.size  # fewer pixels than the core
    restricted = experiment.slopes(config, magnitudes, scene=scene, linearise_at=settings.linearise_at)
    monkeypatch.setattr(type(scene), "factor_region", property(lambda self: None))
    whole_core = experiment.slopes(config, magnitudes, scene=experiment.prepare(config), linearise_at=settings.linearise_at)
    for a, b in zip(restricted, whole_core, strict=True):
        for name in ("dR_over_R", "de1", "de2"):
            assert a.bias[name].mean == pytest.approx(b.bias[name].mean, rel=1e-12)
            assert a.scatter[name]["value"] == pytest.approx(b.scatter[name]["value"], rel=1e-12)
        assert a.extras == b.extras and a.flags == b.flags
