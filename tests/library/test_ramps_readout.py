"""The ramp as the pipeline sees it: an independent read-by-read implementation, romancal's choices.

``brute_force`` below is written from the physics, pixel by pixel and read by read, sharing no code
with ``nlpsf.sim.ramps``: charge accumulates linearly, every read reports S(Q), resultants are means of
reads, saturated resultants are flagged (either rule), and the slope is fitted by an explicit
least-squares solve (numpy's lstsq for OLS; the generalised solve with the covariance built read by
read for the optimal fit). The romancal saturation rule is checked against stcal's own
``flag_saturated_pixels`` where stcal is installed (a test dependency; skipped without it).
"""

import numpy as np
import pytest

from nlpsf.sim import ramps

FULL_WELL = 1.1e5
BETA = 5e-7


def _signal(q, coefficients):
    s = q
    power = q * q
    for b in coefficients:
        s = s - b * power
        power = power * q
    return s


def _romancal_flags(resultants, read_pattern, threshold):
    """romancal's saturation step written out from its documentation and stcal's loops, one pixel."""
    K = len(resultants)
    flagged = [False] * K
    saturated = [False] * K
    for j in range(K):
        if resultants[j] >= threshold or (j and saturated[j - 1]):
            saturated[j] = flagged[j] = True
    for j in range(K - 2, -1, -1):
        dilution = np.mean(read_pattern[j]) / read_pattern[j][-1]
        if dilution != 1 and not flagged[j] and saturated[j + 1] and resultants[j] >= threshold * dilution:
            flagged[j] = True
    if K > 2:
        r1, r2 = resultants[0], resultants[1]
        if (
            r1 / np.mean(read_pattern[0]) * read_pattern[2][-1] < threshold
            and r2 - r1 > (threshold - r1) / len(read_pattern[1])
            and saturated[2]
            and not saturated[1]
        ):
            flagged[1] = True
    return flagged


def brute_force(
    q,
    table,
    exptime,
    coefficients=(BETA,),
    background=0.0,
    fit="ols",
    read_noise=10.0,
    saturation="charge",
    single="through_zero",
    state=None,
    full_well=FULL_WELL,
):
    """(image = fitted slope x exposure, usable resultants) of one pixel, read by read."""
    rate = (q + background) / exptime  # e-/s
    state = coefficients if state is None else state
    resultants, flag_resultants, last_charge, tbar = [], [], [], []
    for reads in table.resultants:
        values, flag_values = [], []
        for index in reads:
            t = index * table.frame_time_s
            charge = rate * t
            values.append(_signal(charge, coefficients))
            flag_values.append(_signal(charge, state))
        resultants.append(sum(values) / len(values))
        flag_resultants.append(sum(flag_values) / len(flag_values))
        last_charge.append(rate * reads[-1] * table.frame_time_s)
        tbar.append(sum(i * table.frame_time_s for i in reads) / len(reads) / exptime)
    if saturation == "charge":
        flags = [c > full_well for c in last_charge]
        flags = [any(flags[: j + 1]) for j in range(len(flags))]
    else:
        flags = _romancal_flags(flag_resultants, table.resultants, full_well)
    k = next((j for j, f in enumerate(flags) if f), len(flags))
    if single == "unusable" and k == 1:
        k = 0
    if k <= 1:  # one resultant (or an unusable pixel's reported value): through zero
        return resultants[0] / tbar[0], k
    y, t = np.array(resultants[:k]), np.array(tbar[:k])
    X = np.stack([np.ones(k), t], axis=1)
    if fit == "ols":
        return float(np.linalg.lstsq(X, y, rcond=None)[0][1]), k
    # Covariance of the resultants, read by read: Poisson counts are cumulative, cov(Q_a, Q_b) = rate_e min(t_a, t_b)
    # (in units of the exposure: total charge q + b times min(tau_a, tau_b)), plus independent read noise.
    total = q + background
    C = np.zeros((k, k))
    for i in range(k):
        for j in range(k):
            ri, rj = table.resultants[i], table.resultants[j]
            acc = 0.0
            for a in ri:
                for b in rj:
                    acc += total * min(a, b) * table.frame_time_s / exptime + (read_noise**2 if a == b else 0.0)
            C[i, j] = acc / (len(ri) * len(rj))
    Ci = np.linalg.inv(C)
    return float(np.linalg.solve(X.T @ Ci @ X, X.T @ Ci @ y)[1]), k


TABLES = ["romanisim-110", "romanisim-109", "C2A_IMG_HLWAS"]
CHARGES = np.array([0.0, 37.0, 2.5e3, 4e4, 1.2e5, 2.9e5, 6e5, 2e6, 5e6])


@pytest.mark.parametrize("name", TABLES)
@pytest.mark.parametrize("fit", ["ols", "optimal"])
@pytest.mark.parametrize("rule", [("charge", "through_zero"), ("signal", "unusable"), ("signal", "through_zero")])
def test_ramps_reproduce_the_read_by_read_brute_force(name, fit, rule):
    table = ramps.load_ma_table(name)
    T = table.duration_s
    ramp = ramps.Ramp(table, fit, 10.0, saturation=rule[0], single_resultant=rule[1])
    coefficients, background = (BETA, 2e-13), 120.0
    got = ramps.simulate_pixels(CHARGES, ramp, T, FULL_WELL, coefficients, background)
    perturbation, usable = ramps.nonlinearity_perturbation(CHARGES, ramp, T, FULL_WELL, coefficients, background)
    for i, q in enumerate(CHARGES):
        image, k = brute_force(q, table, T, coefficients, background, fit, 10.0, *rule)
        assert got.usable[i] == usable[i] == k
        # The explicit reads agree with the brute force to rounding of the image.
        assert got.image[i] == pytest.approx(image, rel=2e-15, abs=1e-9)
        # The factor form: image - (q + b) + the sky's own fitted NL, i.e. the star's perturbation.
        sky, _ = brute_force(0.0, table, T, coefficients, background, fit, 10.0, *rule)
        expected = (image - (q + background)) - (sky - background)
        assert perturbation[i] == pytest.approx(expected, rel=1e-9, abs=1e-9 * max(1.0, abs(image)))


def test_the_perturbation_is_exact_to_1e_15_where_the_fit_is_exact():
    # Without background and with one power, the factor form -beta q^2 c_2 and the brute force are the same
    # number: compare the perturbation itself (not the image it is a tiny part of) at 1e-15 relative... to
    # the rounding of the brute force's subtraction image - q, which is |image| x 1e-16.
    table = ramps.load_ma_table("romanisim-110")
    T = table.duration_s
    for fit in ("ols", "optimal"):
        ramp = ramps.Ramp(table, fit, 10.0)
        for q in (1e3, 3e4, 9e4):
            perturbation, _ = ramps.nonlinearity_perturbation(np.array([q]), ramp, T, FULL_WELL, (BETA,))
            image, _ = brute_force(q, table, T, (BETA,), 0.0, fit)
            assert abs(perturbation[0] - (image - q)) <= 1e-15 * q * 4


def test_romancal_rule_matches_stcal_flag_saturated_pixels():
    saturation = pytest.importorskip("stcal.saturation.saturation", reason="stcal not installed (test dependency)")
    dq = {"DO_NOT_USE": 1, "SATURATED": 2, "AD_FLOOR": 64, "NO_SAT_CHECK": 2**21}
    rng = np.random.default_rng(3)
    for name in [*TABLES, "romanisim-3", "romanisim-12"]:
        table = ramps.load_ma_table(name)
        T = table.duration_s
        charges = np.exp(rng.uniform(np.log(5e4), np.log(3e7), 400))
        ramp = ramps.Ramp(table, "ols", 10.0, saturation="signal")
        signal = ramps.resultant_means(charges, ramp, T, ramps.polynomial_response((BETA,)))
        # The resultants where stcal's loops need them: a second-resultant jump made by hand as well.
        data = np.ascontiguousarray(signal.T[None, :, None, :])  # (ints, groups, rows, cols)
        gdq = np.zeros(data.shape, dtype=np.uint32)
        pdq = np.zeros(data.shape[2:], dtype=np.uint32)
        thresh = np.full(data.shape[2:], FULL_WELL)
        out, _, _ = saturation.flag_saturated_pixels(
            data,
            gdq,
            pdq,
            thresh,
            np.zeros_like(pdq),
            65535.0 * 1e3,
            dq,
            n_pix_grow_sat=0,
            read_pattern=[list(r) for r in table.resultants],
        )
        flagged = (out[0, :, 0, :] & (dq["SATURATED"] | dq["DO_NOT_USE"])) != 0  # (groups, pixels)
        first = np.where(flagged.any(axis=0), np.argmax(flagged, axis=0), table.n_resultants)
        assert np.all(ramps.signal_usable(signal, table, FULL_WELL) == first)
        # and the hand-written rule agrees pixel by pixel
        for p in range(0, charges.size, 37):
            hand = _romancal_flags(list(signal[p]), table.resultants, FULL_WELL)
            assert next((j for j, f in enumerate(hand) if f), table.n_resultants) == first[p]


def test_romancal_second_resultant_pass_is_exercised():
    # A pixel whose second resultant jumps (its last read saturated) with the third saturated.
    table = ramps.MATable(((1,), (2, 3, 4), (5, 6, 7), (8,)), 3.04)
    R = np.array([[1000.0, 70000.0, 2e5, 2e5]])
    assert ramps.signal_usable(R, table, FULL_WELL)[0] == 1
    hand = _romancal_flags(list(R[0]), table.resultants, FULL_WELL)
    assert hand == [False, True, True, True]


# --- ramps inside a scene: IPC, background, polynomial NL -------------------------------------------


def _ipc_loops(image, kernel, n):
    """IPC by explicit loops: pixel (y, x) takes K[1+dy, 1+dx] of the pixel (y + dy n, x + dx n); beyond the
    edge the nearest pixel (the simulator's convention: a uniform field stays uniform)."""
    out = np.zeros_like(image)
    H, W = image.shape
    for y in range(H):
        for x in range(W):
            acc = 0.0
            for dy in (-1, 0, 1):
                for dx in (-1, 0, 1):
                    yy, xx = min(max(y + dy * n, 0), H - 1), min(max(x + dx * n, 0), W - 1)
                    acc += kernel[1 + dy][1 + dx] * image[yy, xx]
            out[y, x] = acc
    return out


def _scene_brute_force(Q, table, T, coefficients, kernel, order, n, fit, saturation, single, read_noise=10.0):
    """Fitted image of a small stamp, read by read: every read's S coupled by IPC (after) or the charge
    coupled first (before), resultants per pixel, each pixel's flags and fit as in ``brute_force``."""
    if order == "before":
        Q = _ipc_loops(Q, kernel, n)
    reads = [i for r in table.resultants for i in r]
    data = {}
    for i in reads:
        tau = i * table.frame_time_s / T
        s = _signal(Q * tau, coefficients)
        data[i] = _ipc_loops(s, kernel, n) if order == "after" else s
    measured = _ipc_loops(Q, kernel, n) if order == "after" else Q
    image = np.zeros_like(Q)
    usable = np.zeros(Q.shape, dtype=int)
    tbar = np.array([np.mean(r) * table.frame_time_s / T for r in table.resultants])
    for y in range(Q.shape[0]):
        for x in range(Q.shape[1]):
            R = [np.mean([data[i][y, x] for i in r]) for r in table.resultants]
            if saturation == "charge":
                last = [Q[y, x] * r[-1] * table.frame_time_s / T for r in table.resultants]
                flags = [any(c > FULL_WELL for c in last[: j + 1]) for j in range(len(last))]
            else:
                flags = _romancal_flags(R, table.resultants, FULL_WELL)
            k = next((j for j, f in enumerate(flags) if f), len(flags))
            if single == "unusable" and k == 1:
                k = 0
            usable[y, x] = k
            if k <= 1:
                image[y, x] = R[0] / tbar[0]
                continue
            X = np.stack([np.ones(k), tbar[:k]], axis=1)
            yv = np.array(R[:k])
            if fit == "ols":
                image[y, x] = np.linalg.lstsq(X, yv, rcond=None)[0][1]
            else:
                C = np.zeros((k, k))
                for a_, ra in enumerate(table.resultants[:k]):
                    for b_, rb in enumerate(table.resultants[:k]):
                        C[a_, b_] = sum(
                            measured[y, x] * min(a, b) * table.frame_time_s / T + (read_noise**2 if a == b else 0.0)
                            for a in ra
                            for b in rb
                        ) / (len(ra) * len(rb))
                Ci = np.linalg.inv(C)
                image[y, x] = np.linalg.solve(X.T @ Ci @ X, X.T @ Ci @ yv)[1]
    return image - measured, usable


@pytest.mark.parametrize("order", ["after", "before"])
@pytest.mark.parametrize("fit", ["ols", "optimal"])
@pytest.mark.parametrize("rule", [("charge", "through_zero"), ("signal", "unusable")])
def test_ramp_with_ipc_background_and_polynomial_nl_equals_the_brute_force(order, fit, rule):
    from nlpsf.sim.scene import ROMAN_IPC_KERNEL

    rng = np.random.default_rng(7)
    n = 3
    table = ramps.load_ma_table("romanisim-109")
    T = table.duration_s
    ramp = ramps.Ramp(table, fit, 10.0, saturation=rule[0], single_resultant=rule[1])
    yy, xx = np.mgrid[0:12, 0:12]
    star = 2.5e6 * np.exp(-((yy - 5.3) ** 2 + (xx - 6.1) ** 2) / 6.0) * (1 + 0.05 * rng.standard_normal((12, 12)))
    Q = np.abs(star) + 150.0  # background 150 e-
    coefficients = (BETA, 3e-12, -1e-17)
    kernel = np.asarray(ROMAN_IPC_KERNEL) * 8  # a strong coupling, so that it matters at the test's precision
    kernel[1, 1] = 0.0
    kernel[1, 1] = 1.0 - kernel.sum()
    sr = ramps.scene_factors(Q, ramp, T, FULL_WELL, coefficients, (2, 3, 4), kernel, order, n)
    perturbation, derivative = ramps.scene_perturbation(sr, coefficients[0], coefficients[1:], kernel, order, n)
    expected, usable = _scene_brute_force(Q, table, T, coefficients, kernel, order, n, fit, *rule)
    assert np.all(sr.usable == usable)
    assert np.sum(usable < table.n_resultants) > 0  # some pixels drop resultants
    scale = np.abs(expected).max()
    assert np.allclose(perturbation, expected, rtol=1e-10, atol=1e-12 * scale)
    # d/d b2: the brute force's finite difference in b2 (the fit is linear in the coefficients at fixed flags)
    step = 1e-3 * BETA
    plus = ramps.scene_perturbation(sr, BETA + step, coefficients[1:], kernel, order, n)[0]
    assert np.allclose(derivative, (plus - perturbation) / step, rtol=1e-6, atol=1e-9 * np.abs(derivative).max())


def test_a_ramp_refuses_brighter_fatter_and_says_why():
    from nlpsf.checks import InputError as Error
    from nlpsf.sim.scene import SceneModel

    ramps.check_scene(
        SceneModel(ipc=((0, 0.02, 0), (0.02, 0.92, 0.02), (0, 0.02, 0)), background_e=100.0, nl_coefficients=(1e-12,))
    )
    with pytest.raises(Error, match="brighter-fatter"):
        ramps.check_scene(SceneModel(bfe_coefficient=1e-7))


@pytest.fixture(scope="module")
def detector_scene():
    from nlpsf.sim import experiment
    from nlpsf.sim.scene import ROMAN_IPC_KERNEL, SceneModel

    model = SceneModel(ipc=ROMAN_IPC_KERNEL, ipc_label="roman", background_e=300.0, nl_coefficients=(2e-12,))
    config = experiment.SimulationConfig(realizations=6, scene=model, exptime_s=168.1)
    return config, experiment.prepare(config)


def _with_ramp(config, prepared, **changes):
    from nlpsf.sim import experiment

    other = experiment.SimulationConfig(**{**{k: getattr(config, k) for k in config.__dataclass_fields__}, **changes})
    return other, experiment.Scene(other, prepared.psf, prepared.offsets, prepared.stamps, prepared.reference, 0.0)


@pytest.mark.parametrize("method", ["monte_carlo", "linear"])
def test_a_one_read_ramp_in_a_detector_scene_is_the_final_frame(detector_scene, method):
    # One read at the end of the exposure: every factor c_n = 1, so IPC, background and the cubic NL
    # come out exactly as the final frame's detector chain computes them.
    from nlpsf.sim.experiment import simulate, slopes

    config, scene = detector_scene
    frame, frame_scene = _with_ramp(config, scene, method=method)
    ramp, ramp_scene = _with_ramp(config, scene, method=method, ramp=ramps.Ramp.uniform(1, 168.1))
    for magnitude in (18.3, 20.0):
        a = simulate(ramp, [magnitude], [BETA], scene=ramp_scene)[0]
        b = simulate(frame, [magnitude], [BETA], scene=frame_scene)[0]
        for metric in ("dR_over_R", "de1", "de2"):
            assert getattr(a, metric).mean == pytest.approx(getattr(b, metric).mean, rel=1e-9, abs=1e-15)
    a = slopes(ramp, [19.0], scene=ramp_scene)[0]
    b = slopes(frame, [19.0], scene=frame_scene)[0]
    for metric in ("dR_over_R", "de1", "de2"):
        assert a.bias[metric].mean == pytest.approx(b.bias[metric].mean, rel=1e-8)
        assert a.scatter[metric]["value"] == pytest.approx(b.scatter[metric]["value"], rel=1e-6)


def test_uniform_ols_ramp_with_ipc_and_background_is_the_final_frame_at_beta_eff(detector_scene):
    # Quadratic NL only, no resultant saturated: every NL term (star, sky, their cross term, IPC after)
    # carries the same c_2 = 1 + 1/N, so the ramp is the final frame at beta (1 + 1/N).
    from nlpsf.sim.experiment import simulate
    from nlpsf.sim.scene import ROMAN_IPC_KERNEL, SceneModel

    config, scene = detector_scene
    model = SceneModel(ipc=ROMAN_IPC_KERNEL, ipc_label="roman", background_e=300.0)
    n = 6
    frame, frame_scene = _with_ramp(config, scene, scene=model, method="linear")
    ramp, ramp_scene = _with_ramp(config, scene, scene=model, method="linear", ramp=ramps.Ramp.uniform(n, 168.1))
    a = simulate(ramp, [19.0], [BETA], scene=ramp_scene)[0]
    b = simulate(frame, [19.0], [BETA * (1 + 1 / n)], scene=frame_scene)[0]
    for metric in ("dR_over_R", "de1", "de2"):
        assert getattr(a, metric).mean == pytest.approx(getattr(b, metric).mean, rel=1e-9, abs=1e-15)


@pytest.mark.slow
def test_a_star_between_the_saturation_limits_matches_the_brute_force_image():
    # The whole chain at the metric level: every pixel of two H158 stamps read by read (brute_force),
    # the fitted images measured, against the simulator's answer at a magnitude where the core keeps
    # only some resultants (romancal's rules, romanisim-110: between its limit m = 15.12 and 17.73).
    from nlpsf.sim import experiment, moments
    from nlpsf.sim.experiment import SimulationConfig, simulate

    table = ramps.load_ma_table("romanisim-110")
    T = table.duration_s
    config = SimulationConfig(band="H158", realizations=2, exptime_s=T, ramp=ramps.Ramp(table))
    scene = experiment.prepare(config)
    magnitude = 16.5
    result = simulate(config, [magnitude], [BETA], scene=scene)[0]
    assert result.extras["ramp"]["fitted_on_fewer"] > 0 and result.extras["ramp"]["unusable"] == 0
    scale = float(config.electrons(magnitude)) * config.oversampling**2
    images = np.empty_like(scene.stamps)
    for index in np.ndindex(scene.stamps.shape):
        images[index] = brute_force(scale * scene.stamps[index], table, T, (BETA,), saturation="signal", single="unusable")[0]
    fitted = moments.fit(images / scale, config.moment_settings, start=scene.reference.parameters())
    d_r, d_e1, d_e2 = moments.differences(fitted, scene.reference)
    for got, expected in ((result.dR_over_R, d_r), (result.de1, d_e1), (result.de2, d_e2)):
        assert got.mean == pytest.approx(float(np.mean(expected)), rel=1e-6, abs=1e-12)
