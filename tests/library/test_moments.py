"""Adaptive moments: analytic Gaussians, failure modes, perturbation precision, the gradient."""

import math

import numpy as np
import pytest

from nlpsf.sim import moment_kernels, moments
from nlpsf.sim.moments import MomentSettings, MomentStatus

from ..conftest import requires_galsim


def gaussian(n, sx, sy, rho=0.0, x0=0.0, y0=0.0, flux=1.0):
    c = np.arange(n) - (n - 1) / 2
    dx, dy = c[None, :] - x0, c[:, None] - y0
    cov = np.array([[sx**2, rho * sx * sy], [rho * sx * sy, sy**2]])
    inv = np.linalg.inv(cov)
    r2 = inv[0, 0] * dx**2 + 2 * inv[0, 1] * dx * dy + inv[1, 1] * dy**2
    return flux * np.exp(-0.5 * r2) / (2 * np.pi * math.sqrt(np.linalg.det(cov))), cov


def test_elliptical_gaussian_moments_are_its_covariance():
    # Without a weight cut the adaptive-moment matrix of a well-sampled Gaussian is its covariance.
    image, cov = gaussian(96, 4.0, 3.0, 0.3, x0=0.4, y0=-0.7)
    fit = moments.fit(image, MomentSettings(weight_cut_rho2=math.inf))
    assert fit.status[0] == MomentStatus.OK
    assert [fit.mxx[0], fit.mxy[0], fit.myy[0]] == pytest.approx([cov[0, 0], cov[0, 1], cov[1, 1]], rel=1e-10)
    assert [fit.x0[0], fit.y0[0]] == pytest.approx([0.4, -0.7], abs=1e-10)
    assert fit.e1[0] == pytest.approx((16 - 9) / 25, rel=1e-10)
    assert fit.e2[0] == pytest.approx(2 * 0.3 * 12 / 25, rel=1e-10)
    assert fit.sigma[0] == pytest.approx(np.linalg.det(cov) ** 0.25, rel=1e-10)


def test_newton_converges_to_the_float64_floor():
    image, _ = gaussian(64, 2.5, 2.0, -0.2)
    fit = moments.fit(image)
    assert fit.status[0] == MomentStatus.OK
    assert fit.last_step[0] < 1e-13
    assert fit.iterations[0] < 40


def test_moments_do_not_see_the_overall_scale():
    image, _ = gaussian(48, 2.0, 2.6, 0.1)
    a, b = moments.fit(image), moments.fit(3.7e5 * image)
    assert b.sigma[0] == pytest.approx(a.sigma[0], rel=1e-13)
    assert b.e1[0] == pytest.approx(a.e1[0], abs=1e-14)


def test_failures_are_reported_per_image_not_raised():
    good, _ = gaussian(32, 2.0, 2.0)
    batch = np.stack([good, np.zeros_like(good), -good, np.full_like(good, np.nan)])
    fit = moments.fit(batch)
    assert list(fit.status) == [MomentStatus.OK, MomentStatus.NO_FLUX, MomentStatus.NO_FLUX, MomentStatus.NONFINITE_IMAGE]
    assert all(moments.STATUS_REASONS[MomentStatus(s)] for s in fit.status)


def test_undersampled_image_collapses_like_hsm_does():
    point = np.zeros((16, 16))
    point[8, 8] = 1.0
    fit = moments.fit(point)
    assert fit.status[0] == MomentStatus.COLLAPSED


def test_perturbed_fit_resolves_effects_far_below_float64_of_the_image():
    image, _ = gaussian(64, 2.2, 1.9, 0.25)
    ref = moments.fit(image)
    # I^2 of a Gaussian has the Gaussian's shape, so tilt it to move e1 and e2 as well as R.
    c = np.arange(64) - 31.5
    direction = -(image**2) / image.max() * (1 + 0.2 * c[None, :] ** 2 / 4 - 0.1 * c[None, :] * c[:, None] / 4)
    gradient = moments.pixel_response(image, ref)[0]
    linear = np.einsum("kij,ij->k", gradient, direction)
    for eps in (1e-14, 1e-12, 1e-10, 1e-8):
        fit = moments.fit_perturbed(image[None], eps * direction[None], ref)
        d_r, d_e1, _ = moments.differences(fit, ref)
        # Relative to the effect itself: exact to first order, second order ~eps.
        assert d_r[0] / (eps * linear[0]) == pytest.approx(1.0, abs=max(1e-9, 30 * eps))
        assert d_e1[0] / (eps * linear[1]) == pytest.approx(1.0, abs=max(1e-9, 30 * eps))


def test_perturbed_fit_equals_a_cold_fit_for_large_perturbations():
    image, _ = gaussian(64, 2.2, 1.9, 0.25)
    ref = moments.fit(image)
    delta = -0.3 * image**2 / image.max()
    warm = moments.fit_perturbed(image[None], delta[None], ref)
    cold = moments.fit(image + delta)
    assert warm.sigma[0] == pytest.approx(cold.sigma[0], rel=1e-12)
    assert warm.e2[0] == pytest.approx(cold.e2[0], abs=1e-12)


def test_pixel_response_is_the_derivative_of_the_fit():
    image, _ = gaussian(40, 2.0, 1.7, 0.2, x0=0.3)
    ref = moments.fit(image)
    gradient = moments.pixel_response(image, ref)[0]
    rng = np.random.default_rng(5)
    direction = rng.normal(size=image.shape) * image
    h = 1e-6
    plus = moments.fit(image + h * direction, start=ref.parameters())
    minus = moments.fit(image - h * direction, start=ref.parameters())
    numeric = np.array(
        [
            (plus.sigma[0] - minus.sigma[0]) / (2 * h) / ref.sigma[0],
            (plus.e1[0] - minus.e1[0]) / (2 * h),
            (plus.e2[0] - minus.e2[0]) / (2 * h),
        ]
    )
    analytic = np.einsum("kij,ij->k", gradient, direction)
    assert analytic == pytest.approx(numeric, rel=1e-6, abs=1e-12)


def test_weight_cut_is_exact_not_a_crop():
    # The core window must hold every pixel with weight: no cut and a huge cut agree.
    image, _ = gaussian(96, 3.0, 2.0, 0.4, x0=1.2)
    a = moments.fit(image, MomentSettings(weight_cut_rho2=math.inf))
    b = moments.fit(image, MomentSettings(weight_cut_rho2=1e4))
    assert b.sigma[0] == pytest.approx(a.sigma[0], rel=1e-14)


def test_a_perturbed_fit_on_the_core_is_the_fit_on_the_whole_stamp():
    # core_margin trims what no weight window (grown 2x in size) reaches; the perturbed fit of the
    # trimmed stamps must then be the whole stamps' fit, and within() must say so.
    rng = np.random.default_rng(2)
    images = np.stack([gaussian(96, 2.0, 1.7, 0.2, x0=rng.uniform(-1, 1), y0=rng.uniform(-1, 1))[0] for _ in range(6)])
    reference = moments.fit(images)
    margin = moments.core_margin(96, reference, 25.0)
    assert 0 < margin < 48
    delta = -0.2 * images**2 / images.max()
    whole = moments.fit_perturbed(images, delta, reference)
    core = (Ellipsis, slice(margin, 96 - margin), slice(margin, 96 - margin))
    trimmed = moments.fit_perturbed(images[core], delta[core], reference)
    assert np.all(moments.within(trimmed, 96 - 2 * margin, 25.0))
    np.testing.assert_allclose(trimmed.parameters(), whole.parameters(), rtol=1e-13, atol=1e-15)
    # A core smaller than the weight window is caught.
    tiny = (Ellipsis, slice(44, 52), slice(44, 52))
    assert not np.any(moments.within(moments.fit_perturbed(images[tiny], delta[tiny], reference), 8, 25.0))
    # Without a cut every pixel has weight: nothing may be trimmed.
    assert moments.core_margin(96, reference, math.inf) == 0


def test_integer_powers_by_products_equal_numpy_powers():
    d = np.random.default_rng(3).uniform(-12, 12, (4, 30))
    np.testing.assert_allclose(moment_kernels.powers(d, 4), d[..., None] ** np.arange(5), rtol=1e-14)


def test_bad_settings_are_named():
    with pytest.raises(ValueError, match="weight_cut_rho2"):
        MomentSettings(weight_cut_rho2=1.0)
    with pytest.raises(ValueError, match="tolerance"):
        MomentSettings(tolerance=0.0)


@requires_galsim
@pytest.mark.parametrize("cut", [moments.PAPER_WEIGHT_CUT_RHO2, moments.GALSIM_WEIGHT_CUT_RHO2])
def test_agrees_with_galsim_find_adaptive_mom_on_the_same_image(cut, paper_scene):
    import galsim

    from nlpsf.sim.reference import weight_cut_threshold

    images = paper_scene.stamps[:4] * 1e5
    ours = moments.fit(images, MomentSettings(weight_cut_rho2=cut))
    params = galsim.hsm.HSMParams(convergence_threshold=weight_cut_threshold(cut), max_mom2_iter=10000)
    for k, image in enumerate(images):
        theirs = galsim.Image(image).FindAdaptiveMom(precision=1e-10, hsmparams=params)
        # GalSim returns float32: agreement is at its rounding.
        assert ours.sigma[k] == pytest.approx(theirs.moments_sigma, rel=1e-6)
        assert ours.e1[k] == pytest.approx(theirs.observed_shape.e1, abs=1e-6)
        assert ours.e2[k] == pytest.approx(theirs.observed_shape.e2, abs=1e-6)
