"""The ramp: an MA table, its fit and saturation rules, which resultants a pixel keeps under them, and
the one builder every entry point uses."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from nlpsf import defaults
from nlpsf.checks import InputError, SimulationError, check_number
from nlpsf.sim import detector

from .tables import MATable, _ols_factors, load_ma_table, shipped_table_names

#: Read noise per read of a :class:`Ramp` built without one and without an SCA (:func:`build`
#: looks up the SCA's official value instead); it only matters for the ``optimal`` fit.
DEFAULT_READ_NOISE_E = defaults.READ_NOISE_E
RAMP_FITS = defaults.RAMP_FITS


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
        # ``table.last_read_fractions(exptime_s)[k]`` of the one resultant k, in the same arithmetic.
        resultant = self.table.resultants[min(self.min_usable, self.table.n_resultants) - 1]
        return float(resultant[-1]) * self.table.frame_time_s / exptime_s

    def limit_charge(self, exptime_s: float, full_well_e: float, beta: float = 0.0, background_e: float = 0.0) -> float:
        """The star's final-frame charge [e-] in a pixel (background ``background_e`` on top) above which
        that pixel keeps fewer resultants than a slope needs, under this ramp's rules with the raw
        quadratic NL ``beta`` (``saturation_beta`` wins when set). Exact for either rule (bisection on
        :func:`usable_resultants`, which only ever loses resultants as the charge grows; memoised, as
        a solve asks for the same limit at every position it checks)."""
        return _limit_charge(self, float(exptime_s), float(full_well_e), float(beta), float(background_e))

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

    def check_saturates(self, full_well_e: float, beta: float, field: str = "beta0") -> None:
        """Refuse a quadratic NL under which no pixel's signal ever reaches the saturation step's
        threshold (the "signal" rule): S = Q - beta Q^2 peaks at 1 / (4 beta), so with 4 beta (full
        well) > 1 no charge is flagged, and the quadratic model is invalid past its turnover anyway."""
        beta = self.saturation_beta if self.saturation_beta is not None else beta
        if self.saturation != "signal" or beta <= 0 or 4.0 * beta * full_well_e <= 1.0:
            return
        raise InputError(
            field,
            f"up the ramp a resultant is flagged saturated when its signal reaches the full well ({full_well_e:g} e-), but "
            f"with beta {beta:g} /e- the quadratic response Q - beta Q^2 peaks at 1/(4 beta) = {0.25 / beta:.4g} e-, below "
            f"it: no charge ever saturates and the quadratic model is invalid past its peak; give beta0 at most "
            f"{0.25 / full_well_e:.4g} /e- for this full well (or a lower full well)",
        )

    def check_gives_slopes(self) -> None:
        """Refuse a table that gives no pixel a slope under its one-resultant rule: one resultant
        under ``single_resultant="unusable"`` (romancal's: stcal's fits need two resultants), where
        every pixel, however faint, is unusable and no star has an answer. Under ``"through_zero"``
        a one-resultant table gives every pixel the slope S_1 / t_1 (docs/ramps.md)."""
        if self.table.n_resultants < self.min_usable:
            field = "ramp" if self.table.name.startswith("uniform-") else "ma_table"
            raise InputError(
                field,
                f"a table of {self.table.n_resultants} resultant gives no pixel a slope under the one-resultant rule "
                f"{self.single_resultant!r} (romancal's: a slope needs two resultants, so every pixel is unusable); give "
                "at least two resultants, or the rule 'through_zero' (slope S_1 / t_1) where the entry point takes it",
            )

    def conditions(self, exptime_s: float) -> dict:
        """What an answer states of its readout at ``exptime_s``: worked out once for each (ramp,
        exposure) -- the ramp is frozen, its description a pure function of it -- and handed out as
        a dict of its own (its read pattern's lists too)."""
        try:  # keyed by what the ramp compares by and by its read noise's source, which it does not
            kept = _conditions(self, self.read_noise_source, exptime_s)
        except TypeError:  # a ramp holding something unhashable: worked out afresh
            return self._conditions(exptime_s)
        out = dict(kept)
        if "read_pattern" in kept:
            out["read_pattern"] = [list(r) for r in kept["read_pattern"]]
        return out

    def _conditions(self, exptime_s: float) -> dict:
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


@lru_cache(maxsize=1024)
def _conditions(ramp: Ramp, read_noise_source: str, exptime_s: float) -> dict:
    """:meth:`Ramp.conditions`, kept (read-only: each caller gets its own copy). ``read_noise_source``:
    the ramp's own, in the key (equal ramps of two SCAs with the same read noise differ there)."""
    return ramp._conditions(exptime_s)


#: Doublings of the bracket of :func:`_limit_charge` from its first guess (2^64: far past any well).
_MAX_DOUBLINGS = 64


@lru_cache(maxsize=1024)
def _limit_charge(ramp: Ramp, exptime_s: float, full_well_e: float, beta: float, background_e: float) -> float:
    """:meth:`Ramp.limit_charge` (a pure function of a frozen ramp and four numbers)."""
    ramp.check_gives_slopes()  # else no charge keeps a slope and the limit would be 0
    ramp.check_saturates(full_well_e, beta)  # else every charge keeps its resultants: no limit to find
    needed = ramp.min_usable

    def keeps(q: float) -> bool:
        return bool(usable_resultants(np.array([q + background_e]), ramp, exptime_s, full_well_e, (beta,))[0] >= needed)

    low = 0.0
    high = max(full_well_e, 1.0) / ramp.first_usable_fraction(exptime_s)
    for _ in range(_MAX_DOUBLINGS):
        if not keeps(high):
            break
        low, high = high, 2 * high
    else:  # every rule above loses resultants well before this (a guard, never an answer)
        raise SimulationError(f"no final-frame charge up to {high:.3g} e- loses a resultant under {ramp.describe()}")
    for _ in range(200):
        middle = 0.5 * (low + high)
        if middle in (low, high):
            break
        low, high = (middle, high) if keeps(middle) else (low, middle)
    return low


# --- what a read reports and which resultants a pixel keeps ------------------------------------


polynomial_perturbation = detector.coefficients_perturbation  # the one NL polynomial (nlpsf.sim.detector)


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


def resultant_means(total_charge: np.ndarray, ramp: Ramp, exptime_s: float, response: Callable[[np.ndarray], np.ndarray]):
    """(..., K) resultants: every read evaluated through ``response`` and averaged (explicit)."""
    tau = ramp.table.read_fractions(exptime_s)
    reads = response(np.asarray(total_charge, dtype=np.float64)[..., None] * tau)
    return ramp.table.resultant_means(reads)


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
        ramp.check_gives_slopes()
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
    ramp.check_gives_slopes()
    exptime = table.duration_s if exptime_s is None else exptime_s
    check_number(exptime, "exptime", *defaults.EXPTIME_RANGE_S)
    ramp.check_exposure(exptime)
    return ramp, exptime


def _read_noise(given: float | None, sca: int) -> tuple[float | None, str]:
    """(read noise per read [e-], where it came from): the caller's, or the SCA's official one."""
    if given is not None:
        return given, "given"
    from nlpsf.roman import backgrounds  # the official tables (astropy): only when no read noise is given

    return backgrounds.read_noise(sca), (
        f"official read noise of SCA {sca}: median CDS noise / sqrt(2), WFI_CDS_Noise_summary.ecsv ({backgrounds.SOURCE_VERSION})"
    )
