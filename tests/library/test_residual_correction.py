"""The calibration residual as the pipeline leaves it: the linearity correction on every resultant.

Two independent checks of ``residual_nl="per_resultant_correction"`` (``nlpsf.sim.experiment.correction``,
``nlpsf.sim.ramps.correction``):

- **stcal as the oracle of the correction.** stcal's ``linearity_correction`` (what romancal's linearity step
  calls, classic path) applies polynomial coefficients to the same resultants; the corrected resultants
  nlpsf's per-resultant model implies, L(R) + r(L(R)), equal stcal's output for a correction polynomial that
  is the detector's inverse (its series to order 16) plus a residual.
- **A read-by-read brute force.** Every read's charge, the raw NL on it, IPC on every read (the scene's kernel),
  resultant means, romancal's saturation rule, the correction applied with stcal to each resultant, the
  optimal slope fitted by an explicit generalised least-squares solve with the covariance built read by read,
  the sky removed as a star-free pixel's own fitted level, and adaptive moments fitted to convergence on the
  result: its finite-difference slope in the calibration error equals nlpsf's linear-response slope, where
  no resultant saturates and between the saturation limits.
"""

import math

import numpy as np
import pytest

from nlpsf.checks import InputError
from nlpsf.sim import experiment, moments, ramps
from nlpsf.sim import scene as scenes
from nlpsf.slopes import tablebuild

stcal_linearity = pytest.importorskip("stcal.linearity.linearity")

BETA0 = 5e-7
#: Order of the detector's inverse series in the correction polynomials (4 beta0 S <= 0.25 here: the
#: series' remainder is below 1e-12 of the signal).
ORDER = 16
DQ = {"SATURATED": 2, "NO_LIN_CORR": 1 << 20, "DO_NOT_USE": 1}


def inverse_series(beta: float, order: int = ORDER) -> np.ndarray:
    """Coefficients of Q(S) = sum_k C_k beta^k S^(k+1), the inverse of S = Q - beta Q^2 (Catalan numbers)."""
    out = np.zeros(order + 1)
    for k in range(order):
        out[k + 1] = math.comb(2 * k, k) / (k + 1) * beta**k
    return out


def residual_correction(beta: float, residual: np.ndarray, order: int = ORDER) -> np.ndarray:
    """The polynomial L(S) + r(L(S)) for r(Q) = sum_m residual[m] Q^m (truncated at ``order``)."""
    inverse = np.polynomial.Polynomial(inverse_series(beta, order))
    total = inverse + np.polynomial.Polynomial(residual)(inverse)
    coefficients = np.zeros(order + 1)
    coefficients[: min(order + 1, total.coef.size)] = total.coef[: order + 1]
    return coefficients


def stcal_correct(resultants: np.ndarray, coefficients: np.ndarray) -> np.ndarray:
    """stcal's linearity_correction (classic path) on (pixels, K) resultants, one polynomial for all pixels."""
    pixels, K = resultants.shape
    data = np.ascontiguousarray(resultants.T.reshape(1, K, 1, pixels)).astype(np.float64)
    gdq = np.zeros(data.shape, dtype=np.uint32)
    pdq = np.zeros((1, pixels), dtype=np.uint32)
    coeffs = np.repeat(coefficients[:, None, None], pixels, axis=2).astype(np.float64)
    lin_dq = np.zeros((1, pixels), dtype=np.uint32)
    out, _, _ = stcal_linearity.linearity_correction(data, gdq, pdq, coeffs, lin_dq, DQ)
    return out[0, :, 0, :].T


def test_the_per_resultant_correction_is_stcals_on_the_same_resultants():
    rng = np.random.default_rng(29)
    table = ramps.load_ma_table("C2A_IMG_HLWAS")
    exptime = table.duration_s
    rate = rng.uniform(0.0, 1.1e5, 400)
    coupled = rate**2 * rng.uniform(0.9, 1.1, rate.size)  # an IPC(Q^2) that is not rate^2
    means = table.mean_powers(exptime, (1, 2))
    weights = rng.normal(size=(rate.size, table.n_resultants))
    cr = ramps.correction.correct(rate, {2: coupled}, (BETA0,), means, weights, rate.shape)
    resultants = np.multiply.outer(rate, means[0]) - BETA0 * np.multiply.outer(coupled, means[1])
    delta = 3e-9
    expected = stcal_correct(resultants, residual_correction(BETA0, np.array([0.0, 0.0, -delta])))
    ours = cr.level + ramps.correction.quadratic_residual(delta)(cr.level)
    assert np.max(np.abs(ours - expected) / np.maximum(expected, 1.0)) < 1e-12
    # The perfectly corrected level alone: stcal with the inverse series.
    assert np.max(np.abs(cr.level - stcal_correct(resultants, inverse_series(BETA0))) / np.maximum(cr.level, 1)) < 1e-12
    # A cubic residual too (any shape enters as r at each resultant's corrected level).
    cubic = np.array([0.0, 0.0, 0.0, 2e-14])
    expected = stcal_correct(resultants, residual_correction(BETA0, cubic))
    ours = cr.level + ramps.correction.polynomial_residual(cubic)(cr.level)
    assert np.max(np.abs(ours - expected) / np.maximum(expected, 1.0)) < 1e-12


def test_inverse_excess_inverts_polynomial_responses():
    q = np.linspace(0.0, 2e5, 2001)
    for coefficients in ((5e-7,), (5e-7, 1e-13), (4e-7, 1e-13, 1e-18), (-3e-7,)):
        signal = q.copy()
        for n, b in enumerate(coefficients, start=2):
            signal -= b * q**n
        excess = ramps.correction.inverse_excess(signal, coefficients)
        assert np.allclose(signal + excess, q, rtol=1e-13, atol=1e-9)
    # Beyond the quadratic's maximum (1 / 4 beta) there is no inverse: NaN, never a silent number.
    assert np.isnan(ramps.correction.inverse_excess(np.array([1.0 / (4 * 5e-7) * 1.01]), (5e-7,)))[0]


def _ipc(images, kernel, n):
    return scenes.apply_ipc(images, kernel, n)


def _optimal_weights(rate, k, table, exptime, read_noise):
    """GLS slope weights of each pixel on its first k resultants, the covariance built read by read."""
    tau = [np.array(r, dtype=float) * table.frame_time_s / exptime for r in table.resultants]
    K = len(tau)
    P = np.empty((K, K))
    for i in range(K):
        for j in range(K):
            P[i, j] = np.mean(np.minimum.outer(tau[i], tau[j]))
    n = np.array([len(t) for t in tau], dtype=float)
    tbar = np.array([t.mean() for t in tau])
    out = np.zeros((rate.size, K))
    for p in range(rate.size):
        kk = int(k[p])
        if kk <= 1:
            out[p, 0] = 1.0 / tbar[0]
            continue
        C = np.diag(read_noise**2 / n[:kk]) + rate[p] * P[:kk, :kk]
        X = np.stack([np.ones(kk), tbar[:kk]], axis=1)
        Ci = np.linalg.inv(C)
        out[p, :kk] = (np.linalg.inv(X.T @ Ci @ X) @ X.T @ Ci)[1]
    return out


def brute_force_image(scene, flux_scale, delta_beta):
    """The corrected, fitted, sky-removed image of every realization, read by read (e- per exposure), and
    each pixel's usable resultants."""
    config = scene.config
    model = config.scene
    table, exptime, n = config.ramp.table, config.exptime_s, config.oversampling
    B = model.background_e
    charge = flux_scale * scene.charge + B
    correction = residual_correction(BETA0, np.array([0.0, 0.0, -delta_beta]))

    def pipeline(q):
        reads = []
        for resultant in table.resultants:
            values = []
            for index in resultant:
                t = index * table.frame_time_s / exptime
                c = q * t
                values.append(_ipc(c - BETA0 * c * c, model.ipc, n))
            reads.append(np.mean(values, axis=0))
        R = np.stack(reads, axis=-1).reshape(-1, len(reads))
        k = ramps.signal_usable(R, table, config.full_well_e)
        k = np.where(k == 1, 0, k)
        rate = _ipc(q, model.ipc, n).reshape(-1)
        w = _optimal_weights(rate, k, table, exptime, config.ramp.read_noise_e)
        return np.sum(w * stcal_correct(R, correction), axis=1).reshape(q.shape), k.reshape(q.shape)

    image, usable = pipeline(charge)
    sky, _ = pipeline(np.full((1, 3 * n, 3 * n), B))  # a star-free pixel's fitted level, its NL included
    return image - sky[0, 3 * n // 2, 3 * n // 2], usable


def _metrics(image, reference, settings):
    fit = moments.fit(image, settings)
    return np.array(moments.differences(fit, reference))


@pytest.mark.parametrize("magnitude", [19.0, 16.6])
def test_brute_force_read_by_read_pipeline_gives_the_default_slope(magnitude):
    """H158 SCA 7 default scene, 3 centroids: no resultant saturated (m = 19) and between the limits (16.6)."""
    settings = tablebuild.TableSettings.roman(realizations=3, stamp=48)
    config = settings.config("H158", 7, position=(900.0, 3100.0))
    scene = experiment.prepare(config)
    flux_scale = float(config.electrons(magnitude)) * config.oversampling**2
    reference = moments.fit(flux_scale * scene.stamps, config.moment_settings)
    h = 2e-9
    plus, usable = brute_force_image(scene, flux_scale, h)
    minus, _ = brute_force_image(scene, flux_scale, -h)
    slope = (_metrics(plus, reference, config.moment_settings) - _metrics(minus, reference, config.moment_settings)) / (2 * h)
    ours = experiment.slopes(config, [magnitude], scene=scene, linearise_at="corrected")[0]
    assert ours.conditions["residual_nl"] == "per_resultant_correction"
    if magnitude < 17:
        assert np.any((usable > 0) & (usable < config.ramp.table.n_resultants))  # between the limits
    for k, name in enumerate(("dR_over_R", "de1", "de2")):
        brute = float(np.mean(slope[k]))
        assert ours.bias[name].mean == pytest.approx(brute, rel=1e-5), name  # measured 1e-9 and 7e-8


def test_the_default_answer_names_its_residual_model_and_the_earlier_one_stays_selectable():
    from dataclasses import replace

    from nlpsf.request import presets as roman_default
    from nlpsf.request.resolve import SolveRequest
    from nlpsf.solve import solver

    scene = replace(roman_default.base_scene(), position=(1200.0, 2900.0))
    common = {"band": "Y106", "sca": 4, "magnitude": 19.0, "precision": 0.01, "scene": scene, "fidelity": "linear"}
    default = solver.answer(SolveRequest(**common))
    earlier = solver.answer(SolveRequest(**common, residual_nl="per_read_beta"))
    assert default.conditions["residual_nl"] == "per_resultant_correction"
    assert earlier.conditions["residual_nl"] == "per_read_beta"
    assert default.tolerance != earlier.tolerance
    with pytest.raises(InputError) as error:
        SolveRequest(**{**common, "scene": "paper"}, residual_nl="per_read_beta")  # the paper's state is beta0
    assert error.value.argument == "residual_nl"
    with pytest.raises(InputError) as error:
        SolveRequest(**common, residual_nl="per_frame")
    assert error.value.argument == "residual_nl"


def test_the_monte_carlo_difference_is_the_linear_response_on_a_band_integrated_psf():
    # Under the per-resultant correction the image is exactly linear in the calibration error, so the
    # Monte Carlo's finite difference must give the linear response's derivative up to the moments'
    # curvature. R062 SCA 1, m = 20 (small e slopes, 8 wavelengths): a step of 1e-4 beta0 met the
    # adaptive fits' convergence instead (e1 -19.9 +- 9.2 against -29.1).
    from dataclasses import replace

    base = tablebuild.TableSettings.roman().config("R062", 1)  # the SCA centre
    values = {}
    for method in ("linear", "monte_carlo"):
        config = replace(base, method=method, n_wavelengths=8)
        result = experiment.slopes(config, [20.0], linearise_at="corrected")[0]
        values[method] = {k: result.bias[k].mean for k in ("dR_over_R", "de1", "de2")}
    modulus = math.hypot(values["linear"]["de1"], values["linear"]["de2"])
    assert values["monte_carlo"]["dR_over_R"] == pytest.approx(values["linear"]["dR_over_R"], rel=1e-3)
    for k in ("de1", "de2"):
        assert abs(values["monte_carlo"][k] - values["linear"][k]) < 0.02 * modulus, (k, values)
