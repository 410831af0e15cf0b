"""The calibration capability (nlpsf.calibration, docs/calibration.md), checked against independent truths:

- the quadratic residual through the kernel is the solver's Delta_beta slope (random points, 1 %);
- a residual curve equal to -Delta_beta Q^2 gives Delta_beta times that slope;
- two linearity reference files made by roman_datamodels, differing in one coefficient, against a read-by-read
  simulation that applies each file's correction with stcal to every resultant and fits the ramps
  (``test_residual_correction.brute_force_image``'s pipeline);
- bad files refused, naming the file and what is wrong.
"""

import numpy as np
import pytest

from nlpsf.calibration import requirement, residuals, star_response
from nlpsf.checks import InputError
from nlpsf.sim import experiment, moments
from nlpsf.sim.ramps.correction import quadratic_residual
from nlpsf.slopes import tablebuild

rng = np.random.default_rng(2929)


def _random_point():
    band = str(rng.choice(["R062", "Z087", "Y106", "J129", "H158", "F184", "W146", "K213"]))
    return (
        band,
        int(rng.integers(1, 19)),
        (float(rng.uniform(100, 3990)), float(rng.uniform(100, 3990))),
        float(rng.uniform(18.5, 22.5)),
    )


@pytest.mark.parametrize("point", [_random_point() for _ in range(3)])
def test_the_quadratic_residual_through_the_kernel_is_the_solvers_slope(point):
    from nlpsf.request.resolve import SolveRequest
    from nlpsf.solve import solver

    band, sca, position, magnitude = point
    request = SolveRequest.from_json(
        {
            "band": band,
            "sca": sca,
            "magnitude": magnitude,
            "precision": 0.01,
            "fidelity": "linear",
            "scene": {"position": list(position)},
        }
    )
    scene = requirement.scene_for(request)
    kernel = star_response(scene, magnitude, request.beta0).kernel()
    through = kernel.integrate(quadratic_residual(1.0))
    density = kernel.density()
    for metric in ("size", "e1", "e2", "e"):
        answer = solver.answer(request.with_changes(metric=metric))
        assert answer.conditions["residual_nl"] == "per_resultant_correction"
        assert through[metric][0] == pytest.approx(answer.slope, rel=0.01), metric
        integral = float(np.trapezoid(density[metric][0] * -(kernel.charge_e**2), kernel.charge_e))
        assert integral == pytest.approx(answer.slope, rel=0.01), metric


def test_a_gain_error_changes_nothing_and_the_fractional_bins_hold_the_kernel(h158):
    """A residual that is the same fraction of the charge everywhere (r = s Q, a gain error) scales the image
    and the sky estimate alike: the moments' size and ellipticity are scale-free, so it changes nothing (the
    sum over the star's samples cancels to rounding). The kernel's fractional bins hold exactly that sum by
    parts: they add up to zero, and with r = Q^2 weights they give the quadratic slope."""
    _, scene = h158
    response = star_response(scene, 19.0)
    gain = response.integrate(lambda q: 1e-3 * q)
    scale = np.abs(response.weights).sum(axis=0).max() * 1e-3 * response.levels.max()
    for metric in ("size", "e1", "e2"):
        assert abs(gain[metric][0]) < 1e-12 * scale, metric
    kernel = response.kernel()
    bins = kernel.fractional_bins()
    assert bins["edges_e"].size == bins["size"].size + 1
    assert np.all(np.diff(np.log10(bins["edges_e"])) == pytest.approx(0.1))
    for metric in ("size", "e1", "e2"):
        assert abs(bins[metric].sum()) < 1e-12 * np.abs(bins[metric]).sum(), metric
        assert np.abs(bins[metric]).max() > 0


@pytest.fixture(scope="module")
def h158():
    settings = tablebuild.TableSettings.roman(realizations=3, stamp=48)
    config = settings.config("H158", 7, position=(30.0, 28.0))
    return config, experiment.prepare(config)


def test_a_quadratic_curve_is_the_beta_answer(h158, tmp_path):
    config, scene = h158
    response = star_response(scene, 19.0)
    delta = 3.7e-9
    q = np.linspace(0.0, 1.2 * response.levels.max(), 4001)
    path = tmp_path / "r.ecsv"
    from astropy.table import Table

    Table({"charge_e": q, "residual_e": -delta * q**2}).write(path, format="ascii.ecsv")
    curve = response.integrate(residuals.read_curve(path))
    slope = experiment.slopes(config, [19.0], scene=scene, linearise_at="corrected")[0]
    for metric, name in (("size", "dR_over_R"), ("e1", "de1"), ("e2", "de2")):
        # the curve is linear between 4001 points: its error against -delta Q^2 is (dQ)^2 / 4 at most
        assert curve[metric][0] == pytest.approx(delta * slope.bias[name].mean, rel=1e-3), metric
    with pytest.raises(InputError, match="covers"):
        response.integrate(residuals.from_curve([0.0, 10.0], [0.0, 1.0]))


def _linearity_file(path, coeffs):
    from roman_datamodels import datamodels as rdd

    model = rdd.LinearityRefModel.create_fake_data(shape=coeffs.shape)
    model.coeffs = coeffs.astype(np.float32)
    model.dq = np.zeros(coeffs.shape[1:], dtype=np.uint32)
    model.save(str(path))
    return path


def _inverse_dn(beta_e: float, gain: float, order: int, shape) -> np.ndarray:
    """Per pixel, the inverse series of S = Q - beta Q^2 written in DN (F_c = sum c_k F^k)."""
    import math

    c = np.zeros((order + 1, *shape))
    for k in range(order):
        c[k + 1] = math.comb(2 * k, k) / (k + 1) * beta_e**k * gain**k
    return c


def _oracle():
    from .test_residual_correction import _metrics, _optimal_weights, stcal_correct

    return _metrics, _optimal_weights, stcal_correct


def _truth(h158, magnitude, applied, reference, gain, measured=None):
    """Per realization, (Delta R / R, Delta e1, Delta e2) of ``applied`` against ``reference`` (per-pixel
    polynomials over the 48 x 48 cut-out, in DN), read by read: each polynomial applied with stcal to every
    resultant of every pixel, the optimal fit built read by read, the sky removed (a star-free pixel with
    the mean polynomial of the cut-out's pixels outside ``measured``, the science pixels the moments read),
    the moments fitted."""
    _metrics, _optimal_weights, stcal_correct = _oracle()
    config, scene = h158
    brute = _brute(scene, magnitude, config.scene.position, applied, reference, gain, stcal_correct, _optimal_weights, measured)
    reference_fit = moments.fit(
        float(config.electrons(magnitude)) * config.oversampling**2 * scene.stamps, config.moment_settings
    )
    settings = config.moment_settings
    return (_metrics(brute[0], reference_fit, settings) - _metrics(brute[1], reference_fit, settings)).T


def _close(ours, truth, rtol=0.01):
    for k in range(3):
        assert np.allclose(ours[:, k], truth[:, k], rtol=rtol, atol=1e-3 * np.max(np.abs(truth[:, k]))), k


#: Two pairs of files differing in one coefficient at a random pixel near the star (drawn inside the test from
#: these seeds: the pixel within 2 of the star's, which coefficient -- linear, quadratic or cubic -- and by how
#: much, 1 to 3 % up or down), and one pair whose cubic differs on every pixel besides.
FILE_CASES = [("one coefficient", int(rng.integers(2**31))) for _ in range(2)] + [("and every pixel's cubic", 29)]


@pytest.mark.parametrize("case, seed", FILE_CASES)
def test_two_files_differing_in_one_coefficient_match_a_read_by_read_simulation(h158, tmp_path, case, seed):
    pytest.importorskip("roman_datamodels")
    _, scene = h158
    draw = np.random.default_rng(seed)
    gain, order, magnitude = 2.0, 12, 18.5
    response = star_response(scene, magnitude)
    r0, r1, c0, c1 = residuals.measured_window(response)
    assert (r1 - r0, c1 - c0) == (8, 8)  # the moments' weight reaches 4 pixels from the star's (H158)
    reference = _inverse_dn(5e-7, gain, order, (48, 48))
    applied = reference.copy()
    # near the star: within 2 pixels of its own (the moments' weight is small at the window's edge)
    x, y = (round(v) for v in response.star_position)
    row, col = y + int(draw.integers(-2, 3)), x + int(draw.integers(-2, 3))  # science pixels (1-based)
    k = int(draw.integers(1, 4))
    factor = 1 + draw.choice([-1, 1]) * draw.uniform(0.01, 0.03)
    applied[k, row - 1, col - 1] *= factor  # the cut-out's first pixel is science pixel 1
    if case != "one coefficient":
        applied[3] *= 0.97
    lin_path = _linearity_file(tmp_path / "linearity.asdf", applied)
    ref_path = _linearity_file(tmp_path / "reference.asdf", reference)
    # As nlpsf residual reads them: the pixels of the star's stamp (the measured ones and, around them, the
    # star-free pixels the sky estimate reads).
    window = residuals.star_window(response.star_position, response.stamp, response.oversampling)
    files = residuals.read_linearity(lin_path, window), residuals.read_linearity(ref_path, window)
    effect = residuals.pixel_effect(response, *files, gain)
    assert effect["conditions"]["sky_pixels"] > 0
    per_pixel, _ = residuals.file_residual(response, *files, gain)
    ours = response.per_realization(lambda _levels: per_pixel)
    for j, name in enumerate(("size", "e1", "e2")):
        assert effect["total"][name]["value"] == pytest.approx(ours[:, j].mean(), rel=1e-12)
    # the same polynomials given inline (as the service takes them) give the same answer
    w0, w1, v0, v1 = window
    inline = residuals.pixel_effect(
        response,
        *(
            residuals.PixelPolynomials.inline(c.astype(np.float32)[:, w0 - 1 : w1, v0 - 1 : v1], w0, v0, name)
            for c, name in ((applied, "applied"), (reference, "reference"))
        ),
        gain,
    )
    assert inline["total"] == effect["total"] and inline["bias"] == effect["bias"]
    truth = _truth(h158, magnitude, applied.astype(np.float32), reference.astype(np.float32), gain, (r0, r1, c0, c1))
    assert np.max(np.abs(truth)) > 0
    _close(ours, truth)


def test_a_higher_order_polynomial_residual_matches_a_read_by_read_simulation(h158):
    """A residual r(Q) = a2 Q^2 + ... + a5 Q^5 of random coefficients (each term up to 0.03 % of the charge at
    3e4 e-, which the star's brightest resultants pass: the linear regime), through the kernel's samples,
    against the read-by-read simulation that corrects every resultant with the polynomial L + r(L) (the
    detector's inverse series and the residual, stcal): measured 1.5e-4."""
    from .test_residual_correction import inverse_series, residual_correction

    _, scene = h158
    draw = np.random.default_rng(int(rng.integers(2**31)))
    pivot = 3e4
    a = np.zeros(6)
    for k in range(2, 6):
        a[k] = draw.choice([-1, 1]) * draw.uniform(0.05, 0.3) * 1e-3 * pivot / pivot**k
    magnitude = 18.5
    response = star_response(scene, magnitude)
    ours = response.per_realization(residuals.from_polynomial(a))
    assert response.levels.max() > pivot  # the star's resultants reach where every term is large
    shape = (17, 48, 48)
    applied = np.broadcast_to(residual_correction(5e-7, a)[:, None, None], shape)
    reference = np.broadcast_to(inverse_series(5e-7)[:, None, None], shape)
    truth = _truth(h158, magnitude, applied, reference, 1.0, residuals.measured_window(response))
    _close(ours, truth)
    # and the summary's mean is the realizations' mean
    assert response.integrate(residuals.from_polynomial(a))["size"][0] == pytest.approx(ours[:, 0].mean(), rel=1e-12)


def _brute(scene, magnitude, position, applied, reference, gain, stcal_correct, optimal_weights, measured):
    from nlpsf.sim import ramps
    from nlpsf.sim import scene as scenes

    config = scene.config
    model, table, exptime, n = config.scene, config.ramp.table, config.exptime_s, config.oversampling
    s = float(config.electrons(magnitude)) * n**2
    stamp = scene.stamps.shape[-1]
    centre = (stamp - 1) / 2
    idx = np.arange(stamp)
    rows = np.rint(position[1] + (idx - centre) / n).astype(int) - 1  # 0-based array rows of the cut-out files
    cols = np.rint(position[0] + (idx - centre) / n).astype(int) - 1

    def pipeline(q, coeffs, pixel_rows, pixel_cols):
        reads = []
        for resultant in table.resultants:
            values = []
            for index in resultant:
                c = q * index * table.frame_time_s / exptime
                values.append(scenes.apply_ipc(c - 5e-7 * c * c, model.ipc, n))
            reads.append(np.mean(values, axis=0))
        R = np.stack(reads, axis=-1)
        k = ramps.signal_usable(R.reshape(-1, len(reads)), table, config.full_well_e)
        k = np.where(k == 1, 0, k)
        w = optimal_weights(scenes.apply_ipc(q, model.ipc, n).reshape(-1), k, table, exptime, config.ramp.read_noise_e)
        flat = R.reshape(-1, len(reads))
        pr, pc = np.broadcast_to(pixel_rows, R.shape[:-1]).ravel(), np.broadcast_to(pixel_cols, R.shape[:-1]).ravel()
        corrected = np.zeros_like(flat)
        for p in range(flat.shape[0]):
            corrected[p] = gain * stcal_correct(flat[p : p + 1] / gain, coeffs[:, pr[p], pc[p]])[0]
        return np.sum(w * corrected, axis=1).reshape(R.shape[:-1])

    charge = s * scene.charge + model.background_e
    grid_r = np.broadcast_to(rows[None, :, None], charge.shape)
    grid_c = np.broadcast_to(cols[None, None, :], charge.shape)
    images = []
    for coeffs in (applied, reference):
        image = pipeline(charge, coeffs, grid_r, grid_c)
        star_free = np.ones(coeffs.shape[1:], dtype=bool)
        star_free[measured[0] - 1 : measured[1], measured[2] - 1 : measured[3]] = False
        mean = coeffs[:, star_free].mean(axis=1)[:, None, None]
        sky = pipeline(np.full((1, 3 * n, 3 * n), model.background_e), np.broadcast_to(mean, (mean.shape[0], 1, 1)), 0, 0)
        images.append(image - sky[0, 3 * n // 2, 3 * n // 2])
    return images


def test_bad_linearity_files_are_refused_naming_the_file_and_the_fault(tmp_path):
    pytest.importorskip("roman_datamodels")
    window = (10, 20, 10, 20)
    good = _inverse_dn(5e-7, 2.0, 4, (32, 32))
    nan = good.copy()
    nan[2, 14, 15] = np.nan
    path = _linearity_file(tmp_path / "nan.asdf", nan)
    with pytest.raises(InputError, match=r"nan.asdf: coefficient 2 of science pixel \(row 15, column 16\)"):
        residuals.read_linearity(path, window)
    small = _linearity_file(tmp_path / "small.asdf", good[:, :12, :12])
    with pytest.raises(InputError, match=r"small.asdf: coeffs of shape"):
        residuals.read_linearity(small, window)
    import asdf

    asdf.AsdfFile({"roman": {"meta": {"reftype": "LINEARITY"}}}).write_to(tmp_path / "nokey.asdf")
    with pytest.raises(InputError, match=r"nokey.asdf: no roman.coeffs"):
        residuals.read_linearity(tmp_path / "nokey.asdf", window)
    (tmp_path / "text.asdf").write_text("not asdf")
    with pytest.raises(InputError, match=r"text.asdf: not an ASDF file"):
        residuals.read_linearity(tmp_path / "text.asdf", window)
    flat = good.copy()
    flat[2] = -1e-3  # dF_c/dF = 1 - 2e-3 F: falls past 500 DN
    polys = residuals.PixelPolynomials(flat[:, 9:20, 9:20], 10, 10, "falling.asdf")
    with pytest.raises(InputError, match=r"falling.asdf: the correction of science pixel .* is not monotonic"):
        residuals._check_monotonic(polys, 4e4)
