"""Detector nonlinearity and its validity limits.

The paper's model (its Eq. 1) is the quadratic S(Q) = Q - beta Q^2 with beta > 0 (charge Q in
electrons, S what the detector reports). GalSim and romanisim write the same thing as
S = Q + beta' Q^2 with beta' = -6e-7 for Roman; ``to_paper_beta`` converts, and every result says
which convention its beta is in.

Validity: the quadratic stops being monotonic where dS/dQ = 1 - 2 beta Q <= 0, and a pixel that
holds more than the full well is saturated; either, in pixels that carry weight in the moments,
makes a result meaningless, so the experiment flags it in plain words.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from nlpsf import defaults
from nlpsf.checks import InputError, check_number, shown

BETA_CONVENTIONS = defaults.BETA_CONVENTIONS
#: Beta values a request may give, in either convention, in 1/e-.
MAX_ABS_BETA = defaults.MAX_ABS_BETA


#: The sign of the paper's beta in each convention, and each convention's law.
_SIGN = {"paper": 1.0, "galsim": -1.0}
_LAW = {"paper": "S = Q - beta Q^2 (paper)", "galsim": "S = Q + beta Q^2 (GalSim/romanisim)"}


def to_paper_beta(beta: float, convention: str = "paper") -> float:
    """The paper's beta (S = Q - beta Q^2) for a value given in ``convention`` (and, the sign being
    its own inverse, a paper beta stated in ``convention``)."""
    if convention not in BETA_CONVENTIONS:
        raise InputError("beta_convention", f"must be one of {', '.join(BETA_CONVENTIONS)}, got {shown(convention)}")
    value = check_number(beta, "beta", -MAX_ABS_BETA, MAX_ABS_BETA)
    return value if _SIGN[convention] > 0 else -value


def describe(convention: str) -> str:
    return _LAW[convention]


def nonlinearity_perturbation(charge: np.ndarray, beta) -> np.ndarray:
    """The change S - Q = -beta Q^2 (``beta`` a scalar or an array of per-pixel values)."""
    return -np.asarray(beta, dtype=np.float64) * charge * charge


def apply_nonlinearity(charge: np.ndarray, beta) -> np.ndarray:
    """S = Q - beta Q^2 with the paper's sign convention."""
    return charge + nonlinearity_perturbation(charge, beta)


def draw_pixel_betas(rng: np.random.Generator, beta0: float, sigma_beta: float, shape: tuple[int, ...]) -> np.ndarray:
    """Per-pixel beta ~ N(beta0, sigma_beta^2) (paper section 4.2)."""
    return beta0 + sigma_beta * rng.standard_normal(shape)


def polynomial_perturbation(charge: np.ndarray, beta, higher: tuple[float, ...] = ()) -> np.ndarray:
    """S - Q for the polynomial response S = Q - b2 Q^2 - b3 Q^3 - ... (paper sign convention).

    ``beta`` is b2 (a scalar or per-pixel values: the scatter option applies to it) and ``higher``
    holds (b3, b4, ...). Computed term by term, never as S - Q, so a tiny NL keeps full relative
    precision. GalSim's convention (S = Q + b Q^2 + ...) is every coefficient negated.
    """
    out = nonlinearity_perturbation(charge, beta)
    power = charge * charge
    for coefficient in higher:
        power = power * charge
        if coefficient != 0.0:
            out = out - coefficient * power
    return out


def coefficients_perturbation(charge: np.ndarray, coefficients: Sequence[float]) -> np.ndarray:
    """S - Q = -(b2 Q^2 + b3 Q^3 + ...) for ``coefficients`` = (b2, b3, ...) (empty: no NL); the
    form the ramp readout uses, computed by :func:`polynomial_perturbation`."""
    if len(coefficients) == 0:
        return np.zeros_like(charge, dtype=np.float64)
    return polynomial_perturbation(charge, coefficients[0], tuple(coefficients[1:]))


def apply_polynomial_nonlinearity(charge: np.ndarray, beta, higher: tuple[float, ...] = ()) -> np.ndarray:
    """S = Q - b2 Q^2 - b3 Q^3 - ... (``beta`` = b2, ``higher`` = (b3, b4, ...))."""
    return charge + polynomial_perturbation(charge, beta, higher)


def response_slope(charge: np.ndarray, beta, higher: tuple[float, ...] = ()) -> np.ndarray:
    """dS/dQ = 1 - 2 b2 Q - 3 b3 Q^2 - ...: where it reaches zero the response stops being monotonic."""
    out = 1.0 - 2.0 * np.asarray(beta, dtype=np.float64) * charge
    power = charge
    for k, coefficient in enumerate(higher, start=3):
        power = power * charge
        out = out - k * coefficient * power
    return out
