"""The slope fit: OLS and optimal (generalised least squares) weights, the per-pixel ramp factors
c_n = w . <tau^n>, and the explicit read-by-read reference (``simulate_pixels``)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .config import Ramp, polynomial_response, resultant_means, usable_resultants
from .tables import MATable, _ols_factors, _resultant_fractions

#: Pixels per block in the per-pixel weight computation (bounds memory for long tables).
_BLOCK = 1 << 16
#: Pixels per block of the optimal factors: a block's (pixels x resultants) weights stay in cache
#: between the passes over them, which halves their cost against 1 << 16 (the same numbers: every
#: pixel's sums are its own row of one matrix product).
_FACTOR_BLOCK = 1 << 12


def _ols_row(tau: np.ndarray, k: int) -> np.ndarray:
    """OLS slope weights on the first k resultants (zeros after); k = 1: the reset is the intercept."""
    out = np.zeros(tau.size)
    if k == 1:
        out[0] = 1.0 / tau[0]
    else:
        centred = tau[:k] - tau[:k].mean()
        out[:k] = centred / np.sum(centred**2)
    return out


@dataclass(frozen=True, eq=False)
class _Covariance:
    """Per prefix length k: eigen-decomposition that diagonalises every pixel's resultant covariance."""

    table: MATable
    exptime_s: float

    @cached_property
    def poisson(self) -> np.ndarray:
        """P_ij = (1 / n_i n_j) sum_{a in i, b in j} min(tau_a, tau_b)."""
        tau = self.table.read_fractions(self.exptime_s)
        sizes = [len(r) for r in self.table.resultants]
        starts = np.concatenate([[0], np.cumsum(sizes)])
        K = len(sizes)
        mean = _resultant_fractions(self.table, self.exptime_s)
        out = np.empty((K, K))
        for i in range(K):
            t = tau[starts[i] : starts[i + 1]]
            n = t.size
            # sorted reads: sum_{a,b} min = sum_a t_a (2 (n - 1 - a) + 1)
            out[i, i] = float(np.sum(t * (2 * (n - 1 - np.arange(n)) + 1))) / n**2
            out[i, i + 1 :] = mean[i]  # reads of i all precede those of j > i
            out[i + 1 :, i] = mean[i]
        return out

    def prefix(self, k: int):
        """(lambda (k,), U (k, k), Xt (k, 2)) for the first k resultants."""
        n = np.array([len(r) for r in self.table.resultants[:k]], dtype=np.float64)
        root = np.sqrt(n)
        M = self.poisson[:k, :k] * root[:, None] * root[None, :]  # D^-1/2 P D^-1/2 with D = diag(1/n)
        lam, V = np.linalg.eigh(M)
        U = V.T * root[None, :]  # V^T D^-1/2
        X = np.stack([np.ones(k), _resultant_fractions(self.table, self.exptime_s)[:k]], axis=1)
        return np.clip(lam, 0.0, None), U, U @ X


def _optimal_coefficients(total: np.ndarray, read_variance: float, prefix) -> np.ndarray:
    """h (P, k): the slope weights in the eigenbasis, w = h @ U."""
    lam, _U, Xt = prefix
    g = 1.0 / (read_variance + total[:, None] * lam[None, :])  # (P, k)
    a00 = g @ (Xt[:, 0] ** 2)
    a01 = g @ (Xt[:, 0] * Xt[:, 1])
    a11 = g @ (Xt[:, 1] ** 2)
    det = a00 * a11 - a01**2
    return g * (a00[:, None] * Xt[None, :, 1] - a01[:, None] * Xt[None, :, 0]) / det[:, None]


def _optimal_groups(flat_total: np.ndarray, flat_k: np.ndarray, ramp: Ramp, exptime_s: float):
    """(pixel indices, k, h, U) blocks of pixels with k >= 2 usable resultants."""
    cov = _Covariance(ramp.table, exptime_s)
    for k in np.unique(flat_k[flat_k > 1]):
        prefix = cov.prefix(int(k))
        where = np.flatnonzero(flat_k == k)
        for s in range(0, where.size, _BLOCK):
            pick = where[s : s + _BLOCK]
            yield pick, int(k), _optimal_coefficients(flat_total[pick], ramp.read_noise_e**2, prefix), prefix[1]


def _optimal_factors(out: np.ndarray, flat_total: np.ndarray, flat_k: np.ndarray, ramp: Ramp, exptime_s: float, powers):
    """c_n = w . <tau^n> of the pixels with k >= 2 usable resultants, into ``out`` (orders, P).

    With w = h U and h_i = g_i (a00 X1_i - a01 X0_i) / det (``_optimal_coefficients``), the factor is
    c_n = (a00 (g . X1 Y_n) - a01 (g . X0 Y_n)) / det with Y = U <tau^n>: one matrix product of g
    (P, k) with the k x (3 + 2 orders) columns below gives a00, a01, a11 and both sums, so neither
    h nor the weights are formed (the same numbers to rounding, ~3.5 x fewer passes over P x k)."""
    cov = _Covariance(ramp.table, exptime_s)
    variance = ramp.read_noise_e**2
    n_orders = powers.shape[0]
    counts = np.bincount(flat_k, minlength=3)
    for k in np.flatnonzero(counts[2:]) + 2:
        lam, U, Xt = cov.prefix(int(k))
        Y = U @ powers[:, : int(k)].T  # (k, orders)
        columns = np.column_stack([Xt[:, 0] ** 2, Xt[:, 0] * Xt[:, 1], Xt[:, 1] ** 2, Xt[:, 1:2] * Y, Xt[:, 0:1] * Y])
        # Every pixel on the same k (no resultant saturated anywhere): contiguous blocks, no gather.
        size = flat_k.size if counts[k] == flat_k.size else int(counts[k])
        where = None if counts[k] == flat_k.size else np.flatnonzero(flat_k == k)
        for s in range(0, size, _FACTOR_BLOCK):
            pick = slice(s, s + _FACTOR_BLOCK) if where is None else where[s : s + _FACTOR_BLOCK]
            g = np.multiply.outer(flat_total[pick], lam)
            g += variance
            np.reciprocal(g, out=g)
            sums = g @ columns
            a00, a01, a11 = sums[:, 0], sums[:, 1], sums[:, 2]
            det = a00 * a11 - a01**2
            for n in range(n_orders):
                out[n, pick] = (a00 * sums[:, 3 + n] - a01 * sums[:, 3 + n_orders + n]) / det


def slope_weights(total_charge: np.ndarray, usable: np.ndarray, ramp: Ramp, exptime_s: float) -> np.ndarray:
    """Per-pixel weights (..., K) on the resultants: image = sum_j w_j R_j (e- per exposure).

    Unusable pixels (k = 0) get the one-resultant weights (their value is flagged, not dropped)."""
    K = ramp.table.n_resultants
    k_eff = np.maximum(usable, 1)
    tau = _resultant_fractions(ramp.table, exptime_s)
    flat_total = np.asarray(total_charge, dtype=np.float64).ravel()
    flat_k = k_eff.ravel()
    out = np.zeros((flat_total.size, K))
    if ramp.fit == "ols":
        for k in np.unique(flat_k):
            out[flat_k == k] = _ols_row(tau, int(k))
        return out.reshape(*np.shape(total_charge), K)
    out[flat_k == 1] = _ols_row(tau, 1)
    for pick, k, h, U in _optimal_groups(flat_total, flat_k, ramp, exptime_s):
        out[pick, :k] = h @ U
    return out.reshape(*np.shape(total_charge), K)


@dataclass(frozen=True)
class RampImage:
    """What the ramp fit hands to the moments, per pixel."""

    image: np.ndarray  # fitted slope x exposure time [e-]
    usable: np.ndarray  # resultants in each pixel's fit (0: saturated in the first resultant, unusable)
    n_resultants: int

    @property
    def unusable(self) -> np.ndarray:
        return self.usable == 0


def simulate_pixels(
    charge: np.ndarray,
    ramp: Ramp,
    exptime_s: float,
    full_well_e: float,
    coefficients: Sequence[float] = (5e-7,),
    background_e: float = 0.0,
    response: Callable[[np.ndarray], np.ndarray] | None = None,
) -> RampImage:
    """The fitted image of pixels with final-frame charge ``charge`` (explicit reads; the reference).

    ``response`` overrides the polynomial S(Q). The background is part of the charge, the fit and
    the saturation, and is not subtracted here."""
    response = response or polynomial_response(coefficients)
    total = np.asarray(charge, dtype=np.float64) + background_e
    usable = usable_resultants(total, ramp, exptime_s, full_well_e, coefficients)
    weights = slope_weights(total, usable, ramp, exptime_s)
    resultants = resultant_means(total, ramp, exptime_s, response)
    return RampImage(np.sum(weights * resultants, axis=-1), usable, ramp.table.n_resultants)


def order_factors(
    charge: np.ndarray,
    ramp: Ramp,
    exptime_s: float,
    full_well_e: float,
    orders: Sequence[int] = (2,),
    background_e: float = 0.0,
    state: Sequence[float] = (),
) -> tuple[np.ndarray, np.ndarray]:
    """(c_n per pixel, shape (orders, ...), usable resultants per pixel): see the module docstring.

    A pixel's NL term of order n in the fitted image is -b_n (q + b)^n c_n. ``state``: the NL
    coefficients (b2, b3, ...) the "signal" saturation rule sees (:func:`usable_resultants`); the
    factors themselves do not depend on them."""
    total = np.asarray(charge, dtype=np.float64) + background_e
    usable = usable_resultants(total, ramp, exptime_s, full_well_e, state)
    return _factors_for(total, usable, ramp, exptime_s, tuple(orders)), usable


def nonlinearity_perturbation(
    charge: np.ndarray,
    ramp: Ramp,
    exptime_s: float,
    full_well_e: float,
    coefficients: Sequence[float] = (5e-7,),
    background_e: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """(fitted image - star charge, usable resultants) for the polynomial NL: the star's image
    after the ramp fit is ``charge`` + this. A background is fitted with the star and its own
    fitted level (a star-free pixel's, what a sky estimate subtracts) is removed."""
    orders = tuple(range(2, 2 + len(coefficients)))
    factors, usable = order_factors(charge, ramp, exptime_s, full_well_e, orders, background_e, coefficients)
    total = np.asarray(charge, dtype=np.float64) + background_e
    out = np.zeros_like(total)
    for b, n, c in zip(coefficients, orders, factors, strict=True):
        out -= b * total**n * c
    if background_e:
        sky, _ = order_factors(np.zeros(1), ramp, exptime_s, full_well_e, orders, background_e, coefficients)
        out += sum(b * background_e**n * c[0] for b, n, c in zip(coefficients, orders, sky, strict=True))
    return out, usable


def usage_summary(usable: np.ndarray, n_resultants: int, mask: np.ndarray | None = None) -> dict:
    """How many pixels (inside ``mask``) were fitted on how many resultants."""
    values = usable[mask] if mask is not None else usable.ravel()
    counts = np.bincount(values.ravel(), minlength=n_resultants + 1)
    return {
        "pixels": int(values.size),
        "resultants": n_resultants,
        "fitted_on_all": int(counts[n_resultants]),
        "fitted_on_fewer": int(counts[1:n_resultants].sum()),
        "unusable": int(counts[0]),
        "pixels_by_resultants": {str(k): int(c) for k, c in enumerate(counts) if c and k > 0},
        "fewest_resultants": int(values.min()) if values.size else None,
    }


def _factors_for(rate_charge: np.ndarray, usable: np.ndarray, ramp: Ramp, exptime_s: float, orders: tuple[int, ...]):
    """c_n (orders, ...) for given usable resultants; the optimal weights at ``rate_charge``."""
    powers = ramp.table.mean_powers(exptime_s, orders)
    if ramp.fit == "ols":
        per_k = _ols_factors(ramp.table, exptime_s, orders)
        return np.moveaxis(per_k[np.maximum(usable, 1) - 1], -1, 0)
    flat_total, flat_k = np.asarray(rate_charge, dtype=np.float64).ravel(), np.maximum(usable, 1).ravel()
    out = np.empty((len(orders), flat_total.size))
    single = flat_k == 1
    out[:, single] = (powers[:, 0] / _resultant_fractions(ramp.table, exptime_s)[0])[:, None]
    _optimal_factors(out, flat_total, flat_k, ramp, exptime_s, powers)
    return out.reshape(len(orders), *np.shape(rate_charge))
