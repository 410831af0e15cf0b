"""The adaptive-moment fit's kernels (``nlpsf.sim.moments``): the weight window and the Gaussian
weights, the raw moments of order <= 4, the residual of the five equations and its analytic
Jacobian, HSM's bounded fixed-point update and the Newton step. The fit, the perturbed fit and the
pixel response share them; ``moments`` alone uses them.
"""

from __future__ import annotations

import contextlib
import math

import numpy as np


def coordinates(n: int) -> np.ndarray:
    return np.arange(n) - (n - 1) / 2.0


def weight_window(n: int, params: np.ndarray, cut: float) -> tuple[int, int, int, int]:
    """Smallest row/column range holding every pixel with rho^2 <= cut for all fits in a batch.

    The weight is a Gaussian a few fine pixels wide, so this is a small core of the stamp; it is
    exact (no pixel with non-zero weight is left out), not an approximation.
    """
    if not math.isfinite(cut):
        return 0, n, 0, n
    centre = (n - 1) / 2.0
    half_x = np.sqrt(cut * np.maximum(params[:, 2], 0.0))
    half_y = np.sqrt(cut * np.maximum(params[:, 4], 0.0))
    c0 = math.floor(np.min(params[:, 0] - half_x) + centre)
    c1 = math.ceil(np.max(params[:, 0] + half_x) + centre) + 1
    r0 = math.floor(np.min(params[:, 1] - half_y) + centre)
    r1 = math.ceil(np.max(params[:, 1] + half_y) + centre) + 1
    return max(r0, 0), min(max(r1, 0), n), max(c0, 0), min(max(c1, 0), n)


def gaussian_weights(
    n: int, params: np.ndarray, cut: float, window: tuple[int, int, int, int] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Weights (B, rows, cols) on ``window`` and the offsets dx (B, cols), dy (B, rows), M^-1."""
    r0, r1, c0, c1 = window if window is not None else (0, n, 0, n)
    coords = coordinates(n)
    x0, y0, mxx, mxy, myy = params.T
    det = mxx * myy - mxy**2
    inverse = np.stack([myy / det, -mxy / det, mxx / det], axis=-1)
    dx = coords[None, c0:c1] - x0[:, None]
    dy = coords[None, r0:r1] - y0[:, None]
    a, b, c = inverse.T
    # rho^2 = a dx^2 + 2 b dx dy + c dy^2, built from the two separable terms and one outer
    # product, in place: this runs at every iteration of every fit.
    rho2 = (2.0 * b[:, None] * dy)[:, :, None] * dx[:, None, :]
    rho2 += (a[:, None] * dx * dx)[:, None, :]
    rho2 += (c[:, None] * dy * dy)[:, :, None]
    weight = np.exp(-0.5 * rho2)
    if math.isfinite(cut):
        weight[rho2 > cut] = 0.0
    return weight, dx, dy, inverse


def powers(d: np.ndarray, order: int) -> np.ndarray:
    """d^0 .. d^order stacked on a last axis, by repeated products: ``d ** np.arange(K)`` goes
    through the general float power and costs 30x more, which made it the simulator's hot spot."""
    out = np.empty((*d.shape, order + 1))
    out[..., 0] = 1.0
    for k in range(1, order + 1):
        np.multiply(out[..., k - 1], d, out=out[..., k])
    return out


def raw_moments(weighted: np.ndarray, dx: np.ndarray, dy: np.ndarray, order: int) -> np.ndarray:
    """S[b, i, j] = sum weighted * dx^i * dy^j for i + j <= order (returned as a full square)."""
    px = powers(dx, order)  # (B, n, K)
    py = powers(dy, order)
    over_x = weighted @ px  # (B, n_y, K): sums over x
    return np.swapaxes(np.swapaxes(py, 1, 2) @ over_x, 1, 2)  # (B, K_x, K_y)


# The five equations, as (dx power, dy power, index of the M element they equal twice, or -1).
EQUATIONS = ((1, 0, -1), (0, 1, -1), (2, 0, 2), (1, 1, 3), (0, 2, 4))


def equation_residual(S: np.ndarray, params: np.ndarray) -> np.ndarray:
    """F = (S[g] / A - c_g) for the five equations; zero at the adaptive-moment solution."""
    amplitude = S[:, 0, 0]
    out = np.empty((S.shape[0], 5))
    for k, (i, j, m_index) in enumerate(EQUATIONS):
        target = 0.0 if m_index < 0 else 0.5 * params[:, m_index]
        out[:, k] = S[:, i, j] / amplitude - target
    return out


# Index tables for the Jacobian. Row g of F is the moment S[i_g, j_g] (``EQUATIONS``); column p
# differentiates the weight, -1/2 d(rho^2)/dp, a polynomial in (dx, dy) with the monomials below:
# first order for the centroid (p = x0, y0), second order for the matrix (p = Mxx, Mxy, Myy).
ROW_I = np.array([e[0] for e in EQUATIONS])
ROW_J = np.array([e[1] for e in EQUATIONS])
FIRST = ((1, 0), (0, 1))
SECOND = ((2, 0), (1, 1), (0, 2))


def weight_derivative_coefficients(inverse: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """-1/2 d(rho^2)/dp as coefficients of the monomials ``FIRST`` (p = x0, y0), shape (B, 2, 2),
    and ``SECOND`` (p = Mxx, Mxy, Myy), shape (B, 3, 3); M^-1 = [[a, b], [b, c]]."""
    a, b, c = inverse[:, 0], inverse[:, 1], inverse[:, 2]
    first = np.stack([np.stack([a, b], -1), np.stack([b, c], -1)], 1)
    second = np.stack(
        [
            np.stack([0.5 * a * a, a * b, 0.5 * b * b], -1),
            np.stack([a * b, a * c + b * b, b * c], -1),
            np.stack([0.5 * b * b, b * c, 0.5 * c * c], -1),
        ],
        1,
    )
    return first, second


def jacobian(S: np.ndarray, inverse: np.ndarray) -> np.ndarray:
    """dF/d(x0, y0, Mxx, Mxy, Myy), shape (B, 5, 5), from weighted moments up to order 4.

    dF_g/dp = <g h_p> - <g><h_p> (h_p = -1/2 d(rho^2)/dp), less d<g>/dp where g itself moves with
    the centroid, less 1/2 where g's target is the element p of M. Vectorised over the 5 x 5
    entries: the per-entry Python loop cost more than the arithmetic.
    """
    amplitude = S[:, 0, 0, None]
    first, second = weight_derivative_coefficients(inverse)
    jac = np.empty((S.shape[0], 5, 5))
    mean_g = S[:, ROW_I, ROW_J] / amplitude  # (B, 5)
    for cols, monomials, coefficients in ((slice(0, 2), FIRST, first), (slice(2, 5), SECOND, second)):
        pi = np.array([m[0] for m in monomials])
        pj = np.array([m[1] for m in monomials])
        s_gh = S[:, ROW_I[:, None] + pi, ROW_J[:, None] + pj]  # (B, 5 rows, terms)
        s_h = S[:, pi, pj]  # (B, terms)
        gh = np.einsum("brt,bct->brc", s_gh, coefficients)
        h = np.einsum("bt,bct->bc", s_h, coefficients)
        jac[:, :, cols] = gh / amplitude[:, :, None] - mean_g[:, :, None] * (h / amplitude)[:, None, :]
    # g is a monomial in dx = x - x0, dy = y - y0: d g / d x0 = -i dx^(i-1) dy^j, likewise y0.
    for row, (i, j, m_index) in enumerate(EQUATIONS):
        if i > 0:
            jac[:, row, 0] -= i * S[:, i - 1, j] / amplitude[:, 0]
        if j > 0:
            jac[:, row, 1] -= j * S[:, i, j - 1] / amplitude[:, 0]
        if m_index >= 0:
            jac[:, row, m_index] -= 0.5
    return jac


def step_size(step: np.ndarray, params: np.ndarray) -> np.ndarray:
    trace = params[:, 2] + params[:, 4]
    sigma = np.sqrt(np.maximum(trace, 0.0) / 2.0)
    centroid = np.abs(step[:, :2]) / sigma[:, None]
    matrix = np.abs(step[:, 2:]) / trace[:, None]
    return np.max(np.concatenate([centroid, matrix], axis=1), axis=1)


def positive_definite(params: np.ndarray) -> np.ndarray:
    return (params[:, 2] > 0) & (params[:, 4] > 0) & (params[:, 2] * params[:, 4] - params[:, 3] ** 2 > 0)


def hsm_update(S: np.ndarray, params: np.ndarray, bound: float = 0.25) -> np.ndarray:
    """GalSim's bounded fixed-point step (robust from a cold start)."""
    amplitude = S[:, 0, 0]
    mxx, mxy, myy = params[:, 2], params[:, 3], params[:, 4]
    two_psi = np.arctan2(2 * mxy, mxx - myy)
    semi_a2 = 0.5 * ((mxx + myy) + (mxx - myy) * np.cos(two_psi)) + mxy * np.sin(two_psi)
    semi_b2 = mxx + myy - semi_a2
    shift_scale = np.sqrt(np.maximum(semi_b2, 1e-300))
    d = np.empty_like(params)
    d[:, 0] = 2.0 * S[:, 1, 0] / (amplitude * shift_scale)
    d[:, 1] = 2.0 * S[:, 0, 1] / (amplitude * shift_scale)
    d[:, 2] = 4.0 * (S[:, 2, 0] / amplitude - 0.5 * mxx) / semi_b2
    d[:, 3] = 4.0 * (S[:, 1, 1] / amplitude - 0.5 * mxy) / semi_b2
    d[:, 4] = 4.0 * (S[:, 0, 2] / amplitude - 0.5 * myy) / semi_b2
    d = np.clip(d, -bound, bound)
    new = params.copy()
    new[:, 0] += d[:, 0] * shift_scale
    new[:, 1] += d[:, 1] * shift_scale
    new[:, 2:] += d[:, 2:] * semi_b2[:, None]
    return new


def evaluate_moments(images: np.ndarray, index: np.ndarray, params: np.ndarray, cut: float, order: int):
    """Weighted moments of ``images[index]`` at ``params``, touching only the weight's core."""
    window = weight_window(images.shape[-1], params, cut)
    r0, r1, c0, c1 = window
    weight, dx, dy, inverse = gaussian_weights(images.shape[-1], params, cut, window)
    S = raw_moments(weight * images[index, r0:r1, c0:c1], dx, dy, order)
    return S, inverse


def newton_step(jac: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """-J^-1 F for each item; a singular Jacobian gives NaN for that item only."""
    try:
        return -np.linalg.solve(jac, residual[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.full(residual.shape, np.nan)
        for k in range(jac.shape[0]):
            with contextlib.suppress(np.linalg.LinAlgError):
                out[k] = -np.linalg.solve(jac[k], residual[k])
        return out
