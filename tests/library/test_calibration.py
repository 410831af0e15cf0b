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


def test_two_files_differing_in_one_coefficient_match_a_read_by_read_simulation(h158, tmp_path):
    pytest.importorskip("roman_datamodels")
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_residual_correction import _metrics, _optimal_weights, stcal_correct

    config, scene = h158
    gain, order = 2.0, 12
    shape = (48, 48)
    reference = _inverse_dn(5e-7, gain, order, shape)
    applied = reference.copy()
    row, col = 16, 21  # one pixel under the star (science pixel row 17, column 22)
    applied[2, row, col] *= 1.02  # its quadratic coefficient 2 % larger
    applied[3] *= 0.97  # and every pixel's cubic term 3 % smaller
    ref_path = _linearity_file(tmp_path / "reference.asdf", reference)
    lin_path = _linearity_file(tmp_path / "linearity.asdf", applied)
    magnitude = 18.5
    response = star_response(scene, magnitude)
    position = config.scene.position
    window = residuals.star_window(position, scene.stamps.shape[-1], config.oversampling)
    per_pixel, _ = residuals.file_residual(
        response, position, residuals.read_linearity(lin_path, window), residuals.read_linearity(ref_path, window), gain
    )
    ours = np.zeros((response.count, 3))
    for k in range(3):
        ours[:, k] = np.bincount(response.owner, weights=response.weights[:, k] * per_pixel, minlength=response.count)
    # Read by read: each file's polynomial (per pixel) applied with stcal to every resultant, fitted, the sky removed.
    brute = _brute(scene, magnitude, position, applied, reference, gain, stcal_correct, _optimal_weights)
    reference_fit = moments.fit(
        float(config.electrons(magnitude)) * config.oversampling**2 * scene.stamps, config.moment_settings
    )
    truth = _metrics(brute[0], reference_fit, config.moment_settings) - _metrics(brute[1], reference_fit, config.moment_settings)
    for k in range(3):
        assert np.allclose(ours[:, k], truth[k], rtol=0.01, atol=1e-3 * np.max(np.abs(truth[k]))), k


def _brute(scene, magnitude, position, applied, reference, gain, stcal_correct, optimal_weights):
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
        mean = coeffs.mean(axis=(1, 2))[:, None, None]
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
