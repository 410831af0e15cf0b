"""The ramp as the pipeline sees it: an independent read-by-read implementation, romancal's choices.

``brute_force`` below is written from the physics, pixel by pixel and read by read, sharing no code
with ``nlpsf.ramps``: charge accumulates linearly, every read reports S(Q), resultants are means of
reads, saturated resultants are flagged (either rule), and the slope is fitted by an explicit
least-squares solve (numpy's lstsq for OLS; the generalised solve with the covariance built read by
read for the optimal fit). The romancal saturation rule is checked against stcal's own
``flag_saturated_pixels`` where stcal is installed (a test dependency; skipped without it).
"""

import numpy as np
import pytest

from nlpsf import ramps

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
