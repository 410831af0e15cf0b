"""Ramps inside a scene: IPC, a background and a polynomial NL combined with the ramp fit (docs/ramps.md)."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from nlpsf.checks import InputError

from . import correction
from .config import Ramp, polynomial_response, signal_usable, usable_resultants
from .correction import CorrectedRamp
from .fits import _factors_for, slope_weights

RAMP_REFUSES: dict[str, str] = {
    "brighter_fatter": (
        "brighter-fatter moves charge by an amount that grows as the square of the charge collected so far, so up "
        "the ramp it is one more flux-dependent term per read, and its NL-free reference image would change with "
        "each pixel's saturated resultants; the published kernel form is for a final frame and is not derived here"
    ),
}


def check_scene(scene) -> None:
    """Refuse a scene a ramp cannot take (:data:`RAMP_REFUSES`); every other effect combines
    (optical ones trivially, IPC, background and polynomial NL by :func:`scene_factors`)."""
    on = scene.effects_on()
    refused = [name for name in RAMP_REFUSES if on.get(name)]
    if refused:
        raise InputError(
            "scene", "an up-the-ramp readout cannot take " + "; ".join(f"{name}: {RAMP_REFUSES[name]}" for name in refused)
        )


@dataclass(frozen=True)
class SceneRamp:
    """A ramp's per-pixel factors inside a scene, at one flux (see :func:`scene_factors`)."""

    factors: np.ndarray  # (orders, ...) c_n of the pixel that measures (its weights)
    usable: np.ndarray  # resultants in each pixel's fit
    charge: np.ndarray  # the charge the NL acts on (after IPC when IPC comes first)
    orders: tuple[int, ...]
    #: IPC after the NL: IPC(Q^n) per order n (from :class:`CoupledPowers`), so that
    #: :func:`scene_perturbation` couples no image again; None: it couples ``charge``'s powers.
    coupled: dict[int, np.ndarray] | None = None
    #: Pixels trimmed from every side of the stamps (the moments' core, ``Scene.core_margin``): every
    #: array above is that central core; 0: the whole stamps.
    margin: int = 0
    #: For a trimmed one: computes the whole-stamp SceneRamp (when a fit leaves the core).
    whole: Callable[[], SceneRamp] | None = field(default=None, compare=False, repr=False)
    #: Where the factors were computed, (R, core, core), None: everywhere. Elsewhere they are 0: a
    #: moments fit whose weight window (rho^2 <= cut) stays inside never reads them (beyond the cut
    #: the weight is exactly zero); one that leaves it must use ``whole()``.
    region: np.ndarray | None = field(default=None, compare=False, repr=False)

    def head(self, count: int) -> SceneRamp:
        """The first ``count`` realizations."""
        coupled = None if self.coupled is None else {n: v[:count] for n, v in self.coupled.items()}
        whole = None if self.whole is None else (lambda: self.whole().head(count))
        region = None if self.region is None else self.region[:count]
        return SceneRamp(
            self.factors[:, :count], self.usable[:count], self.charge[:count], self.orders, coupled, self.margin, whole, region
        )


@dataclass(frozen=True, eq=False)
class CoupledPowers:
    """IPC of every power of a scene's charge Q = s psi + B, from IPC of the unit stamps' powers.

    IPC is linear, so IPC(Q^n) = sum_m C(n, m) s^m B^(n-m) IPC(psi^m), IPC(psi^0) = sum K (the
    edge-continued coupling of a uniform field). The stamps' powers are coupled once per scene
    (cached per m); every flux then costs a few multiply-adds per pixel instead of coupling every
    read of every pixel (the "signal" rule) and every NL term (the perturbation) again. Equal to
    coupling Q^n directly up to rounding (tests/library/test_ramp_speed.py)."""

    unit: np.ndarray  # (R, n, n) unit-flux charge before IPC
    kernel: np.ndarray
    oversampling: int
    _cache: dict = field(default_factory=dict, repr=False)

    def unit_power(self, m: int) -> np.ndarray | float:
        if m == 0:
            return float(np.sum(np.asarray(self.kernel, dtype=np.float64)))
        if m not in self._cache:
            self._cache[m] = _ipc(self.unit**m, self.kernel, self.oversampling)
        return self._cache[m]

    def seed(self, m: int, coupled: np.ndarray) -> None:
        """Give IPC(psi^m) already computed (by ``_ipc`` on the same stamps and kernel)."""
        self._cache[m] = coupled

    def below(self, scale: float, background: float, threshold: float, state, pick, saturation_beta=None) -> bool:
        """Whether no pixel's coupled signal can reach ``threshold`` (no resultant saturates): the
        largest measured charge IPC(Q) stays below it and the NL (coefficients >= 0, a kernel >= 0)
        only lowers the signal. False when that cannot be told without the resultants."""
        state = tuple(state)
        if saturation_beta is not None:
            state = (saturation_beta, *state[1:])
        if any(b < 0 for b in state) or np.any(np.asarray(self.kernel) < 0):
            return False
        key = ("peak", pick.start, pick.stop, pick.step) if isinstance(pick, slice) else None
        peak = self._cache.get(key) if key else None
        if peak is None:
            peak = float(np.max(self.unit_power(1)[pick]))
            if key:
                self._cache[key] = peak
        # The arithmetic of at(.., 1) on the brightest pixel (x -> scale x + B sum K is monotonic),
        # so this is that pixel's measured charge, compared exactly.
        return scale * peak + background * self.unit_power(0) < threshold

    def at(self, scale: float, background: float, n: int, pick=slice(None)) -> np.ndarray:
        """IPC((scale psi + background)^n) at ``pick`` (an index into the (R, n, n) stamps)."""
        out = 0.0
        for m in range(n, -1, -1):
            term = self.unit_power(m)
            term = term[pick] if m else term
            out = out + math.comb(n, m) * scale**m * background ** (n - m) * term
        return np.broadcast_to(out, self.unit[pick].shape) if np.ndim(out) == 0 else out

    def at_pixels(self, scale: float, background: float, n: int, pick, flat: np.ndarray) -> np.ndarray:
        """:meth:`at` at the pixels ``flat`` (indices into the flattened stamps ``pick``): the same
        arithmetic per pixel, so the same numbers as ``at(...).ravel()[flat]``."""
        out = 0.0
        for m in range(n, -1, -1):
            term = self.unit_power(m)[pick].reshape(-1)[flat] if m else self.unit_power(m)
            out = out + math.comb(n, m) * scale**m * background ** (n - m) * term
        return np.broadcast_to(out, flat.shape) if np.ndim(out) == 0 else out

    def _reaching(self, pick, cut: float) -> np.ndarray | None:
        """Flat indices (ascending) of the pixels of the stamps ``pick`` with IPC(psi) >= ``cut``; None
        when ``pick`` is no slice. A pool of the pixels above the lowest cut asked so far is kept
        per slice (a table asks from its brightest magnitude, the lowest cut, down), so a cut costs
        a pass over the pool, not over the stamps."""
        if not isinstance(pick, slice):
            return None
        key = ("pool", pick.start, pick.stop, pick.step)
        pool = self._cache.get(key)
        if pool is None or cut < pool[0]:
            values = np.asarray(self.unit_power(1)[pick]).reshape(-1)
            where = np.flatnonzero(values >= cut)
            pool = self._cache[key] = (cut, where, values[where])
        _, where, values = pool
        return where[values >= cut]

    def may_reach(self, scale: float, background: float, threshold: float, pick, state) -> np.ndarray | None:
        """Flat indices (into the stamps ``pick``) of every pixel whose coupled signal can reach
        ``threshold`` in some resultant, and a few more; None when that cannot be bounded this way.

        With NL coefficients >= 0, a kernel >= 0, psi >= 0 and B >= 0 every coupled power IPC(Q^n) is
        a sum of non-negative terms, so each read's signal is at most the measured charge IPC(Q); that
        is s IPC(psi) + B sum K, rising with IPC(psi), and the pixels where it can reach the threshold
        are those with IPC(psi) >= (threshold - B sum K) / s, taken here with a 1e-9 relative margin
        (rounding moves it by ~1e-16) and tested exactly by the caller."""
        if any(b < 0 for b in state) or np.any(np.asarray(self.kernel) < 0) or background < 0 or scale <= 0:
            return None
        if "unit_min" not in self._cache:
            self._cache["unit_min"] = float(np.min(self.unit))
        if self._cache["unit_min"] < 0:
            return None
        cut = (threshold - background * self.unit_power(0)) / scale
        return self._reaching(pick, cut - 1e-9 * abs(cut))


def _ipc(images: np.ndarray, kernel, oversampling: int) -> np.ndarray:
    from ..scene import apply_ipc  # scene effects have one owner

    return apply_ipc(images, kernel, oversampling)


def scene_factors(
    charge: np.ndarray,
    ramp: Ramp,
    exptime_s: float,
    full_well_e: float,
    state: Sequence[float],
    orders: Sequence[int],
    ipc=None,
    ipc_order: str = "after",
    oversampling: int = 1,
) -> SceneRamp:
    """Ramp factors of a scene's pixels: ``charge`` is the final-frame charge per fine pixel, star plus
    background (Q = s psi + B), before IPC; ``state`` the NL coefficients the saturation step sees.

    Derivation (docs/ramps.md). Every read i of pixel p measures D_p(tau_i) = sum_k K_k S_{p+k}(tau_i)
    (IPC after the NL: coupling of the read voltages, linear and the same at every read) with
    S(Q tau) = Q tau - sum_n b_n Q^n tau^n; resultants average reads, the fit is image_p = sum_j w_pj R_pj
    with sum_j w_pj <tau>_j = 1. So

        image_p = IPC(Q)_p - sum_n b_n IPC(Q^n)_p c_{n,p},     c_{n,p} = sum_j w_pj <tau^n>_j,

    the factor of the *measuring* pixel p (its usable resultants and, for ``optimal``, its measured rate
    IPC(Q)_p). IPC before the NL couples the charge instead: Q -> IPC(Q) first, then the plain form.
    Saturation: "charge" judges the charge collected in the pixel (Q, or IPC(Q) when IPC comes first);
    "signal" the resultants the pipeline receives, D (romancal flags the read data, after IPC).
    """
    total = np.asarray(charge, dtype=np.float64)
    after = ipc is not None and ipc_order == "after"
    if ipc is not None and not after:
        total = _ipc(total, ipc, oversampling)
    measured = _ipc(total, ipc, oversampling) if after else total
    orders = tuple(orders)
    if not after or ramp.saturation == "charge":
        usable = usable_resultants(total, ramp, exptime_s, full_well_e, state)
    else:
        usable = _usable_after_ipc(total, measured, ramp, exptime_s, full_well_e, state, ipc, oversampling)
    factors = _factors_for(measured, usable, ramp, exptime_s, orders)
    return SceneRamp(factors, usable, total, orders)


def scene_factors_coupled(
    powers: CoupledPowers,
    scale: float,
    background: float,
    ramp: Ramp,
    exptime_s: float,
    full_well_e: float,
    state: Sequence[float],
    orders: Sequence[int],
    pick=slice(None),
    margin: int = 0,
    region: np.ndarray | None = None,
) -> tuple[SceneRamp, np.ndarray]:
    """:func:`scene_factors` for IPC after the NL, on Q = ``scale`` psi + ``background`` (psi the unit
    stamps of ``powers``, realizations ``pick``), with every coupled image from ``powers``; and the
    usable resultants of every pixel of the whole stamps.

    ``margin`` > 0: the factors (the per-pixel optimal weights, most of the cost), the charge and its
    coupled powers only on the stamps' central core, ``margin`` pixels in from every side (outside the
    moments' weight window they multiply nothing); the SceneRamp's ``whole`` computes the rest.
    ``region`` (boolean, the core's shape): the factors only there, 0 elsewhere (``SceneRamp.region``).

    Under the "signal" rule each read's coupled signal is D(tau) = tau IPC(Q) - sum_n b_n tau^n IPC(Q^n)
    (IPC is linear and the NL a polynomial), so resultant j is IPC(Q) <tau>_j - sum_n b_n IPC(Q^n) <tau^n>_j:
    the same resultants as coupling every read (:func:`_usable_after_ipc`), from one coupled image per order."""
    orders = tuple(orders)
    shape = powers.unit[pick].shape
    n = shape[-1]
    core = (Ellipsis, slice(margin, n - margin), slice(margin, n - margin))
    rows = pick if margin == 0 else (pick, slice(margin, n - margin), slice(margin, n - margin))
    # The charge on the core only (elementwise, so the same numbers as the whole stamps' core).
    charge = scale * powers.unit[rows] + background
    if ramp.saturation == "charge":
        usable = usable_resultants(scale * powers.unit[pick] + background, ramp, exptime_s, full_well_e, state)
    elif powers.below(scale, background, full_well_e, state, pick, ramp.saturation_beta):
        # No resultant saturates anywhere: one value for every pixel (read-only, no per-pixel work).
        usable = np.broadcast_to(np.int32(_all_kept(ramp)), shape)
    else:
        usable = _usable_coupled(powers, scale, background, ramp, exptime_s, full_well_e, state, pick)
    rate = powers.at(scale, background, 1, rows)
    if region is None:
        factors = _factors_for(rate, usable[core], ramp, exptime_s, orders)
    else:
        # Per pixel the factors are the pixel's own (its rate and usable resultants), so computing
        # fewer pixels gives the same numbers on those.
        inside = np.flatnonzero(region)
        one = usable[(0,) * usable.ndim] if usable.size and not any(usable.strides) else None
        if one is not None:
            kept = np.full(inside.size, one, dtype=np.int32)
        else:
            kept = np.ascontiguousarray(usable[core]).reshape(-1)[inside]
        factors = np.zeros((len(orders), *rate.shape))
        factors.reshape(len(orders), -1)[:, inside] = _factors_for(rate.reshape(-1)[inside], kept, ramp, exptime_s, orders)
    coupled = {n: powers.at(scale, background, n, rows) for n in orders}
    whole = None
    if margin:
        args = (powers, scale, background, ramp, exptime_s, full_well_e, state, orders, pick)
        whole = lambda: scene_factors_coupled(*args)[0]  # noqa: E731
    return SceneRamp(factors, usable[core], charge, orders, coupled, margin, whole, region), usable


def _all_kept(ramp: Ramp) -> int:
    """Usable resultants of a pixel that saturates in none (the one-resultant rule applied)."""
    K = ramp.table.n_resultants
    return 0 if K == 1 and ramp.single_resultant == "unusable" else K


def _usable_coupled(powers: CoupledPowers, scale, background, ramp: Ramp, exptime_s, threshold, state, pick):
    """The "signal" rule on coupled reads, each resultant from the coupled powers (see above).

    Only pixels whose measured signal can reach the threshold need their resultants; where
    :meth:`CoupledPowers.may_reach` bounds them, only those pixels are computed at all."""
    state = tuple(state)
    if ramp.saturation_beta is not None:
        state = (ramp.saturation_beta, *state[1:])
    state_orders = range(2, 2 + len(state))
    K = ramp.table.n_resultants
    usable = np.full(powers.unit[pick].shape, K, dtype=np.int32)
    pixels = powers.may_reach(scale, background, threshold, pick, state)
    if pixels is None:  # every pixel, as coupled images
        measured = powers.at(scale, background, 1, pick)
        terms = [(b, n, powers.at(scale, background, n, pick)) for b, n in zip(state, state_orders, strict=True) if b != 0]
        target = usable
    else:
        measured = powers.at_pixels(scale, background, 1, pick, pixels)
        terms = [
            (b, n, powers.at_pixels(scale, background, n, pick, pixels))
            for b, n in zip(state, state_orders, strict=True)
            if b != 0
        ]
        target = np.full(pixels.shape, K, dtype=np.int32)
    final = measured
    for b, _, coupled in terms:
        final = final - b * coupled
    candidates = (measured >= threshold) | (final >= threshold)
    if np.any(candidates):
        mean_tau = ramp.table.mean_powers(exptime_s, (1, *(n for _, n, _ in terms)))
        resultants = measured[candidates][:, None] * mean_tau[0]
        for row, (b, _, coupled) in enumerate(terms, start=1):
            resultants = resultants - b * coupled[candidates][:, None] * mean_tau[row]
        target[candidates] = signal_usable(resultants, ramp.table, threshold)
    if ramp.single_resultant == "unusable":
        target[target == 1] = 0
    if pixels is not None:
        usable.reshape(-1)[pixels] = target
        if K == 1 and ramp.single_resultant == "unusable":
            usable[...] = np.where(usable == 1, 0, usable)
    return usable


def _usable_after_ipc(total, measured, ramp: Ramp, exptime_s: float, threshold: float, state, kernel, oversampling: int):
    """The "signal" rule on IPC-coupled reads: each read's S is coupled, then averaged into resultants."""
    state = tuple(state)
    if ramp.saturation_beta is not None:
        state = (ramp.saturation_beta, *state[1:])
    response = polynomial_response(state)
    usable = np.full(total.shape, ramp.table.n_resultants, dtype=np.int32)
    # As in usable_resultants: only pixels whose measured signal can reach the threshold need their reads.
    candidates = (measured >= threshold) | (_ipc(response(total), kernel, oversampling) >= threshold)
    if np.any(candidates):
        tau = ramp.table.read_fractions(exptime_s)
        sizes = [len(r) for r in ramp.table.resultants]
        sums = np.zeros((int(candidates.sum()), len(sizes)))
        which = np.repeat(np.arange(len(sizes)), sizes)
        for i, t in enumerate(tau):
            sums[:, which[i]] += _ipc(response(total * t), kernel, oversampling)[candidates]
        usable[candidates] = signal_usable(sums / np.array(sizes, dtype=np.float64), ramp.table, threshold)
    if ramp.single_resultant == "unusable":
        usable = np.where(usable == 1, 0, usable).astype(np.int32)
    return usable


def scene_perturbation(
    sr: SceneRamp, beta, higher: Sequence[float], ipc=None, ipc_order: str = "after", oversampling: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """(fitted image - NL-free image, d it / d b2) in e-, from :func:`scene_factors` (``beta`` = b2,
    scalar or per pixel; ``higher`` = (b3, ...)). Term by term, never a difference of images."""
    after = ipc is not None and ipc_order == "after"
    if sr.margin and (sr.coupled is None or np.ndim(beta) != 0):
        sr = sr.whole()  # coupling a core would lose its edges: per-pixel coefficients need the whole stamps
    q = sr.charge
    coefficients = (beta, *higher)
    perturbation = np.zeros(np.shape(q))
    orders = range(2, 2 + len(coefficients))
    all_coupled = (
        after and sr.coupled is not None and all(np.ndim(b) == 0 for b in coefficients) and all(n in sr.coupled for n in orders)
    )
    # Q^n only where some term needs it (every order coupled already with a uniform beta: none).
    power = None if all_coupled else q * q
    derivative = None
    for n, b in zip(orders, coefficients, strict=True):
        c = sr.factors[sr.orders.index(n)]
        coupled = sr.coupled.get(n) if after and sr.coupled is not None else None
        uncoupled = coupled is None
        term = (_ipc(power, ipc, oversampling) if after else power) if uncoupled else coupled
        if n == 2:
            derivative = -c * term
        if np.any(b != 0):
            if coupled is not None and np.ndim(b) == 0:
                # A uniform coefficient commutes with IPC: IPC(b Q^n) = b IPC(Q^n).
                perturbation = perturbation - c * (b * coupled)
            else:
                perturbation = perturbation - c * (_ipc(b * power, ipc, oversampling) if after else b * power)
        if power is not None:
            power = power * q
    return perturbation, derivative


# --- the pipeline's linearity correction per resultant (``correction``) ------------------------


def _mean_powers(ramp: Ramp | None, exptime_s: float, count: int) -> np.ndarray:
    """<tau^n>_j for n = 1 .. count: the ramp's, or a final frame's one resultant at tau = 1."""
    if ramp is None:
        return np.ones((count, 1))
    return ramp.table.mean_powers(exptime_s, tuple(range(1, count + 1)))


def _pixel_weights(rate: np.ndarray, usable: np.ndarray | None, ramp: Ramp | None, exptime_s: float) -> np.ndarray:
    """(P, K) slope weights of P pixels (the optimal ones at their measured rate); a final frame: 1."""
    if ramp is None:
        return np.ones((rate.size, 1))
    return slope_weights(rate, usable, ramp, exptime_s).reshape(rate.size, ramp.table.n_resultants)


def corrected_coupled(
    powers: CoupledPowers,
    scale: float,
    background: float,
    ramp: Ramp | None,
    exptime_s: float,
    usable: np.ndarray | None,
    raw: Sequence[float],
    residual_terms: Sequence[float] = (),
    pick=slice(None),
    margin: int = 0,
    region: np.ndarray | None = None,
) -> CorrectedRamp:
    """:func:`correction.correct` for IPC after the NL on Q = ``scale`` psi + ``background``, every coupled
    power from ``powers``: on the stamps' core (``margin``) and, with ``region``, only there (the pixels
    a moments fit whose window stays inside reads; zero elsewhere, as ``scene_factors_coupled``'s).
    ``usable``: the core's usable resultants (any broadcastable shape; None for a final frame)."""
    shape = powers.unit[pick].shape
    n = shape[-1]
    rows = pick if margin == 0 else (pick, slice(margin, n - margin), slice(margin, n - margin))
    rate = powers.at(scale, background, 1, rows)
    core_shape = rate.shape
    index = None if region is None else np.flatnonzero(region)

    def take(a: np.ndarray) -> np.ndarray:
        flat = np.ascontiguousarray(a).reshape(-1)
        return flat if index is None else flat[index]

    flat_rate = take(rate)
    kept = None if usable is None else take(np.broadcast_to(usable, core_shape))
    raw = tuple(raw)
    orders = [k for k, b in enumerate(raw, start=2) if b != 0]
    coupled = {k: take(powers.at(scale, background, k, rows)) for k in orders}
    weights = _pixel_weights(flat_rate, kept, ramp, exptime_s)
    means = _mean_powers(ramp, exptime_s, 1 + len(raw))
    return correction.correct(flat_rate, coupled, raw, means, weights, core_shape, index, residual_terms)


def corrected_images(
    charge: np.ndarray,
    ramp: Ramp | None,
    exptime_s: float,
    usable: np.ndarray | None,
    raw: Sequence[float],
    residual_terms: Sequence[float] = (),
    ipc=None,
    ipc_order: str = "after",
    oversampling: int = 1,
) -> CorrectedRamp:
    """:func:`correction.correct` on whole images of the charge ``charge`` (star plus background, before
    IPC): IPC after the NL couples each power of the charge, IPC before couples the charge itself."""
    total = np.asarray(charge, dtype=np.float64)
    after = ipc is not None and ipc_order == "after"
    if ipc is not None and not after:
        total = _ipc(total, ipc, oversampling)
    raw = tuple(raw)
    rate = _ipc(total, ipc, oversampling) if after else total
    coupled = {}
    for k, b in enumerate(raw, start=2):
        if b != 0:
            coupled[k] = (_ipc(total**k, ipc, oversampling) if after else total**k).reshape(-1)
    kept = None if usable is None else np.broadcast_to(usable, total.shape).reshape(-1)
    weights = _pixel_weights(rate.reshape(-1), kept, ramp, exptime_s)
    means = _mean_powers(ramp, exptime_s, 1 + len(raw))
    return correction.correct(rate.reshape(-1), coupled, raw, means, weights, total.shape, None, residual_terms)
