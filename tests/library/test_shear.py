"""The shear-bias propagation (nlpsf.request.shear) against a simulated galaxy measured with and without a PSF error.

A Gaussian galaxy convolved with a Gaussian PSF is a Gaussian whose covariance is the sum of the
two; we draw it on a pixel grid, measure it and the PSF models with our adaptive moments, correct
by moments (M_gal = M_obs - M_psf_model), turn the corrected distortion into a shear with the
exact inverse for a round source (gamma = e / (1 + sqrt(1 - e^2))), and read m and c from the
estimates with and without the PSF-model error. The formulas hold to first order in the error and
in the ellipticities, so with errors of 1e-3 and |e_psf| <= 0.05 they must agree to ~1 %.
"""

import math

import numpy as np
import pytest

from nlpsf.checks import InputError
from nlpsf.request import shear
from nlpsf.sim import moments

SETTINGS = moments.MomentSettings(weight_cut_rho2=math.inf)
R_PSF = 3.0  # fine pixels; R = det(M)^(1/4)


def covariance(radius: float, e1: float = 0.0, e2: float = 0.0) -> np.ndarray:
    """The 2x2 covariance with det^(1/4) = radius and distortion (e1, e2)."""
    trace = 2 * radius**2 / math.sqrt(1 - e1**2 - e2**2)
    return 0.5 * trace * np.array([[1 + e1, e2], [e2, 1 - e1]])


def sheared(radius: float, g1: float, g2: float = 0.0) -> np.ndarray:
    """A round Gaussian of size ``radius`` sheared by (g1, g2): A C A^T, A the (area-keeping) shear matrix."""
    a = np.array([[1 + g1, g2], [g2, 1 - g1]]) / math.sqrt(1 - g1**2 - g2**2)
    return radius**2 * a @ a.T


def gaussian_image(cov: np.ndarray, n: int) -> np.ndarray:
    y, x = np.mgrid[:n, :n] - (n - 1) / 2
    inverse = np.linalg.inv(cov)
    rho2 = inverse[0, 0] * x**2 + 2 * inverse[0, 1] * x * y + inverse[1, 1] * y**2
    return np.exp(-0.5 * rho2)


def measured(cov: np.ndarray, n: int) -> np.ndarray:
    fit = moments.fit(gaussian_image(cov, n), SETTINGS)
    assert fit.ok.all()
    return np.array([[fit.mxx[0], fit.mxy[0]], [fit.mxy[0], fit.myy[0]]])


def shear_estimate(observed: np.ndarray, psf_model: np.ndarray) -> np.ndarray:
    """(g1, g2) from moment-based PSF correction."""
    m = observed - psf_model
    trace = m[0, 0] + m[1, 1]
    e = np.array([m[0, 0] - m[1, 1], 2 * m[0, 1]]) / trace
    return e / (1 + math.sqrt(1 - e @ e))


def stamp(ratio: float) -> int:
    return int(2 * math.ceil(6 * R_PSF * math.hypot(1, ratio) * 1.2))


@pytest.mark.parametrize("ratio", [0.7, 1.5, 3.0])
@pytest.mark.parametrize("psf_e", [(0.0, 0.0), (0.05, -0.03)])
def test_multiplicative_bias_from_a_psf_size_error(ratio, psf_e):
    # m from the response to +g and -g (an elliptical PSF's size error also adds a c, tested below).
    d_r, g = 1e-3, (0.02, 0.01)
    n = stamp(ratio)
    psf = covariance(R_PSF, *psf_e)
    model = measured(psf * (1 + d_r) ** 2, n)  # the model's R is (1 + d_r) R
    exact_psf = measured(psf, n)
    observed = [measured(sheared(ratio * R_PSF, s * g[0], s * g[1]) + psf, n) for s in (1, -1)]
    exact = [shear_estimate(o, exact_psf) for o in observed]
    wrong = [shear_estimate(o, model) for o in observed]
    m = (wrong[0] - wrong[1]) / (exact[0] - exact[1]) - 1
    c = (wrong[0] + wrong[1]) / 2 - (exact[0] + exact[1]) / 2
    rho = shear.check_size_ratio(ratio)
    predicted = shear.multiplicative_bias(d_r, rho)
    assert m == pytest.approx([predicted, predicted], rel=1e-2)
    # The cross term the e tolerance leaves out (shear.CROSS_TERM_NOTE): c = -e_psf (2 dR/R) / (P rho^2).
    cross = -np.array(psf_e) * 2 * d_r / (shear.RESPONSIVITY * ratio**2)
    assert c == pytest.approx(cross, rel=2e-2, abs=1e-9)  # abs: the round PSF, where it vanishes
    # What the solver inverts: the tolerance that gives this m is the error we put in.
    assert shear.size_tolerance(m[0], rho) == pytest.approx(d_r, rel=1e-2)


@pytest.mark.parametrize("ratio", [0.7, 1.5, 3.0])
@pytest.mark.parametrize("psf_e", [(0.0, 0.0), (0.05, -0.03)])
@pytest.mark.parametrize("component", [0, 1])
def test_additive_bias_from_a_psf_ellipticity_error(ratio, psf_e, component):
    d_e = 1e-3
    n = stamp(ratio)
    psf = covariance(R_PSF, *psf_e)
    model_e = list(psf_e)
    model_e[component] += d_e
    observed = measured(sheared(ratio * R_PSF, 0.0) + psf, n)  # a round galaxy: no shear, any g is c
    exact = shear_estimate(observed, measured(psf, n))
    wrong = shear_estimate(observed, measured(covariance(R_PSF, *model_e), n))
    c = wrong - exact
    predicted = shear.additive_bias(d_e, shear.check_size_ratio(ratio))
    assert c[component] == pytest.approx(predicted, rel=1e-2)
    assert abs(c[1 - component]) < 1e-2 * abs(predicted)
    assert shear.ellipticity_tolerance(c[component], shear.check_size_ratio(ratio)) == pytest.approx(d_e, rel=1e-2)


def test_a_size_distribution_acts_through_the_mean_inverse_square_ratio():
    # m averaged over galaxies (shear weights w) equals the formula at rho_eff = <rho^-2>_w^(-1/2).
    d_r, ratios, weights = 1e-3, [0.8, 1.5, 2.5], [0.2, 0.5, 0.3]
    psf = covariance(R_PSF)
    biases = []
    for ratio in ratios:
        n = stamp(ratio)
        observed = measured(sheared(ratio * R_PSF, 0.02) + psf, n)
        exact = shear_estimate(observed, measured(psf, n))
        biases.append((shear_estimate(observed, measured(psf * (1 + d_r) ** 2, n)) / exact - 1)[0])
    distribution = shear.check_size_ratio(list(zip(ratios, weights, strict=True)))
    assert np.average(biases, weights=weights) == pytest.approx(shear.multiplicative_bias(d_r, distribution), rel=1e-2)
    assert distribution.effective == pytest.approx(np.average(np.array(ratios) ** -2.0, weights=weights) ** -0.5)
    assert min(ratios) < distribution.effective < np.average(ratios, weights=weights)  # small galaxies dominate


def test_size_ratio_forms_agree(tmp_path):
    pairs = [(1.2, 0.3), (1.5, 0.5), (2.0, 0.2)]
    path = tmp_path / "ratios.txt"
    path.write_text("# ratio weight\n1.2 0.3\n1.5, 0.5\n2.0 0.2  # big ones\n")
    forms = [
        pairs,
        {"ratios": [1.2, 1.5, 2.0], "weights": [0.3, 0.5, 0.2]},
        "1.2:0.3,1.5:0.5,2:0.2",
        f"@{path}",
    ]
    effective = [shear.check_size_ratio(f).effective for f in forms]
    assert effective == pytest.approx([effective[0]] * len(forms), rel=1e-15)
    assert shear.check_size_ratio("1.5").effective == 1.5
    assert shear.check_size_ratio([1.5, 1.5]).effective == pytest.approx(1.5)


@pytest.mark.parametrize(
    "value",
    [
        "",
        "abc",
        "1.5:x",
        "-1",
        "0",
        "1:0",
        "@/no/such/file",
        [],
        [(1.0, 2.0, 3.0)],
        {"ratio": 1},
        True,
        float("nan"),
        [(1.0, 1e300)],
    ],
)
def test_bad_size_ratios_name_the_field(value):
    with pytest.raises(InputError) as info:
        shear.check_size_ratio(value)
    assert info.value.argument == "size_ratio"


def test_budget_goes_with_its_metric():
    assert shear.budget_for("size", shear_m=1e-3, size_ratio=1.5).tolerance == pytest.approx(1e-3 * 1.5**2 / 2)
    assert shear.budget_for("e1", shear_c=1e-4, size_ratio=1.5).tolerance == pytest.approx(2 * 1e-4 * 1.5**2)
    for metric, kwargs, field in [
        ("e1", {"shear_m": 1e-3}, "shear_m"),
        ("size", {"shear_c": 1e-3}, "shear_c"),
        ("size", {"shear_m": 1e-3, "shear_c": 1e-3}, "shear_c"),
        ("size", {"shear_m": 2.0}, "shear_m"),
        ("size", {"shear_m": 0.0}, "shear_m"),
    ]:
        with pytest.raises(InputError) as info:
            shear.budget_for(metric, size_ratio=1.5, **kwargs)
        assert info.value.argument == field
    with pytest.raises(InputError) as info:
        shear.budget_for("size", shear_m=1e-3)
    assert info.value.argument == "size_ratio"


@pytest.mark.parametrize("method", ["BJ", "REGAUSS", "KSB"])
@pytest.mark.parametrize("ratio", [0.7, 1.5, 3.0])
def test_galsims_psf_corrections_agree_with_the_formulas(method, ratio):
    """An independent measurement: GalSim's HSM PSF correction (BJ, REGAUSS: distortions; KSB: a
    shear) of a sheared Gaussian galaxy with a PSF model that is too large, or too elongated."""
    galsim = pytest.importorskip("galsim")
    d_r, d_e, sigma = 1e-3, 1e-3, 2.0
    n = int(2 * 12 * sigma * (1 + ratio))
    psf = galsim.Gaussian(sigma=sigma)

    def draw(profile):
        return profile.drawImage(nx=n, ny=n, scale=1.0, method="no_pixel")

    def shear_of(observed, model) -> np.ndarray:
        result = galsim.hsm.EstimateShear(observed, draw(model), shear_est=method)
        if method == "KSB":
            return np.array([result.corrected_g1, result.corrected_g2])
        return np.array([result.corrected_e1, result.corrected_e2]) / shear.RESPONSIVITY  # distortion -> shear

    rho = shear.check_size_ratio(ratio)
    estimates = []
    for sign in (1, -1):
        observed = draw(galsim.Convolve(galsim.Gaussian(sigma=ratio * sigma).shear(g1=0.02 * sign), psf))
        estimates.append((shear_of(observed, psf), shear_of(observed, galsim.Gaussian(sigma=sigma * (1 + d_r)))))
    m = (estimates[0][1][0] - estimates[1][1][0]) / (estimates[0][0][0] - estimates[1][0][0]) - 1
    assert m == pytest.approx(shear.multiplicative_bias(d_r, rho), rel=1e-2)
    round_galaxy = draw(galsim.Convolve(galsim.Gaussian(sigma=ratio * sigma), psf))
    c = shear_of(round_galaxy, psf.shear(e1=d_e)) - shear_of(round_galaxy, psf)
    assert c[0] == pytest.approx(shear.additive_bias(d_e, rho), rel=1e-2)
