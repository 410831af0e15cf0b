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

from . import defaults, detector
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
#: How a resultant is judged saturated. "charge": the charge at its last read passed the full well
#: (nlpsf's original rule). "signal": romancal's saturation step (stcal ``flag_saturated_pixels``
#: with the read pattern, no flag growth): the resultant's *signal* (the mean of the reads' S) against
#: the per-pixel threshold, with stcal's dilution and second-resultant passes (see ``signal_usable``).
SATURATION_RULES: tuple[str, ...] = ("charge", "signal")
#: A pixel left with one usable resultant. "through_zero": slope S_1 / tau_1 (the reset level taken
#: as zero; nlpsf's original rule). "unusable": no slope, as romancal's ramp fits do (stcal's
#: likelihood fit has no resultant difference to fit and ols_cas22 returns NaN for a one-resultant
#: ramp), so the pixel is flagged do-not-use.
SINGLE_RESULTANT_RULES: tuple[str, ...] = ("through_zero", "unusable")


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
        data = json.loads((shipped_table_dir() / f"{name}.json").read_text())
        # A shipped table answers to its file name and to the names its source gives it (C2A_IMG_HLWAS).
        if key in {name.lower(), *(alias.lower() for alias in data.get("aliases", ()))}:
            return MATable.from_dict(data, name=name)
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
    #: :data:`SATURATION_RULES`; the threshold is the full well, read as the saturation level in
    #: signal e- for "signal" (romanisim: 55000 DN at 2 e-/DN = 1.1e5 e-, the paper's full well).
    #: The default follows romancal; "charge" is nlpsf's rule before it.
    saturation: str = "signal"
    #: :data:`SINGLE_RESULTANT_RULES`; the default follows romancal, "through_zero" is nlpsf's rule before it.
    single_resultant: str = "unusable"
    #: The raw detector's quadratic NL (paper convention, 1/e-) that the saturation step sees under
    #: the "signal" rule (it runs before the linearity correction); None: the NL being simulated.
    saturation_beta: float | None = None

    def __post_init__(self) -> None:
        if self.saturation not in SATURATION_RULES:
            raise InputError("ramp_saturation", f"must be one of {', '.join(SATURATION_RULES)}, got {self.saturation!r}")
        if self.single_resultant not in SINGLE_RESULTANT_RULES:
            raise InputError(
                "ramp_single_resultant", f"must be one of {', '.join(SINGLE_RESULTANT_RULES)}, got {self.single_resultant!r}"
            )
        if self.saturation_beta is not None:
            limit = defaults.MAX_ABS_BETA
            object.__setattr__(self, "saturation_beta", check_number(self.saturation_beta, "saturation_beta", -limit, limit))
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
        cls,
        n: int,
        exptime_s: float,
        fit: str = "ols",
        read_noise_e: float | None = None,
        read_noise_source: str = "",
        **rules,
    ) -> Ramp:
        """``rules``: ``saturation``, ``single_resultant``, ``saturation_beta`` (the fields)."""
        return cls(MATable.uniform(n, exptime_s), fit, read_noise_e, read_noise_source, **rules)

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
        """tau of the last read of the last resultant a slope needs (the first; the second when one
        resultant gives no slope): the charge there must stay under the full well. Exact for the
        "charge" rule; for "signal" the limit of a linear detector (the NL lowers the signal, so a
        star with beta > 0 keeps its resultants slightly longer)."""
        return float(self.table.last_read_fractions(exptime_s)[min(self.min_usable, self.table.n_resultants) - 1])

    def limit_charge(self, exptime_s: float, full_well_e: float, beta: float = 0.0, background_e: float = 0.0) -> float:
        """The star's final-frame charge [e-] in a pixel (background ``background_e`` on top) above which
        that pixel keeps fewer resultants than a slope needs, under this ramp's rules with the raw
        quadratic NL ``beta`` (``saturation_beta`` wins when set). Exact for either rule (bisection on
        :func:`usable_resultants`, which only ever loses resultants as the charge grows)."""
        needed = min(self.min_usable, self.table.n_resultants)

        def keeps(q: float) -> bool:
            return bool(usable_resultants(np.array([q + background_e]), self, exptime_s, full_well_e, (beta,))[0] >= needed)

        low = 0.0
        high = max(full_well_e, 1.0) / self.first_usable_fraction(exptime_s)
        while keeps(high):
            low, high = high, 2 * high
        for _ in range(200):
            middle = 0.5 * (low + high)
            if middle in (low, high):
                break
            low, high = (middle, high) if keeps(middle) else (low, middle)
        return low

    def saturation_shift_mag(
        self, exptime_s: float, full_well_e: float | None = None, beta: float = 0.0, background_e: float = 0.0
    ) -> float:
        """How much brighter the ramp rule's saturation magnitude is than the final frame's.

        Without ``full_well_e``: 2.5 log10(T / t_k) with t_k the last read of the last resultant a
        slope needs, the limit of a linear detector judged by its charge. With it: exact for this
        ramp's rules, 2.5 log10(:meth:`limit_charge` / (full well - background)), the final frame's
        limit being a peak charge of full well - background (the "signal" rule's NL lowers the signal,
        so that star is a little brighter than the linear estimate)."""
        if full_well_e is not None:
            limit = self.limit_charge(exptime_s, full_well_e, beta, background_e)
            return 2.5 * math.log10(limit / (full_well_e - background_e))
        return 2.5 * math.log10(1.0 / self.first_usable_fraction(exptime_s))

    def describe(self) -> str:
        t = self.table
        return (
            f"{t.name}: {t.n_resultants} resultants of {t.n_reads} reads, last read at {t.duration_s:.4g} s, "
            f"{self.fit.upper() if self.fit == 'ols' else 'optimally weighted'} slope fit"
        )

    def saturation_rule(self) -> str:
        if self.saturation == "charge":
            rule = "resultants whose last read's charge passes the full well are dropped"
        else:
            rule = (
                "resultants flagged as romancal's saturation step does (stcal flag_saturated_pixels, read pattern, no growth): "
                "signal >= the saturation level, and the dilution and second-resultant passes"
            )
        single = (
            "a pixel with one usable resultant is fitted through zero (S_1 / t_1)"
            if self.single_resultant == "through_zero"
            else "a pixel with fewer than two usable resultants has no slope (romancal) and is unusable"
        )
        return f"{rule}; {single}; a pixel saturated in its first resultant is unusable"

    @property
    def min_usable(self) -> int:
        """Fewest usable resultants that give a slope."""
        return 1 if self.single_resultant == "through_zero" else 2

    def conditions(self, exptime_s: float) -> dict:
        out = {
            "ma_table": self.table.name,
            "source": self.table.source,
            "resultants": self.table.n_resultants,
            "reads": self.table.n_reads,
            "frame_time_s": self.table.frame_time_s,
            "last_read_s": self.table.duration_s,
            "first_resultant_end_s": self.table.resultants[0][-1] * self.table.frame_time_s,
            # The resultant a slope needs (the first, or the second where one resultant gives no slope)
            # and when it ends: a star is usable until its brightest pixel saturates there.
            "limit_resultant": min(self.min_usable, self.table.n_resultants),
            "limit_resultant_end_s": self.first_usable_fraction(1.0),
            "fit": self.fit,
            "read_noise_e": self.read_noise_e,
            "read_noise_source": self.read_noise_source,
            "description": self.describe(),
            "saturation_rule": self.saturation_rule(),
            "saturation": self.saturation,
            "single_resultant": self.single_resultant,
        }
        if self.saturation_beta is not None:
            out["saturation_beta"] = self.saturation_beta
        if self.fit == "ols":
            out["quadratic_beta_factor"] = self.quadratic_factor(exptime_s)
        if self.table.name not in {"custom"} and not self.table.name.startswith("uniform-"):
            out["read_pattern"] = [list(r) for r in self.table.resultants]
        return out


# --- kernels ----------------------------------------------------------------------------------


polynomial_perturbation = detector.coefficients_perturbation  # the one NL polynomial (nlpsf.detector)


def polynomial_response(coefficients: Sequence[float]) -> Callable[[np.ndarray], np.ndarray]:
    """S(Q) = Q - b2 Q^2 - b3 Q^3 - ... (the paper's quadratic for ``(beta,)``)."""
    coefficients = tuple(float(b) for b in coefficients)
    return lambda charge: charge + polynomial_perturbation(charge, coefficients)


def usable_resultants(
    total_charge: np.ndarray,
    ramp: Ramp,
    exptime_s: float,
    full_well_e: float,
    state: Sequence[float] = (),
) -> np.ndarray:
    """Number k of leading resultants the fit uses (0: unusable), by ``ramp.saturation``.

    "charge": the last read's charge stays within the full well. "signal": :func:`signal_usable` on
    the resultants of the response S = Q - b2 Q^2 - ... with ``state`` = (b2, b3, ...), the NL the
    saturation step sees (``ramp.saturation_beta`` replaces b2 when set). With
    ``single_resultant="unusable"`` a pixel left with one resultant is unusable too (k = 0)."""
    total = np.asarray(total_charge, dtype=np.float64)
    if ramp.saturation == "charge":
        last = ramp.table.last_read_fractions(exptime_s)
        with np.errstate(divide="ignore"):
            limit = np.where(total > 0, full_well_e / total, np.inf)
        usable = np.searchsorted(last, limit, side="right").astype(np.int32)
    else:
        state = tuple(state)
        if ramp.saturation_beta is not None:
            state = (ramp.saturation_beta, *state[1:])
        usable = np.full(total.shape, ramp.table.n_resultants, dtype=np.int32)
        # Only pixels whose signal can reach the threshold need their reads: while S(Q) rises, the
        # largest read is the last (S at the full charge); Q itself bounds S where beta >= 0, and a
        # falling S (past 1 - 2 beta Q = 0) only happens far above any threshold a well allows.
        response = polynomial_response(state)
        candidates = (total >= full_well_e) | (response(total) >= full_well_e)
        if np.any(candidates):
            signal = resultant_means(total[candidates], ramp, exptime_s, response)
            usable[candidates] = signal_usable(signal, ramp.table, full_well_e)
    if ramp.single_resultant == "unusable":
        usable = np.where(usable == 1, 0, usable).astype(np.int32)
    return usable


def signal_usable(resultants: np.ndarray, table: MATable, threshold: float) -> np.ndarray:
    """Leading resultants left unflagged by romancal's saturation step, (..., K) -> (...).

    romancal calls stcal's ``flag_saturated_pixels`` with the read pattern and ``n_pix_grow_sat=0``
    (romancal/saturation/saturation.py); for one pixel's noiseless resultants R_j that is:

    1. R_j >= threshold flags resultant j and every later one SATURATED;
    2. going backwards, resultant j (not yet flagged, the next one SATURATED) is flagged DO_NOT_USE
       when R_j >= threshold * mean(reads of j) / last(read of j) (its last reads may have saturated
       while the mean stayed below; skipped when the dilution factor is 1);
    3. with more than two resultants, the second is flagged DO_NOT_USE when the first, extrapolated
       to the end of the third, stays below the threshold, R_2 - R_1 > (threshold - R_1) / n_2, and
       the third is SATURATED but the second is not (no bias: romancal passes none).

    Flags only ever cover a tail of the ramp, so the usable resultants are the leading unflagged ones.
    (The A/D-floor flag, R <= 0, is not applied: a real ramp sits on a reset level far above zero.)
    """
    R = np.asarray(resultants, dtype=np.float64)
    K = table.n_resultants
    saturated = np.maximum.accumulate(threshold <= R, axis=-1)
    flagged = saturated.copy()
    for j in range(K - 2, -1, -1):
        reads = table.resultants[j]
        dilution = float(np.mean(reads)) / reads[-1]
        if dilution == 1:
            continue
        flagged[..., j] |= (R[..., j] >= threshold * dilution) & ~flagged[..., j] & saturated[..., j + 1]
    if K > 2:
        first, second = table.resultants[0], table.resultants[1]
        extrapolated = R[..., 0] / np.mean(first) * table.resultants[2][-1] < threshold
        jumped = R[..., 1] - R[..., 0] > (threshold - R[..., 0]) / len(second)
        flagged[..., 1] |= extrapolated & jumped & saturated[..., 2] & ~saturated[..., 1]
    # k = index of the first flagged resultant (K when none is).
    return np.where(flagged.any(axis=-1), np.argmax(flagged, axis=-1), K).astype(np.int32)


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
        for s in range(0, size, _BLOCK):
            pick = slice(s, s + _BLOCK) if where is None else where[s : s + _BLOCK]
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


def build(
    reads: int | None = None,
    ma_table: str | Path | dict | MATable | None = None,
    fit: str = "ols",
    read_noise_e: float | None = None,
    exptime_s: float | None = None,
    allow_files: bool = True,
    sca: int = defaults.SCA,
    saturation: str = "signal",
    single_resultant: str = "unusable",
) -> tuple[Ramp | None, float]:
    """The ramp a request asks for and the exposure time to use with it (one rule for every entry point).

    ``reads``: N uniform reads over the exposure (``--ramp N``); ``ma_table``: a table file or a
    shipped table's name (files only with ``allow_files``; the web service takes names or an inline
    object), an inline ``{"resultants": ..., "frame_time_s": ...}`` or an :class:`MATable`. Without
    an exposure time, an MA table's exposure is its last read and otherwise the paper's 168.1 s.
    Neither given: (None, exposure) -- the paper's single final frame.

    ``read_noise_e`` None (not given): the official read noise of ``sca`` (its median CDS noise /
    sqrt 2, ``backgrounds.read_noise``), named in the ramp's conditions. ``saturation`` and
    ``single_resultant``: the ramp's rules (:data:`SATURATION_RULES`, :data:`SINGLE_RESULTANT_RULES`;
    romancal's by default).
    """
    rules = {"saturation": saturation, "single_resultant": single_resultant}
    if reads is not None and ma_table is not None:
        raise InputError("ma_table", "give either a uniform ramp (ramp = N reads) or an MA table, not both")
    if ma_table is None:
        exptime = defaults.EXPTIME_S if exptime_s is None else exptime_s
        if reads is None:
            return None, exptime
        ramp = Ramp.uniform(reads, exptime, fit, *_read_noise(read_noise_e, sca), **rules)
        return ramp, exptime
    if isinstance(ma_table, MATable):
        table = ma_table
    elif isinstance(ma_table, dict):
        table = MATable.from_dict(ma_table)
    elif not allow_files and (Path(str(ma_table)).suffix or "/" in str(ma_table) or "\\" in str(ma_table)):
        raise InputError("ma_table", f"give a shipped table's name ({', '.join(shipped_table_names())}) or the table itself")
    else:
        table = load_ma_table(ma_table)
    ramp = Ramp(table, fit, *_read_noise(read_noise_e, sca), **rules)
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


# --- ramps inside a scene (IPC, background, polynomial NL) -------------------------------------

#: Scene effects an up-the-ramp readout does not combine with yet, and why (the one place that says so).
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

    def head(self, count: int) -> SceneRamp:
        """The first ``count`` realizations."""
        coupled = None if self.coupled is None else {n: v[:count] for n, v in self.coupled.items()}
        whole = None if self.whole is None else (lambda: self.whole().head(count))
        return SceneRamp(
            self.factors[:, :count], self.usable[:count], self.charge[:count], self.orders, coupled, self.margin, whole
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


def _ipc(images: np.ndarray, kernel, oversampling: int) -> np.ndarray:
    from .scene import apply_ipc  # scene effects have one owner

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
) -> tuple[SceneRamp, np.ndarray]:
    """:func:`scene_factors` for IPC after the NL, on Q = ``scale`` psi + ``background`` (psi the unit
    stamps of ``powers``, realizations ``pick``), with every coupled image from ``powers``; and the
    usable resultants of every pixel of the whole stamps.

    ``margin`` > 0: the factors (the per-pixel optimal weights, most of the cost), the charge and its
    coupled powers only on the stamps' central core, ``margin`` pixels in from every side (outside the
    moments' weight window they multiply nothing); the SceneRamp's ``whole`` computes the rest.

    Under the "signal" rule each read's coupled signal is D(tau) = tau IPC(Q) - sum_n b_n tau^n IPC(Q^n)
    (IPC is linear and the NL a polynomial), so resultant j is IPC(Q) <tau>_j - sum_n b_n IPC(Q^n) <tau^n>_j:
    the same resultants as coupling every read (:func:`_usable_after_ipc`), from one coupled image per order."""
    total = scale * powers.unit[pick] + background
    orders = tuple(orders)
    n = total.shape[-1]
    core = (Ellipsis, slice(margin, n - margin), slice(margin, n - margin))
    rows = pick if margin == 0 else (pick, slice(margin, n - margin), slice(margin, n - margin))
    if ramp.saturation == "charge":
        usable = usable_resultants(total, ramp, exptime_s, full_well_e, state)
    elif powers.below(scale, background, full_well_e, state, pick, ramp.saturation_beta):
        usable = np.full(total.shape, _all_kept(ramp), dtype=np.int32)
    else:
        measured = powers.at(scale, background, 1, pick)
        usable = _usable_coupled(powers, scale, background, measured, ramp, exptime_s, full_well_e, state, pick)
    factors = _factors_for(powers.at(scale, background, 1, rows), usable[core], ramp, exptime_s, orders)
    coupled = {n: powers.at(scale, background, n, rows) for n in orders}
    whole = None
    if margin:
        args = (powers, scale, background, ramp, exptime_s, full_well_e, state, orders, pick)
        whole = lambda: scene_factors_coupled(*args)[0]  # noqa: E731
    return SceneRamp(factors, usable[core], total[core], orders, coupled, margin, whole), usable


def _all_kept(ramp: Ramp) -> int:
    """Usable resultants of a pixel that saturates in none (the one-resultant rule applied)."""
    K = ramp.table.n_resultants
    return 0 if K == 1 and ramp.single_resultant == "unusable" else K


def _usable_coupled(powers: CoupledPowers, scale, background, measured, ramp: Ramp, exptime_s, threshold, state, pick):
    """The "signal" rule on coupled reads, each resultant from the coupled powers (see above)."""
    state = tuple(state)
    if ramp.saturation_beta is not None:
        state = (ramp.saturation_beta, *state[1:])
    state_orders = range(2, 2 + len(state))
    terms = [(b, n, powers.at(scale, background, n, pick)) for b, n in zip(state, state_orders, strict=True) if b != 0]
    final = measured
    for b, _, coupled in terms:
        final = final - b * coupled
    usable = np.full(measured.shape, ramp.table.n_resultants, dtype=np.int32)
    # As in usable_resultants: only pixels whose measured signal can reach the threshold need their resultants.
    candidates = (measured >= threshold) | (final >= threshold)
    if np.any(candidates):
        mean_tau = ramp.table.mean_powers(exptime_s, (1, *(n for _, n, _ in terms)))
        resultants = measured[candidates][:, None] * mean_tau[0]
        for row, (b, _, coupled) in enumerate(terms, start=1):
            resultants = resultants - b * coupled[candidates][:, None] * mean_tau[row]
        usable[candidates] = signal_usable(resultants, ramp.table, threshold)
    if ramp.single_resultant == "unusable":
        usable = np.where(usable == 1, 0, usable).astype(np.int32)
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
    power = q * q
    derivative = None
    for n, b in zip(range(2, 2 + len(coefficients)), coefficients, strict=True):
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
        power = power * q
    return perturbation, derivative
