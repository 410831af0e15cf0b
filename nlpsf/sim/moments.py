"""Adaptive moments (Bernstein & Jarvis 2002; Hirata & Seljak 2003), batched over images.

The adaptive moments of an image I are the centroid x0 and matrix M of the elliptical Gaussian
weight w = exp(-rho^2 / 2), rho^2 = (x - x0)^T M^-1 (x - x0) (cut to zero beyond
``weight_cut_rho2``), at which the weighted moments reproduce the weight:

    sum w I (x - x0) = 0,    sum w I (x - x0)(x - x0)^T / sum w I = M / 2.

That is the fixed point GalSim's ``FindAdaptiveMom`` iterates towards. We solve the same five
equations, but by Newton's method with the analytic Jacobian (all its entries are weighted moments
of order <= 4), so a fit converges to the float64 floor in a handful of iterations instead of
stopping at GalSim's 1e-6. The first iterations from a cold start use HSM's own bounded
fixed-point update, which is robust far from the solution.

Outputs: e1 = (Mxx - Myy) / (Mxx + Myy), e2 = 2 Mxy / (Mxx + Myy), sigma = det(M)^(1/4), all in
fine pixels. A fit that fails is reported per image through ``status``, never raised.

Perturbations. For the difference between the fit of I + dI and the fit of I, the first Newton
step from the reference solution is taken with the residual of dI alone (the reference's own
roundoff is left out), which resolves the difference to float64 precision *relative to the
difference* however small dI is. Larger perturbations are then iterated to convergence as usual.

The fit, the perturbed fit and the pixel response share their kernels (the weight window, the raw
moments, the residual of the five equations and its analytic Jacobian): ``nlpsf.sim.moment_kernels``,
which only this module uses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from enum import IntEnum

import numpy as np

from nlpsf import defaults
from nlpsf.checks import InputError

from .moment_kernels import (
    EQUATIONS as _EQUATIONS,
)
from .moment_kernels import (
    equation_residual as _residual,
)
from .moment_kernels import (
    evaluate_moments as _evaluate,
)
from .moment_kernels import (
    gaussian_weights as _weights,
)
from .moment_kernels import (
    hsm_update as _hsm_update,
)
from .moment_kernels import (
    jacobian as _jacobian,
)
from .moment_kernels import (
    newton_step as _newton_step,
)
from .moment_kernels import (
    positive_definite as _positive_definite,
)
from .moment_kernels import (
    raw_moments as _raw_moments,
)
from .moment_kernels import (
    step_size as _step_size,
)
from .moment_kernels import (
    weight_window as _window,
)

PAPER_WEIGHT_CUT_RHO2 = defaults.PAPER_WEIGHT_CUT_RHO2
GALSIM_WEIGHT_CUT_RHO2 = defaults.GALSIM_WEIGHT_CUT_RHO2


class MomentStatus(IntEnum):
    OK = 0
    NOT_CONVERGED = 1
    NOT_POSITIVE_DEFINITE = 2
    NO_FLUX = 3
    CENTROID_LOST = 4
    NONFINITE_IMAGE = 5
    COLLAPSED = 6


STATUS_REASONS = {
    MomentStatus.OK: "converged",
    MomentStatus.NOT_CONVERGED: "did not converge within the iteration limit",
    MomentStatus.NOT_POSITIVE_DEFINITE: "the moment matrix stopped being positive definite",
    MomentStatus.NO_FLUX: "the weighted flux is not positive",
    MomentStatus.CENTROID_LOST: "the centroid wandered off the stamp",
    MomentStatus.NONFINITE_IMAGE: "the image holds NaN or infinite values",
    MomentStatus.COLLAPSED: "the weight collapsed onto a single pixel (the image is undersampled; raise the oversampling)",
}

#: Below this weight variance (fine pixels^2) the fit has shrunk onto one pixel, as HSM does on
#: undersampled images ("HSM collapsed to singular moment matrix").
_COLLAPSE_VARIANCE = 0.01


@dataclass(frozen=True)
class MomentSettings:
    """How the adaptive moments are computed.

    ``weight_cut_rho2``: the weight is zero beyond this rho^2 (paper: 25; GalSim >= 2.4: 32.24;
    ``math.inf`` for no cut). ``tolerance``: a fit has converged when the last Newton step moved
    the centroid and every element of M by less than this fraction of sigma and of tr(M).
    ``guess_sigma``: starting size (fine pixels) of a cold fit.
    """

    weight_cut_rho2: float = PAPER_WEIGHT_CUT_RHO2
    tolerance: float = 1e-11
    max_iterations: int = 100
    guess_sigma: float = 5.0

    def __post_init__(self) -> None:
        cut = float(self.weight_cut_rho2)
        low = defaults.WEIGHT_CUT_RHO2_RANGE[0]
        if math.isnan(cut) or cut < low:
            raise InputError("weight_cut_rho2", f"must be at least {low:g} (or inf), got {self.weight_cut_rho2!r}")
        if not (math.isfinite(self.tolerance) and 1e-15 <= self.tolerance <= 1e-3):
            raise InputError("tolerance", f"must lie between 1e-15 and 1e-3, got {self.tolerance!r}")
        if not 1 <= int(self.max_iterations) <= 10000:
            raise InputError("max_iterations", f"must lie between 1 and 10000, got {self.max_iterations!r}")
        if not (math.isfinite(self.guess_sigma) and self.guess_sigma > 0):
            raise InputError("guess_sigma", f"must be positive, got {self.guess_sigma!r}")


@dataclass(frozen=True, eq=False)
class Moments:
    """Adaptive moments of a batch of images; every field is an array over the batch.

    Coordinates are in fine pixels relative to the stamp's true centre.
    """

    x0: np.ndarray
    y0: np.ndarray
    mxx: np.ndarray
    mxy: np.ndarray
    myy: np.ndarray
    amplitude: np.ndarray
    iterations: np.ndarray
    last_step: np.ndarray
    status: np.ndarray
    #: For fits made by :func:`fit_perturbed`: the change of (x0, y0, Mxx, Mxy, Myy) from the
    #: reference fit, held separately so that changes far below the float64 resolution of the
    #: parameters themselves are not rounded away.
    delta: np.ndarray | None = field(default=None, repr=False)

    @property
    def e1(self) -> np.ndarray:
        return (self.mxx - self.myy) / (self.mxx + self.myy)

    @property
    def e2(self) -> np.ndarray:
        return 2.0 * self.mxy / (self.mxx + self.myy)

    @property
    def sigma(self) -> np.ndarray:
        return (self.mxx * self.myy - self.mxy**2) ** 0.25

    @property
    def ok(self) -> np.ndarray:
        return self.status == MomentStatus.OK

    def parameters(self) -> np.ndarray:
        return np.stack([self.x0, self.y0, self.mxx, self.mxy, self.myy], axis=-1)

    def __len__(self) -> int:
        return self.x0.shape[0]


_FIELDS = ("x0", "y0", "mxx", "mxy", "myy", "amplitude", "iterations", "last_step", "status")


def select(fit: Moments, index) -> Moments:
    """The fits at ``index`` (an int, slice or index array) as a batch of their own."""
    delta = None if fit.delta is None else np.atleast_2d(fit.delta[index])
    return Moments(*(np.atleast_1d(getattr(fit, name)[index]) for name in _FIELDS), delta=delta)


def core_margin(n: int, fits: Moments, cut: float, growth: float = 2.0) -> int:
    """Pixels every side of an n x n stamp can lose, its centre kept, so that the weight window of
    every fit, grown ``growth`` times in size, still lies inside.

    A perturbed fit started from these fits reads only that core: beyond the cut the weight is
    zero. Nothing can be trimmed without a finite cut, or when a fit failed.
    """
    if not math.isfinite(cut) or len(fits) == 0 or not np.all(fits.ok):
        return 0
    params = fits.parameters()
    extent_x = np.max(np.abs(params[:, 0]) + growth * np.sqrt(cut * params[:, 2]))
    extent_y = np.max(np.abs(params[:, 1]) + growth * np.sqrt(cut * params[:, 4]))
    # Pixel centres lie (n - 1) / 2 from the stamp's centre at most; keep one pixel to spare.
    return max(math.floor((n - 1) / 2.0 - max(extent_x, extent_y) - 1.0), 0)


def within(fits: Moments, n: int, cut: float) -> np.ndarray:
    """Whether each fit converged with its whole weight window (rho^2 <= cut) inside an n x n stamp.

    Such a fit is the same on any larger stamp with the same centre: the pixels it weighs, and
    their offsets from the centroid, are the same ones.
    """
    if not math.isfinite(cut):
        return np.zeros(len(fits), dtype=bool)
    params = fits.parameters()
    centre = (n - 1) / 2.0
    half_x = np.sqrt(cut * np.maximum(params[:, 2], 0.0))
    half_y = np.sqrt(cut * np.maximum(params[:, 4], 0.0))
    inside = (
        (np.floor(params[:, 0] - half_x + centre) >= 0)
        & (np.ceil(params[:, 0] + half_x + centre) + 1 <= n)
        & (np.floor(params[:, 1] - half_y + centre) >= 0)
        & (np.ceil(params[:, 1] + half_y + centre) + 1 <= n)
    )
    return inside & fits.ok


@np.errstate(all="ignore")
def fit(
    images: np.ndarray,
    settings: MomentSettings | None = None,
    start: np.ndarray | None = None,
    chunk: int = 256,
) -> Moments:
    """Adaptive moments of each image in a batch of shape (B, n, n) (or a single (n, n) image)."""
    settings = settings or MomentSettings()
    images = np.asarray(images, dtype=np.float64)
    if images.ndim == 2:
        images = images[None]
    if images.ndim != 3 or images.shape[1] != images.shape[2]:
        raise InputError("images", f"expected square images of shape (B, n, n), got {images.shape}")
    batch = images.shape[0]
    if start is None:
        start = np.tile([0.0, 0.0, settings.guess_sigma**2, 0.0, settings.guess_sigma**2], (batch, 1))
        cold = True
    else:
        start = np.asarray(start, dtype=np.float64).reshape(batch, 5)
        cold = False
    results = [_fit_chunk(images[s : s + chunk], start[s : s + chunk], settings, cold) for s in range(0, batch, chunk)]
    return concatenate(results)


def concatenate(parts: list[Moments]) -> Moments:
    """One batch from several (in order)."""
    if len(parts) == 1:
        return parts[0]
    delta = None if any(p.delta is None for p in parts) else np.concatenate([p.delta for p in parts])
    return Moments(
        *(np.concatenate([getattr(p, name) for p in parts]) for name in _FIELDS),
        delta=delta,
    )


def _fit_chunk(
    images: np.ndarray,
    start: np.ndarray,
    settings: MomentSettings,
    cold: bool,
    first_step: np.ndarray | None = None,
) -> Moments:
    batch, n = images.shape[0], images.shape[-1]
    cut = float(settings.weight_cut_rho2)
    params = start.copy()
    status = np.full(batch, MomentStatus.NOT_CONVERGED, dtype=np.int8)
    status[~np.all(np.isfinite(images), axis=(1, 2))] = MomentStatus.NONFINITE_IMAGE
    iterations = np.zeros(batch, dtype=np.int32)
    last_step = np.full(batch, np.inf)
    amplitude = np.full(batch, np.nan)
    active = status == MomentStatus.NOT_CONVERGED
    if first_step is not None:
        params = params + first_step
        last_step = _step_size(first_step, start)
        iterations += 1
    # Newton from a cold start is only trusted once HSM's fixed-point step has come close.
    newton = np.full(batch, not cold)
    previous = np.full(batch, np.inf)
    limit = 3.0 * n / 4.0
    for _ in range(settings.max_iterations):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        p = params[idx]
        bad = ~_positive_definite(p)
        collapsed = ~bad & (np.minimum(p[:, 2], p[:, 4]) < _COLLAPSE_VARIANCE)
        status[idx[collapsed]] = MomentStatus.COLLAPSED
        bad |= collapsed
        lost = (np.abs(p[:, 0]) > limit) | (np.abs(p[:, 1]) > limit)
        S, inverse = _evaluate(images, idx, np.where((bad | lost)[:, None], start[idx], p), cut, 4)
        amp = S[:, 0, 0]
        no_flux = ~(amp > 0)
        failed = bad | lost | no_flux
        status[idx[bad & ~collapsed]] = MomentStatus.NOT_POSITIVE_DEFINITE
        status[idx[lost & ~bad]] = MomentStatus.CENTROID_LOST
        status[idx[no_flux & ~bad & ~lost]] = MomentStatus.NO_FLUX
        keep = ~failed
        idx, p, S, inverse = idx[keep], p[keep], S[keep], inverse[keep]
        if idx.size == 0:
            break
        amplitude[idx] = S[:, 0, 0]
        use_newton = newton[idx]
        step, size, risky = _step(S, inverse, p, use_newton)
        newton[idx[risky]] = False
        params[idx] = p + step
        iterations[idx] += 1
        last_step[idx] = size
        newton[idx[~use_newton & (size < 1e-3)]] = True
        done = use_newton & ~risky & (size <= settings.tolerance * 1e-3)
        # Quadratic convergence has stalled at the float64 floor: stop once within tolerance.
        stalled = use_newton & ~risky & (size <= settings.tolerance) & (size >= 0.5 * previous[idx])
        finished = idx[done | stalled]
        status[finished] = MomentStatus.OK
        previous[idx] = size
        active = status == MomentStatus.NOT_CONVERGED
        active &= iterations < settings.max_iterations
    # Anything still active ran out of iterations; accept it if the last step met the tolerance.
    leftover = (status == MomentStatus.NOT_CONVERGED) & (last_step <= settings.tolerance)
    status[leftover] = MomentStatus.OK
    return Moments(*(params[:, k] for k in range(5)), amplitude, iterations, last_step, status)


def _step(S: np.ndarray, inverse: np.ndarray, p: np.ndarray, use_newton: np.ndarray):
    """(step, its size, where a Newton step fell back to HSM's) of one iteration of :func:`_fit_chunk`:
    Newton's step where it is trusted, else HSM's bounded fixed-point step, and HSM's where a Newton
    step is large or breaks positivity."""
    step = np.zeros_like(p)
    if np.any(use_newton):
        step[use_newton] = _newton_step(_jacobian(S[use_newton], inverse[use_newton]), _residual(S[use_newton], p[use_newton]))
    if np.any(~use_newton):
        step[~use_newton] = _hsm_update(S[~use_newton], p[~use_newton]) - p[~use_newton]
    size = _step_size(step, p)
    size[~np.isfinite(size)] = np.inf
    risky = use_newton & ((size > 0.2) | ~_positive_definite(p + step))
    if np.any(risky):
        step[risky] = _hsm_update(S[risky], p[risky]) - p[risky]
        size[risky] = _step_size(step[risky], p[risky])
    return step, size, risky


@np.errstate(all="ignore")
def fit_perturbed(
    images: np.ndarray,
    perturbations: np.ndarray,
    reference: Moments,
    settings: MomentSettings | None = None,
    chunk: int = 256,
) -> Moments:
    """Adaptive moments of ``images + perturbations``, started from the fits of ``images``.

    ``images`` (B, n, n) are the images ``reference`` was fitted on (B entries, or one reference
    shared by all); ``perturbations`` has the same shape. See the module docstring for why the
    first step is taken on the perturbation alone.
    """
    settings = settings or MomentSettings()
    images = np.asarray(images, dtype=np.float64)
    perturbations = np.asarray(perturbations, dtype=np.float64)
    if images.shape != perturbations.shape:
        raise InputError("perturbations", "must have the shape of the images")
    params = reference.parameters()
    if params.shape[0] != images.shape[0]:
        raise InputError("reference", "needs one fit per image")
    parts = []
    for s in range(0, images.shape[0], chunk):
        sl = slice(s, s + chunk)
        base, delta, p = images[sl], perturbations[sl], params[sl]
        first = _perturbation_step(base, delta, p, reference.status[sl], float(settings.weight_cut_rho2))
        small = _step_size(np.nan_to_num(first, nan=np.inf), p) < 1e-8
        total = base + delta
        fitted = _fit_chunk(total, p, settings, cold=False, first_step=np.nan_to_num(first))
        # Below 1e-8 the second-order term is under 1e-16: the precise first step is the answer,
        # and further iterations would only add the float64 noise of the full image.
        exact = small & (reference.status[sl] == MomentStatus.OK) & (fitted.status != MomentStatus.NONFINITE_IMAGE)
        delta = fitted.parameters() - p
        if np.any(exact):
            values = p[exact] + first[exact]
            for k, name in enumerate(("x0", "y0", "mxx", "mxy", "myy")):
                getattr(fitted, name)[exact] = values[:, k]
            fitted.status[exact] = MomentStatus.OK
            fitted.iterations[exact] = 1
            fitted.last_step[exact] = _step_size(first[exact], p[exact])
            delta[exact] = first[exact]
        parts.append(replace(fitted, delta=delta))
    return concatenate(parts)


def differences(fit: Moments, reference: Moments) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(Delta R / R, Delta e1, Delta e2) of ``fit`` relative to ``reference``, computed from the
    parameter changes so that they keep full relative precision however small they are."""
    ref = reference.parameters()
    delta = fit.delta if fit.delta is not None else fit.parameters() - ref
    mxx, mxy, myy = ref[:, 2], ref[:, 3], ref[:, 4]
    dxx, dxy, dyy = delta[:, 2], delta[:, 3], delta[:, 4]
    det = mxx * myy - mxy**2
    # det(M + dM) / det(M) - 1, expanded so no large terms cancel.
    ratio_minus_one = (myy * dxx + mxx * dyy - 2 * mxy * dxy + dxx * dyy - dxy**2) / det
    d_r = np.expm1(0.25 * np.log1p(ratio_minus_one))
    trace, d_trace = mxx + myy, dxx + dyy
    d_e1 = ((dxx - dyy) * trace - (mxx - myy) * d_trace) / (trace * (trace + d_trace))
    d_e2 = 2 * (dxy * trace - mxy * d_trace) / (trace * (trace + d_trace))
    return d_r, d_e1, d_e2


def _perturbation_step(base: np.ndarray, delta: np.ndarray, params: np.ndarray, status: np.ndarray, cut: float) -> np.ndarray:
    """Newton step from the reference solution driven by the perturbation's residual only."""
    out = np.full(params.shape, np.nan)
    good = (status == MomentStatus.OK) & _positive_definite(params)
    if not np.any(good):
        return out
    window = _window(base.shape[-1], params[good], cut)
    r0, r1, c0, c1 = window
    weight, dx, dy, inverse = _weights(base.shape[-1], params[good], cut, window)
    S_base = _raw_moments(weight * base[good, r0:r1, c0:c1], dx, dy, 4)
    S_delta = _raw_moments(weight * delta[good, r0:r1, c0:c1], dx, dy, 2)
    amplitude = S_base[:, 0, 0] + S_delta[:, 0, 0]
    pert = np.empty((S_base.shape[0], 5))
    for k, (i, j, m_index) in enumerate(_EQUATIONS):
        # At the reference solution S_base[g] / A_base = c_g, so the residual of the
        # perturbed image is (S_delta[g] - A_delta c_g) / (A_base + A_delta).
        target = 0.0 if m_index < 0 else 0.5 * params[good, m_index]
        pert[:, k] = (S_delta[:, i, j] - S_delta[:, 0, 0] * target) / amplitude
    jac = _jacobian(S_base, inverse)
    out[good] = _newton_step(jac, pert)
    return out


def metric_gradients(moments: Moments) -> np.ndarray:
    """d(R/R0, e1, e2)/d(x0, y0, Mxx, Mxy, Myy) at each fit, shape (B, 3, 5)."""
    mxx, mxy, myy = moments.mxx, moments.mxy, moments.myy
    det = mxx * myy - mxy**2
    trace = mxx + myy
    out = np.zeros((len(moments), 3, 5))
    # R = det^(1/4): dR/R = (myy dMxx + mxx dMyy - 2 mxy dMxy) / (4 det)
    out[:, 0, 2] = myy / (4 * det)
    out[:, 0, 3] = -2 * mxy / (4 * det)
    out[:, 0, 4] = mxx / (4 * det)
    # e1 = (mxx - myy) / trace
    out[:, 1, 2] = 2 * myy / trace**2
    out[:, 1, 4] = -2 * mxx / trace**2
    # e2 = 2 mxy / trace
    out[:, 2, 2] = -2 * mxy / trace**2
    out[:, 2, 3] = 2 / trace
    out[:, 2, 4] = -2 * mxy / trace**2
    return out


def _core_response(
    images: np.ndarray, moments: Moments, settings: MomentSettings
) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """Gradient of (dR/R, e1, e2) with respect to the pixels of the weight's core window."""
    params = moments.parameters()
    n = images.shape[-1]
    cut = float(settings.weight_cut_rho2)
    r0, r1, c0, c1 = window = _window(n, params, cut)
    weight, dx, dy, inverse = _weights(n, params, cut, window)
    S = _raw_moments(weight * images[:, r0:r1, c0:c1], dx, dy, 4)
    jac = _jacobian(S, inverse)
    amplitude = S[:, 0, 0]
    chain = -metric_gradients(moments) @ np.linalg.inv(jac)  # (B, 3, 5): d metric / dF
    ddx = dx[:, None, :]
    ddy = dy[:, :, None]
    basis = (
        ddx + 0 * ddy,
        ddy + 0 * ddx,
        ddx**2 - 0.5 * params[:, 2, None, None],
        ddx * ddy - 0.5 * params[:, 3, None, None],
        ddy**2 - 0.5 * params[:, 4, None, None],
    )
    scaled = weight / amplitude[:, None, None]
    core = np.zeros((images.shape[0], 3, r1 - r0, c1 - c0))
    for k, g in enumerate(basis):
        core += chain[:, :, k, None, None] * (scaled * g)[:, None]
    return core, window


@np.errstate(all="ignore")
def pixel_response(images: np.ndarray, moments: Moments, settings: MomentSettings | None = None) -> np.ndarray:
    """Gradient of (dR/R, e1, e2) with respect to every pixel value, shape (B, 3, n, n).

    By the implicit function theorem at the solution F(theta, I) = 0:
    d theta / d I_k = -J^-1 dF/dI_k with dF_g/dI_k = w_k (g_k - c_g) / A. Pixels outside the
    weight cut get zero (the cut itself is a discontinuity the gradient ignores).
    """
    settings = settings or MomentSettings()
    images = np.asarray(images, dtype=np.float64)
    if images.ndim == 2:
        images = images[None]
    core, (r0, r1, c0, c1) = _core_response(images, moments, settings)
    n = images.shape[-1]
    out = np.zeros((images.shape[0], 3, n, n))
    out[:, :, r0:r1, c0:c1] = core
    return out


@np.errstate(all="ignore")
def response_to(
    images: np.ndarray, moments: Moments, directions: np.ndarray, settings: MomentSettings | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """First-order response of (dR/R, e1, e2) to perturbing each image along a direction.

    Returns (g . d, ||g (.) d||) per image and metric, each of shape (B, 3): the change per unit
    step along ``directions`` (B, n, n), and the spread if every pixel were perturbed by an
    independent unit-variance amount times d (the closed-form scatter). Only the weight's core is
    touched.
    """
    settings = settings or MomentSettings()
    core, (r0, r1, c0, c1) = _core_response(np.asarray(images, dtype=np.float64), moments, settings)
    d = np.asarray(directions, dtype=np.float64)[:, None, r0:r1, c0:c1]
    along = core * d  # once for both sums
    return np.sum(along, axis=(2, 3)), np.sqrt(np.sum(along**2, axis=(2, 3)))
