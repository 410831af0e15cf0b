"""Up-the-ramp exposures: MultiAccum (MA) tables, reads, resultants and the slope fit.

Roman's WFI does not deliver a final frame. Every pixel is read non-destructively every frame time
(3.04 s); an MA table groups the reads into *resultants* (the mean of their reads, all that is sent
to the ground), and the ground pipeline fits a slope to the resultants, dropping those that passed
saturation. This module turns a pixel's final-frame charge into the image the moments then see:
the fitted slope times the exposure time.

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

from __future__ import annotations

import json
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import cached_property
from importlib import resources
from pathlib import Path

import numpy as np

from . import defaults
from .checks import InputError, check_integer, check_number

ROMAN_FRAME_TIME_S = defaults.ROMAN_FRAME_TIME_S
#: Read noise per read of a :class:`Ramp` built without one and without an SCA (:func:`build`
#: looks up the SCA's official value instead); it only matters for the ``optimal`` fit.
DEFAULT_READ_NOISE_E = defaults.READ_NOISE_E
RAMP_FITS = defaults.RAMP_FITS
MAX_READS = defaults.MAX_RAMP_READS
#: Relative slack when comparing a table's last read time with the exposure time (rounding of
#: frame_time * n).
_TIME_SLACK = 1e-9
#: Pixels per block in the per-pixel weight computation (bounds memory for long tables).
_BLOCK = 1 << 16


def shipped_table_dir() -> Path:
    return Path(str(resources.files("nlpsf") / "data" / "ma_tables"))


def shipped_table_names() -> list[str]:
    return sorted(p.stem for p in shipped_table_dir().glob("*.json"))


# --- the MA table -----------------------------------------------------------------------------


@dataclass(frozen=True)
class MATable:
    """Resultants as tuples of read indices (read i ends at i * frame_time after the reset)."""

    resultants: tuple[tuple[int, ...], ...]
    frame_time_s: float
    name: str = "custom"
    source: str = ""

    def __post_init__(self) -> None:
        field = "ma_table"
        try:
            resultants = tuple(tuple(r) for r in self.resultants)
        except TypeError:
            raise InputError(f"{field}.resultants", "must be a list of lists of read indices") from None
        if not resultants:
            raise InputError(f"{field}.resultants", "give at least one resultant")
        previous = 0
        for j, reads in enumerate(resultants, start=1):
            if not reads:
                raise InputError(f"{field}.resultants", f"resultant {j} has no reads")
            for index in reads:
                if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 1:
                    raise InputError(f"{field}.resultants", f"resultant {j}: read indices are integers >= 1, got {index!r}")
                if index <= previous:
                    raise InputError(
                        f"{field}.resultants",
                        f"resultant {j}: read {index} is not after read {previous}; reads must increase "
                        "within and across resultants (no reordering, no read in two resultants)",
                    )
                previous = int(index)
        if previous > MAX_READS:
            raise InputError(f"{field}.resultants", f"at most {MAX_READS} reads, got read {previous}")
        object.__setattr__(self, "resultants", tuple(tuple(int(i) for i in r) for r in resultants))
        check_number(self.frame_time_s, f"{field}.frame_time_s", *defaults.FRAME_TIME_RANGE_S, open_low=True)
        object.__setattr__(self, "frame_time_s", float(self.frame_time_s))

    @classmethod
    def uniform(cls, n: int, exptime_s: float) -> MATable:
        """``--ramp N``: N reads evenly spaced over the exposure, the last at its end, one per resultant."""
        n = check_integer(n, "ramp", 1, MAX_READS)
        exptime_s = check_number(exptime_s, "exptime", *defaults.EXPTIME_RANGE_S)
        return cls(tuple((i,) for i in range(1, n + 1)), exptime_s / n, name=f"uniform-{n}", source="uniform reads")

    @classmethod
    def from_dict(cls, data: dict, name: str = "custom") -> MATable:
        if not isinstance(data, dict):
            raise InputError("ma_table", "must be an object with 'resultants' (or 'read_pattern') and 'frame_time_s'")
        resultants = data.get("resultants", data.get("read_pattern"))
        if resultants is None:
            raise InputError("ma_table.resultants", "missing (a list of lists of read indices)")
        frame = data.get("frame_time_s", ROMAN_FRAME_TIME_S)
        return cls(resultants, frame, name=str(data.get("name", name)), source=str(data.get("source", "")))

    @property
    def n_resultants(self) -> int:
        return len(self.resultants)

    @property
    def n_reads(self) -> int:
        return sum(len(r) for r in self.resultants)

    @property
    def duration_s(self) -> float:
        """Time of the last read after the reset."""
        return self.resultants[-1][-1] * self.frame_time_s

    def check_exposure(self, exptime_s: float, field: str = "ma_table") -> None:
        if self.duration_s > exptime_s * (1 + _TIME_SLACK):
            raise InputError(
                field,
                f"the table's last read is at {self.duration_s:.6g} s, after the end of the {exptime_s:.6g} s exposure; "
                "give a longer exposure or a shorter table",
            )

    def read_fractions(self, exptime_s: float) -> np.ndarray:
        """tau of every read (time / exposure), in order."""
        return np.array([i for r in self.resultants for i in r], dtype=np.float64) * self.frame_time_s / exptime_s

    def resultant_means(self, reads: np.ndarray) -> np.ndarray:
        """(..., reads) -> (..., resultants): each resultant the mean of its reads (O(reads))."""
        sizes = np.array([len(r) for r in self.resultants])
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        return np.add.reduceat(reads, starts, axis=-1) / sizes

    def mean_powers(self, exptime_s: float, orders: Sequence[int]) -> np.ndarray:
        """<tau^n>_j: (orders, resultants)."""
        tau = self.read_fractions(exptime_s)
        return self.resultant_means(np.stack([tau**n for n in orders]))

    def last_read_fractions(self, exptime_s: float) -> np.ndarray:
        return np.array([r[-1] for r in self.resultants], dtype=np.float64) * self.frame_time_s / exptime_s

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "frame_time_s": self.frame_time_s,
            "resultants": [list(r) for r in self.resultants],
            "source": self.source,
        }


def load_ma_table(spec: str | Path) -> MATable:
    """An MA table from a JSON file, or a shipped one by name (``nlpsf/data/ma_tables``)."""
    path = Path(spec)
    if path.suffix.lower() == ".json" or path.exists():
        if not path.is_file():
            raise InputError("ma_table", f"no MA table file at {path}")
        try:
            data = json.loads(path.read_text())
        except (OSError, ValueError) as error:
            raise InputError("ma_table", f"cannot read {path} as JSON: {error}") from None
        return MATable.from_dict(data, name=path.stem)
    key = str(spec).strip().lower()
    for name in shipped_table_names():
        if name.lower() == key:
            return MATable.from_dict(json.loads((shipped_table_dir() / f"{name}.json").read_text()), name=name)
    raise InputError("ma_table", f"no file and no shipped MA table named {spec!r}; shipped: {', '.join(shipped_table_names())}")


# --- the ramp configuration -------------------------------------------------------------------


@dataclass(frozen=True)
class Ramp:
    """An MA table and how the ground system fits it."""

    table: MATable
    fit: str = "ols"
    #: Noise of one read [e-]; None: :data:`DEFAULT_READ_NOISE_E` (``build`` gives the SCA's own).
    read_noise_e: float | None = None
    #: Where the read noise came from, said in the conditions ("given" when the caller chose it).
    read_noise_source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        if self.read_noise_e is None:
            object.__setattr__(self, "read_noise_e", DEFAULT_READ_NOISE_E)
            object.__setattr__(
                self,
                "read_noise_source",
                self.read_noise_source or f"nlpsf default {DEFAULT_READ_NOISE_E:g} e- (romanisim's reference data; no SCA given)",
            )
        elif not self.read_noise_source:
            object.__setattr__(self, "read_noise_source", "given")
        if not isinstance(self.table, MATable):
            raise InputError("ma_table", f"must be an MATable, got {type(self.table).__name__}")
        if self.fit not in RAMP_FITS:
            raise InputError("ramp_fit", f"must be one of {', '.join(RAMP_FITS)}, got {self.fit!r}")
        if self.fit == "optimal" and self.table.n_resultants > defaults.MAX_OPTIMAL_RESULTANTS:
            raise InputError(
                "ramp_fit",
                f"the optimal fit takes at most {defaults.MAX_OPTIMAL_RESULTANTS} resultants, the table has "
                f"{self.table.n_resultants}; use ols or group the reads into fewer resultants",
            )
        low_open = self.fit == "optimal"  # the optimal weights need sigma_read > 0 for empty pixels
        noise = check_number(self.read_noise_e, "read_noise", *defaults.READ_NOISE_RANGE_E, open_low=low_open)
        object.__setattr__(self, "read_noise_e", noise)

    @classmethod
    def uniform(
        cls, n: int, exptime_s: float, fit: str = "ols", read_noise_e: float | None = None, read_noise_source: str = ""
    ) -> Ramp:
        return cls(MATable.uniform(n, exptime_s), fit, read_noise_e, read_noise_source)

    def check_exposure(self, exptime_s: float) -> None:
        self.table.check_exposure(exptime_s, "ramp" if self.table.name.startswith("uniform-") else "ma_table")

    @property
    def is_uniform(self) -> bool:
        return all(len(r) == 1 and r[0] == j for j, r in enumerate(self.table.resultants, start=1))

    def quadratic_factor(self, exptime_s: float) -> float:
        """c_2 for a pixel that keeps every resultant under OLS: beta_eff / beta (exact; see the module)."""
        if self.fit != "ols":
            raise ValueError("beta_eff is exact only for the OLS fit")
        return self.ols_quadratic_factor(exptime_s)

    def ols_quadratic_factor(self, exptime_s: float) -> float:
        """c_2 of an OLS fit of this table, whatever the fit in use (an approximation for ``optimal``)."""
        return float(_ols_factors(self.table, exptime_s, (2,))[-1, 0])

    def first_usable_fraction(self, exptime_s: float) -> float:
        """tau of the last read of the first resultant: the charge there must stay under the full well."""
        return float(self.table.last_read_fractions(exptime_s)[0])

    def saturation_shift_mag(self, exptime_s: float) -> float:
        """How much brighter the ramp rule's saturation magnitude is than the final frame's:
        2.5 log10(T / t_1) with t_1 the last read of the first resultant."""
        return 2.5 * math.log10(1.0 / self.first_usable_fraction(exptime_s))

    def describe(self) -> str:
        t = self.table
        return (
            f"{t.name}: {t.n_resultants} resultants of {t.n_reads} reads, last read at {t.duration_s:.4g} s, "
            f"{self.fit.upper() if self.fit == 'ols' else 'optimally weighted'} slope fit"
        )

    def conditions(self, exptime_s: float) -> dict:
        out = {
            "ma_table": self.table.name,
            "source": self.table.source,
            "resultants": self.table.n_resultants,
            "reads": self.table.n_reads,
            "frame_time_s": self.table.frame_time_s,
            "last_read_s": self.table.duration_s,
            "first_resultant_end_s": self.table.resultants[0][-1] * self.table.frame_time_s,
            "fit": self.fit,
            "read_noise_e": self.read_noise_e,
            "read_noise_source": self.read_noise_source,
            "description": self.describe(),
            "saturation_rule": "resultants past the full well are dropped; a pixel saturated in its first resultant is unusable",
        }
        if self.fit == "ols":
            out["quadratic_beta_factor"] = self.quadratic_factor(exptime_s)
        if self.table.name not in {"custom"} and not self.table.name.startswith("uniform-"):
            out["read_pattern"] = [list(r) for r in self.table.resultants]
        return out


# --- kernels ----------------------------------------------------------------------------------


def polynomial_perturbation(charge: np.ndarray, coefficients: Sequence[float]) -> np.ndarray:
    """S - Q = -(b2 Q^2 + b3 Q^3 + ...) for ``coefficients`` = (b2, b3, ...)."""
    out = np.zeros_like(charge, dtype=np.float64)
    power = charge * charge
    for b in coefficients:
        out -= b * power
        power = power * charge
    return out


def polynomial_response(coefficients: Sequence[float]) -> Callable[[np.ndarray], np.ndarray]:
    """S(Q) = Q - b2 Q^2 - b3 Q^3 - ... (the paper's quadratic for ``(beta,)``)."""
    coefficients = tuple(float(b) for b in coefficients)
    return lambda charge: charge + polynomial_perturbation(charge, coefficients)


def usable_resultants(total_charge: np.ndarray, ramp: Ramp, exptime_s: float, full_well_e: float) -> np.ndarray:
    """Number k of leading resultants whose last read stays within the full well (0: unusable)."""
    last = ramp.table.last_read_fractions(exptime_s)
    with np.errstate(divide="ignore"):
        limit = np.where(total_charge > 0, full_well_e / np.asarray(total_charge, dtype=np.float64), np.inf)
    return np.searchsorted(last, limit, side="right").astype(np.int32)


def _resultant_fractions(table: MATable, exptime_s: float) -> np.ndarray:
    return table.mean_powers(exptime_s, (1,))[0]


def _ols_row(tau: np.ndarray, k: int) -> np.ndarray:
    """OLS slope weights on the first k resultants (zeros after); k = 1: the reset is the intercept."""
    out = np.zeros(tau.size)
    if k == 1:
        out[0] = 1.0 / tau[0]
    else:
        centred = tau[:k] - tau[:k].mean()
        out[:k] = centred / np.sum(centred**2)
    return out


def _ols_factors(table: MATable, exptime_s: float, orders: Sequence[int]) -> np.ndarray:
    """(K, orders): c_n = w_k . <tau^n> for every number k of usable resultants, in O(K) from running
    sums (sum_j (tau_j - mean) m_j / sum_j (tau_j - mean)^2), so long tables cost no K x K matrix."""
    tau = _resultant_fractions(table, exptime_s)
    powers = table.mean_powers(exptime_s, orders)  # (orders, K)
    k = np.arange(1, tau.size + 1, dtype=np.float64)
    # Centre on the full table's mean first: the running sums then carry no large common offset.
    shift = tau - tau.mean()
    s_shift = np.cumsum(shift)
    variance = np.cumsum(shift**2) - s_shift**2 / k
    covariance = np.cumsum(shift * powers, axis=1) - s_shift * np.cumsum(powers, axis=1) / k
    out = np.empty((tau.size, len(orders)))
    out[0] = powers[:, 0] / tau[0]
    if tau.size > 1:
        out[1:] = (covariance[:, 1:] / variance[1:]).T
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


def resultant_means(total_charge: np.ndarray, ramp: Ramp, exptime_s: float, response: Callable[[np.ndarray], np.ndarray]):
    """(..., K) resultants: every read evaluated through ``response`` and averaged (explicit)."""
    tau = ramp.table.read_fractions(exptime_s)
    reads = response(np.asarray(total_charge, dtype=np.float64)[..., None] * tau)
    return ramp.table.resultant_means(reads)


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
    usable = usable_resultants(total, ramp, exptime_s, full_well_e)
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
) -> tuple[np.ndarray, np.ndarray]:
    """(c_n per pixel, shape (orders, ...), usable resultants per pixel): see the module docstring.

    A pixel's NL term of order n in the fitted image is -b_n (q + b)^n c_n."""
    total = np.asarray(charge, dtype=np.float64) + background_e
    usable = usable_resultants(total, ramp, exptime_s, full_well_e)
    powers = ramp.table.mean_powers(exptime_s, orders)  # (orders, K)
    if ramp.fit == "ols":
        per_k = _ols_factors(ramp.table, exptime_s, orders)  # (K, orders)
        factors = np.moveaxis(per_k[np.maximum(usable, 1) - 1], -1, 0)
        return factors, usable
    # c_n = w . <tau^n> = h . (U <tau^n>): O(k) per pixel, the weights themselves are never formed.
    flat_total, flat_k = total.ravel(), np.maximum(usable, 1).ravel()
    out = np.empty((len(orders), flat_total.size))
    single = flat_k == 1
    out[:, single] = (powers[:, 0] / _resultant_fractions(ramp.table, exptime_s)[0])[:, None]
    for pick, k, h, U in _optimal_groups(flat_total, flat_k, ramp, exptime_s):
        out[:, pick] = (h @ (U @ powers[:, :k].T)).T
    return out.reshape(len(orders), *total.shape), usable


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
    factors, usable = order_factors(charge, ramp, exptime_s, full_well_e, orders, background_e)
    total = np.asarray(charge, dtype=np.float64) + background_e
    out = np.zeros_like(total)
    for b, n, c in zip(coefficients, orders, factors, strict=True):
        out -= b * total**n * c
    if background_e:
        sky, _ = order_factors(np.zeros(1), ramp, exptime_s, full_well_e, orders, background_e)
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


def build(
    reads: int | None = None,
    ma_table: str | Path | dict | MATable | None = None,
    fit: str = "ols",
    read_noise_e: float | None = None,
    exptime_s: float | None = None,
    allow_files: bool = True,
    sca: int = defaults.SCA,
) -> tuple[Ramp | None, float]:
    """The ramp a request asks for and the exposure time to use with it (one rule for every entry point).

    ``reads``: N uniform reads over the exposure (``--ramp N``); ``ma_table``: a table file or a
    shipped table's name (files only with ``allow_files``; the web service takes names or an inline
    object), an inline ``{"resultants": ..., "frame_time_s": ...}`` or an :class:`MATable`. Without
    an exposure time, an MA table's exposure is its last read and otherwise the paper's 168.1 s.
    Neither given: (None, exposure) -- the paper's single final frame.

    ``read_noise_e`` None (not given): the official read noise of ``sca`` (its median CDS noise /
    sqrt 2, ``backgrounds.read_noise``), named in the ramp's conditions.
    """
    if reads is not None and ma_table is not None:
        raise InputError("ma_table", "give either a uniform ramp (ramp = N reads) or an MA table, not both")
    if ma_table is None:
        exptime = defaults.EXPTIME_S if exptime_s is None else exptime_s
        if reads is None:
            return None, exptime
        ramp = Ramp.uniform(reads, exptime, fit, *_read_noise(read_noise_e, sca))
        return ramp, exptime
    if isinstance(ma_table, MATable):
        table = ma_table
    elif isinstance(ma_table, dict):
        table = MATable.from_dict(ma_table)
    elif not allow_files and (Path(str(ma_table)).suffix or "/" in str(ma_table) or "\\" in str(ma_table)):
        raise InputError("ma_table", f"give a shipped table's name ({', '.join(shipped_table_names())}) or the table itself")
    else:
        table = load_ma_table(ma_table)
    ramp = Ramp(table, fit, *_read_noise(read_noise_e, sca))
    exptime = table.duration_s if exptime_s is None else exptime_s
    check_number(exptime, "exptime", *defaults.EXPTIME_RANGE_S)
    ramp.check_exposure(exptime)
    return ramp, exptime


def _read_noise(given: float | None, sca: int) -> tuple[float | None, str]:
    """(read noise per read [e-], where it came from): the caller's, or the SCA's official one."""
    if given is not None:
        return given, "given"
    from . import backgrounds  # the official tables (astropy): only when no read noise is given

    return backgrounds.read_noise(sca), (
        f"official read noise of SCA {sca}: median CDS noise / sqrt(2), WFI_CDS_Noise_summary.ecsv ({backgrounds.SOURCE_VERSION})"
    )
