"""The pipeline's linearity correction, applied per resultant, and the residual a calibration leaves.

romancal's linearity step hands each resultant of the data *as read* (the IPC-coupled mean of its reads'
signals, after the saturation flags) to stcal's ``linearity_correction``, whose classic path evaluates the
reference file's polynomial on it, F_c = c0 + c1 F + c2 F^2 + ... (docs/calibration.md). Call S(Q) the
detector's response (S = Q - b2 Q^2 - ... per read) and L its exact inverse, the correction a perfect
calibration applies. A calibration L_cal leaves the residual

    r(Q) = L_cal(S(Q)) - Q,

corrected signal minus true charge at charge Q, the curve a calibration team judges its work by. For any
resultant R, put Q* = L(R) (so S(Q*) = R): L_cal(R) = L(R) + r(L(R)) exactly. So the corrected resultant
is the perfectly corrected one, Q*_j, plus r(Q*_j); the fit is linear in the resultants,

    image_p = sum_j w_pj Q*_pj + sum_j w_pj r(Q*_pj),

and the residual enters the image *linearly*, through the measuring pixel's slope weights and evaluated
at each resultant's corrected level, whatever its shape. The first sum is not the linear image either:
L of a mean of reads is not the mean of L (the reads of a resultant differ), and L of an IPC-coupled
signal is not the coupled charge, so even a perfect calibration leaves the *baseline* sum_j w_pj
(Q*_pj - rate_p <tau>_j), of order b2 times the spread of a resultant's reads or IPC's mixing of the
neighbours' curvature. A calibration error is judged about that state.

:class:`CorrectedRamp` holds, per pixel, the corrected levels Q*_pj, the weights w_pj and the baseline;
:meth:`CorrectedRamp.response` turns any residual into its image. The quadratic residual of a
miscalibrated b2 is ``quadratic_residual``: r(Q) = -Delta_beta Q^2 (the residual's quadratic coefficient,
see :data:`BETA_RESIDUALS` for the exact inverse's difference and why the default takes this one).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

#: A residual: corrected signal minus true charge [e-] as a function of the charge [e-] (vectorised).
Residual = Callable[[np.ndarray], np.ndarray]

#: How a miscalibrated b2 shows as a residual. "quadratic": r(Q) = -Delta_beta Q^2, the residual's
#: quadratic coefficient (the calibration leaves -Delta_beta Q^2 in the corrected signal): the default's
#: precision. "inverse": the correction is the exact inverse of Q - (beta0 - Delta_beta) Q^2, whose
#: residual is -Delta_beta Q^2 / (1 - 2 beta0 Q) to first order (exact: :func:`beta_inverse_residual`),
#: larger by 2 beta0 Q (10 % at 1e5 e- for beta0 = 5e-7). docs/calibration.md derives both.
BETA_RESIDUALS: tuple[str, ...] = ("quadratic", "inverse")

#: Newton steps of the inverse of a polynomial response beyond b2 (quadratic convergence from the
#: quadratic's closed form; 6 reach the float64 floor for any response the scene allows).
_NEWTON_STEPS = 6


def inverse_excess(signal: np.ndarray, coefficients: Sequence[float]) -> np.ndarray:
    """L(S) - S, elementwise: the charge Q with Q - b2 Q^2 - b3 Q^3 - ... = S, less S [e-].

    Computed as a difference, never as L(S) - S of two large numbers: for the quadratic,
    L(S) - S = 4 b2 S^2 / (1 + sqrt(1 - 4 b2 S))^2 exactly (the rising branch, 1 - 2 b2 Q > 0); higher
    orders by Newton's method on d = Q - S from there. NaN where S is beyond the response's maximum
    (no charge gives that signal on the rising branch)."""
    S = np.asarray(signal, dtype=np.float64)
    coefficients = tuple(float(b) for b in coefficients)
    b2 = coefficients[0] if coefficients else 0.0
    with np.errstate(invalid="ignore"):
        root = np.sqrt(1.0 - 4.0 * b2 * S)
        excess = 4.0 * b2 * S * S / (1.0 + root) ** 2
    if len(coefficients) <= 1 or not any(coefficients[1:]):
        return excess
    d = np.where(np.isfinite(excess), excess, 0.0)
    for _ in range(_NEWTON_STEPS):
        Q = S + d
        f = d.copy()  # Q - sum b_n Q^n - S = d - sum b_n Q^n
        slope = np.ones_like(Q)  # d/dd of f
        power = Q
        for n, b in enumerate(coefficients, start=2):
            previous = power
            power = power * Q
            f -= b * power
            slope -= n * b * previous
        d = d - f / slope
    ok = np.isfinite(d) & (_response_slope(S + d, coefficients) > 0)
    return np.where(ok, d, np.nan)


def _response_slope(Q: np.ndarray, coefficients: Sequence[float]) -> np.ndarray:
    out = np.ones_like(Q)
    for n, b in enumerate(coefficients, start=2):
        out -= n * b * Q ** (n - 1)
    return out


def quadratic_residual(delta_beta: float = 1.0) -> Residual:
    """r(Q) = -Delta_beta Q^2: the calibration's quadratic coefficient off by Delta_beta (paper sign)."""
    return lambda q: -delta_beta * np.asarray(q, dtype=np.float64) ** 2


def beta_inverse_residual(beta0: float, delta_beta: float) -> Residual:
    """The residual of a correction that is the exact inverse of Q - (beta0 - Delta_beta) Q^2 on a
    detector S = Q - beta0 Q^2: r(Q) = L_cal(S(Q)) - Q, exactly (to first order -Delta_beta Q^2 / (1 - 2 beta0 Q))."""
    calibrated = beta0 - delta_beta

    def residual(q):
        q = np.asarray(q, dtype=np.float64)
        signal = q - beta0 * q * q
        # L_cal(S) - Q = (S + excess_cal(S)) - Q = excess_cal(S) - beta0 Q^2
        return inverse_excess(signal, (calibrated,)) - beta0 * q * q

    return residual


def polynomial_residual(coefficients: Sequence[float]) -> Residual:
    """r(Q) = sum_k a_k Q^k for ``coefficients`` (a_0, a_1, ...) [e-, Q in e-]."""
    coefficients = np.asarray(coefficients, dtype=np.float64)
    return lambda q: np.polynomial.polynomial.polyval(np.asarray(q, dtype=np.float64), coefficients)


@dataclass(frozen=True)
class CorrectedRamp:
    """The corrected resultants of a set of pixels (flat, P of them) and the fit's weights on them.

    ``level`` (P, K): Q*_pj = L(R_pj), each resultant as a perfect calibration corrects it [e-];
    ``weights`` (P, K): the slope weights of the measuring pixel (zero beyond its usable resultants;
    the image is sum_j w_pj x_j); ``baseline`` (P,): the corrected image less the linear one with a
    perfect calibration (plus the residual terms it was built with); ``index``: where the pixels sit
    in an array of ``shape`` (flat indices; None: every pixel, in order)."""

    level: np.ndarray
    weights: np.ndarray
    baseline: np.ndarray
    shape: tuple[int, ...]
    index: np.ndarray | None = None

    def response(self, residual: Residual) -> np.ndarray:
        """sum_j w_pj r(Q*_pj) per pixel (P,): the image a residual adds [e-]. Saturated resultants
        carry zero weight, so the residual is never evaluated where the fit does not look (their
        level is set to 0)."""
        values = np.asarray(residual(self.level), dtype=np.float64)
        return np.einsum("pk,pk->p", self.weights, values)

    def image(self, values: np.ndarray) -> np.ndarray:
        """Per-pixel ``values`` (P,) placed in an array of ``shape`` (zero at the pixels not held)."""
        if self.index is None:
            return np.asarray(values).reshape(self.shape)
        out = np.zeros(int(np.prod(self.shape)))
        out[self.index] = values
        return out.reshape(self.shape)

    def residual_image(self, residual: Residual) -> np.ndarray:
        return self.image(self.response(residual))

    @property
    def baseline_image(self) -> np.ndarray:
        return self.image(self.baseline)


def correct(
    rate: np.ndarray,
    powers: dict[int, np.ndarray],
    raw: Sequence[float],
    mean_powers: np.ndarray,
    weights: np.ndarray,
    shape: tuple[int, ...],
    index: np.ndarray | None = None,
    residual_terms: Sequence[float] = (),
) -> CorrectedRamp:
    """Correct P pixels' resultants with the detector's exact inverse.

    ``rate`` (P,): the measured linear charge over the exposure (IPC(Q) with IPC after the NL);
    ``powers[n]`` (P,): the measured n-th power (IPC(Q^n) after, Q'^n with IPC before) for n = 2 .. of
    the raw response ``raw`` = (b2, b3, ...); ``mean_powers`` (1 + len(raw), K): <tau^n>_j for n = 1, 2, ...
    (``MATable.mean_powers``; a final frame is one resultant at tau = 1). Resultant j of pixel p reads
    R_pj = rate_p <tau>_j - sum_n b_n powers_n,p <tau^n>_j (exact: IPC is linear, the NL a polynomial).
    ``residual_terms`` (b3, b4, ...): a residual -sum_m b_m Q^m the correction leaves, in the baseline.
    """
    raw = tuple(float(b) for b in raw)
    rate = np.asarray(rate, dtype=np.float64)
    nl = np.zeros((rate.size, mean_powers.shape[1]))
    for n, b in enumerate(raw, start=2):
        if b != 0:
            nl -= b * np.multiply.outer(np.asarray(powers[n], dtype=np.float64), mean_powers[n - 1])
    linear = np.multiply.outer(rate, mean_powers[0])
    signal = linear + nl
    excess = inverse_excess(signal, raw)
    # Saturated resultants have no weight: keep their level finite (the residual is never needed there).
    dead = weights == 0
    excess = np.where(dead, 0.0, excess)
    level = np.where(dead, 0.0, signal + excess)
    delta = excess + nl  # Q* - rate <tau>, term by term
    if any(residual_terms):
        delta = delta - sum(b * level**m for m, b in enumerate(residual_terms, start=3) if b != 0)
    baseline = np.einsum("pk,pk->p", weights, delta)
    return CorrectedRamp(level, weights, baseline, tuple(shape), index)
