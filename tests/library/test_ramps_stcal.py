"""``--ramp-fit optimal`` against stcal's own likelihood ramp fitter (romancal's), on the same noiseless resultants.

stcal is a test dependency (the ``pipeline`` extra, installed by scripts/test.sh); without it these tests
are skipped. Jump rejection is
off: stcal's ``fit_ramps`` is called directly with every resultant difference used (``likely_ramp_fit``
always runs its jump masking first, which at the full beta0 takes the NL curvature of bright cores for
cosmic-ray jumps).
"""

import numpy as np
import pytest

from nlpsf.sim import ramps

likely = pytest.importorskip("stcal.ramp_fitting.likely_fit", reason="stcal not installed (test dependency)")
classes = pytest.importorskip("stcal.ramp_fitting.likely_algo_classes")

BETA0 = 5e-7
READ_NOISE = 10.0
CHARGES = np.array([50.0, 800.0, 6e3, 2.5e4, 6e4, 1.05e5])


def _stcal_image(resultants, table, exptime, rate_guess):
    """stcal's likelihood slope [e-/s] x exposure, every difference used, gain 1 (e- in, e- out)."""
    readtimes = [np.array(r, dtype=np.float64) * table.frame_time_s for r in table.resultants]
    covar = classes.Covar(readtimes)
    diffs = (resultants[:, 1:] - resultants[:, :-1]).T / covar.delta_t[:, None]  # (ndiffs, pixels)
    n = resultants.shape[0]
    result = likely.fit_ramps(
        diffs,
        covar,
        np.ones(n),
        np.full(n, READ_NOISE),
        count_rate_guess=rate_guess,
        diffs2use=np.ones(diffs.shape, np.uint8),
    )
    return result.countrate * exptime


@pytest.mark.parametrize("name", ["romanisim-110", "C2A_IMG_HLWAS", "romanisim-109"])
@pytest.mark.parametrize("beta", [BETA0, 1e-2 * BETA0])
def test_optimal_fit_equals_stcals_likelihood_fit_at_the_same_rate(name, beta):
    # Both fits evaluate the covariance at a rate: nlpsf at the pixel's true (linear) rate. Given the
    # same rate, stcal's difference-based likelihood and nlpsf's GLS with a free intercept are the
    # same estimator: the bias (fitted - true) agrees to 1e-4 of itself.
    table = ramps.load_ma_table(name)
    T = table.duration_s
    ramp = ramps.Ramp(table, "optimal", READ_NOISE)
    resultants = ramps.resultant_means(CHARGES, ramp, T, ramps.polynomial_response((beta,)))
    ours = ramps.simulate_pixels(CHARGES, ramp, T, 1e9, (beta,))
    assert np.all(ours.usable == table.n_resultants)
    theirs = _stcal_image(resultants, table, T, CHARGES / T)
    bias = ours.image - CHARGES
    assert np.all(np.abs(theirs - ours.image) <= 1e-4 * np.abs(bias))


@pytest.mark.parametrize("name", ["romanisim-110", "C2A_IMG_HLWAS"])
def test_optimal_fit_equals_stcal_with_its_own_rate_at_residual_nl(name):
    # stcal estimates the rate from the data (the mean resultant difference), nlpsf takes the true one;
    # at a residual NL (beta ~ 1e-2 beta0, after the linearity correction) the two rates are close
    # enough that the biases still agree to 1e-4 of themselves.
    table = ramps.load_ma_table(name)
    T = table.duration_s
    ramp = ramps.Ramp(table, "optimal", READ_NOISE)
    beta = 1e-2 * BETA0
    resultants = ramps.resultant_means(CHARGES, ramp, T, ramps.polynomial_response((beta,)))
    readtimes = [np.array(r, dtype=np.float64) * table.frame_time_s for r in table.resultants]
    delta_t = classes.Covar(readtimes).delta_t
    guess = np.mean((resultants[:, 1:] - resultants[:, :-1]) / delta_t[None, :], axis=1)
    theirs = _stcal_image(resultants, table, T, guess)
    ours = ramps.simulate_pixels(CHARGES, ramp, T, 1e9, (beta,)).image
    assert np.all(np.abs(theirs - ours) <= 1e-4 * np.abs(ours - CHARGES))


def test_why_jump_rejection_is_off_stcal_takes_full_nl_curvature_for_jumps():
    # At the full beta0 the curvature of a bright pixel's ramp looks like cosmic-ray jumps to stcal's
    # jump masking (the first step of likely_ramp_fit); at a residual NL (after the linearity step) it does not.
    table = ramps.load_ma_table("romanisim-110")
    T = table.duration_s
    ramp = ramps.Ramp(table, "optimal", READ_NOISE)
    readtimes = [np.array(r, dtype=np.float64) * table.frame_time_s for r in table.resultants]
    covar = classes.Covar(readtimes)
    masked = {}
    for beta in (BETA0, 1e-2 * BETA0):
        R = ramps.resultant_means(CHARGES, ramp, T, ramps.polynomial_response((beta,)))
        diffs = (R[:, 1:] - R[:, :-1]).T / covar.delta_t[:, None]
        d2use, _ = likely.mask_jumps(
            diffs, covar, np.full(CHARGES.size, READ_NOISE), np.ones(CHARGES.size), diffs2use=np.ones(diffs.shape, np.uint8)
        )
        masked[beta] = (d2use == 0).sum(axis=0)
    assert masked[BETA0][-1] > 0  # the 1.05e5 e- pixel
    assert not np.any(masked[1e-2 * BETA0])
