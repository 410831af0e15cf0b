"""Up-the-ramp exposures: MultiAccum (MA) tables, reads, resultants and the slope fit.

Roman's WFI does not deliver a final frame. Every pixel is read non-destructively every frame time
(3.04 s); an MA table groups the reads into *resultants* (the mean of their reads, all that is sent
to the ground), and the ground pipeline fits a slope to the resultants, dropping those that passed
saturation. This module turns a pixel's final-frame charge into the image the moments then see:
the fitted slope times the exposure time.

The package, one module per part (every public name is re-exported here, so ``ramps.X`` reads as
it always did):

- ``tables``: MA tables (``MATable``, ``load_ma_table``, the shipped ones);
- ``config``: the ramp (``Ramp``: table, fit, rules), the response a read reports, which resultants
  a pixel keeps (the saturation rules), and ``build``, the one builder;
- ``fits``: OLS / optimal slope weights, the per-pixel ramp factors, the read-by-read reference;
- ``in_scene``: ramps with IPC, a background and a polynomial NL (``scene_factors``,
  ``CoupledPowers``), and what a ramp still refuses;
- ``correction``: the pipeline's linearity correction applied per resultant and the residual a
  calibration leaves (``CorrectedRamp``; built in a scene by ``corrected_coupled`` / ``corrected_images``).

Pixel physics (noiseless, as the rest of the simulator):

- charge grows linearly in time, Q(t) = (q + b) t / T with q the pixel's final-frame charge from
  the star, b an optional background/dark charge over the same exposure T;
- the detector reports S(Q) at every read; the response is a small swappable function, by default
  the polynomial S = Q - b2 Q^2 - b3 Q^3 - ... with ``coefficients = (b2, b3, ...)`` (b2 = beta, the
  paper's quadratic, is the default case);
- resultant j is the mean of S over its reads;
- a resultant is saturated when the charge at its last read exceeds the full well; the pixel's
  saturated resultants are dropped (they follow the unsaturated ones, so the usable ones are always
  the first k). A pixel saturated already in its first resultant is *unusable*: it is flagged, and
  its value is the first resultant's (an unphysical number, never a silent one);
- slope fit, in units of the exposure (time tau = t / T, slope in e- per exposure = the image):
  with k >= 2 usable resultants a straight line with a free intercept (the reset level is unknown),
  either ``ols`` (ordinary least squares, all resultants weighted equally) or ``optimal``
  (generalised least squares with the exact covariance of the resultants for read noise plus
  Poisson noise, below); with k = 1 the slope is S_1 / tau_1 (the intercept cannot be fitted, the
  reset level is taken as zero, as romancal does for single-resultant ramps).

The fit is linear in the resultants: image = sum_j w_j R_j with weights w_j that depend only on the
table, the number of usable resultants and (for ``optimal``) the pixel's charge rate, not on beta.
So for the NL written as a sum of powers, R_j = tau_j-mean of S, and

    image - (q + b) = -sum_n b_n (q + b)^n c_n,     c_n = sum_j w_j <tau^n>_j,

a per-pixel "ramp factor" c_n per power. ``order_factors`` computes c_n for every pixel in one
vectorised pass; ``simulate_pixels`` evaluates every read explicitly (the reference the tests
compare the factors with). For the quadratic NL d(image)/d(beta) = -(q + b)^2 c_2 exactly: the
linear-response method uses that.

Quadratic NL, OLS, all resultants usable: c_2 is one number for the whole stamp, so the ramp image
is the final-frame image at beta_eff = c_2 beta. For N uniform reads tau_i = i/N (one read per
resultant), the OLS slope of tau^2 against tau is cov(i^2, i) / var(i) / N = (N + 1) / N (sums over
i = 1..N: cov = (N+1)^2 (N-1)/12, var = (N+1)(N-1)/12), hence beta_eff = beta (1 + 1/N) for N >= 2.
(N = 1 is the one-resultant rule, S/tau = the final frame: beta_eff = beta.)

Optimal weighting: the best linear unbiased slope is the generalised least-squares fit
w = e_slope^T (X^T C^-1 X)^-1 X^T C^-1 with X = [1, <tau>_j] and the resultant covariance
C_ij = sigma_read^2 / n_i delta_ij + (q + b) P_ij, P_ij = (1 / n_i n_j) sum_{a in i, b in j} min(tau_a,
tau_b) (Poisson: the counts are a cumulative process). This is the estimator that Casertano et al.
(2022, Roman-STScI-000394, "Determining the best-fitting slope and its uncertainty for up-the-ramp
sampled images with unevenly distributed resultants") approximate for the romancal ramp fit and that
Brandt (2024, PASP 136, 045004, "Optimal fitting and debiasing for detectors read out up-the-ramp")
computes exactly from the same covariance. The ground pipeline evaluates the covariance at a rate
estimated from the data; this noiseless simulator evaluates it at the pixel's true (linear) charge,
so the weights do not depend on beta. C = D^1/2 (sigma^2 I + q M) D^1/2 with D = diag(1/n_j) and
M = D^-1/2 P D^-1/2: one eigendecomposition of M per number of usable resultants diagonalises the
covariance of every pixel at once, and each pixel's weights cost O(k) instead of a k x k solve.
"""

from . import correction
from .config import (
    DEFAULT_READ_NOISE_E,
    RAMP_FITS,
    SATURATION_RULES,
    SINGLE_RESULTANT_RULES,
    Ramp,
    build,
    polynomial_perturbation,
    polynomial_response,
    resultant_means,
    signal_usable,
    usable_resultants,
)
from .correction import CorrectedRamp
from .fits import RampImage, nonlinearity_perturbation, order_factors, simulate_pixels, slope_weights, usage_summary
from .in_scene import (
    RAMP_REFUSES,
    CoupledPowers,
    SceneRamp,
    check_scene,
    corrected_coupled,
    corrected_images,
    scene_factors,
    scene_factors_coupled,
    scene_perturbation,
)
from .tables import MAX_READS, ROMAN_FRAME_TIME_S, MATable, load_ma_table, shipped_table_dir, shipped_table_names

__all__ = [
    "DEFAULT_READ_NOISE_E",
    "MAX_READS",
    "RAMP_FITS",
    "RAMP_REFUSES",
    "ROMAN_FRAME_TIME_S",
    "SATURATION_RULES",
    "SINGLE_RESULTANT_RULES",
    "CorrectedRamp",
    "CoupledPowers",
    "MATable",
    "Ramp",
    "RampImage",
    "SceneRamp",
    "build",
    "check_scene",
    "corrected_coupled",
    "corrected_images",
    "correction",
    "load_ma_table",
    "nonlinearity_perturbation",
    "order_factors",
    "polynomial_perturbation",
    "polynomial_response",
    "resultant_means",
    "scene_factors",
    "scene_factors_coupled",
    "scene_perturbation",
    "shipped_table_dir",
    "shipped_table_names",
    "signal_usable",
    "simulate_pixels",
    "slope_weights",
    "usable_resultants",
    "usage_summary",
]
