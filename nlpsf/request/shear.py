"""From a shear-bias budget to the PSF tolerance: how a PSF-model error becomes a shear error.

Weak-lensing requirements are written as budgets for the multiplicative and additive shear bias,
γ̂ = (1 + m) γ + c (Heymans et al. 2006). A PSF-model error enters a moment-corrected shape as
(Paulin-Henriksson et al. 2008, A&A 484, 67, section 2; Massey et al. 2013, MNRAS 429, 661,
section 2)

    m = ⟨(R²_psf / R²_gal)⟩ · δ(R²_psf) / R²_psf,     c = ⟨(R²_psf / R²_gal)⟩ · δe_psf  (up to the responsivity),

with R² a *trace* size. Here are the factors for OUR definitions, derived so that nothing is
borrowed from a different convention.

Definitions (``nlpsf.sim.moments``): M the second-moment matrix (adaptive moments; for a Gaussian
profile they are its covariance, and for unweighted moments everything below is exact), the
trace T = Mxx + Myy, the distortion e = (Mxx − Myy, 2 Mxy) / T (a "χ"-type ellipticity), and the
size R = det(M)^(1/4), i.e. R² = sqrt(det M), *not* the trace. Because det M = (T²/4)(1 − |e|²),

    T = 2 R² / sqrt(1 − |e|²)   and   δT/T = 2 δR/R + |e| δ|e| / (1 − |e|²).

PSF correction by moments. The observed galaxy is the intrinsic (pre-PSF) galaxy convolved with
the PSF, and second moments add: M_obs = M_gal + M_psf. Correcting with a PSF model
M_psf + δM_psf gives M̂_gal = M_gal − δM_psf. To first order in δM_psf,

    ê_gal = e_gal (1 + (T_psf/T_gal) δT_psf/T_psf) − (T_psf/T_gal) (δe_psf + e_psf δT_psf/T_psf).

The shear estimate is ê_gal divided by the responsivity P (for a χ-type ellipticity, e ≈ 2γ for a
round source, so P = 2; for a population of intrinsic ellipticity rms e_rms per component
P = 2 (1 − e_rms²), Bernstein & Jarvis 2002, AJ 123, 583, section 5). A multiplicative error of
ê_gal is a multiplicative error of γ̂ whatever P is; an additive one is divided by P. Hence, with
the size ratio ρ = R_gal / R_psf (both R = det(M)^(1/4); R_gal the *intrinsic*, pre-PSF galaxy):

    m = (T_psf/T_gal) δT_psf/T_psf  ≈ (2 / ρ²) · ΔR/R                (size metric)
    c = −(T_psf/T_gal) δe_psf / P    ≈ −(1 / (P ρ²)) · Δe_i           (e1, e2; e: the modulus)

to first order in the PSF error and in the ellipticities: T_psf/T_gal = ρ⁻² · sqrt(1 − |e_gal|²) /
sqrt(1 − |e_psf|²) = ρ⁻² (1 + O(e²)), and δT/T = 2 ΔR/R + O(e δe). The cross term −(T_psf/T_gal)
e_psf δT/T / P (an additive bias from a *size* error of an elliptical PSF) belongs to the size
budget's side and is of order e_psf · ΔR/R: it is left out here and named in the answer.

So the tolerances are

    ΔR/R = |m| ρ² / 2,        Δe = P |c| ρ²   (P = 2 by default: Δe = 2 |c| ρ²).

A distribution of galaxy sizes. m and c are averages over the galaxies used for shear, weighted
by their shear weights w; both are linear in ρ⁻², so a distribution acts through the effective
ratio ρ_eff = ⟨ρ⁻²⟩_w^(−1/2) (small galaxies dominate). ``SizeRatio`` holds the ratios and weights.

The test (tests/library/test_shear.py) simulates a Gaussian galaxy convolved with a Gaussian PSF, measures
it with our adaptive moments, corrects with a PSF model with and without a size or ellipticity
error, and checks m and c against these formulas to their stated order (1 %, for errors of 1e-3
and |e_psf| <= 0.06); GalSim's HSM PSF corrections (BJ, REGAUSS, KSB) of the same galaxies agree too.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from pathlib import Path

from nlpsf.checks import InputError, check_number, shown
from nlpsf.flags import CATALOGUE, FlagCode

#: Responsivity of a χ-type (distortion) ellipticity to shear for a round source: e = 2 γ.
RESPONSIVITY = 2.0
#: Accepted range of a shear-bias budget |m| or |c| (above 1 the first-order propagation is meaningless).
BUDGET_RANGE = (1e-12, 1.0)
#: Accepted range of R_gal / R_psf.
SIZE_RATIO_RANGE = (1e-3, 1e3)
#: Ratios in one distribution at most.
MAX_SIZE_RATIOS = 100_000
#: Largest weight: sums of up to MAX_SIZE_RATIOS weights / ratio^2 stay far from float overflow.
MAX_WEIGHT = 1e100
#: Which budget goes with which metric.
BUDGET_FOR_METRIC = {"size": "m", "e1": "c", "e2": "c", "e": "c"}

#: The cross term an e budget leaves out (the flag ``shear_cross_term`` says it; nlpsf.flags owns the text).
CROSS_TERM_NOTE = CATALOGUE[FlagCode.SHEAR_CROSS_TERM].template


@dataclass(frozen=True)
class SizeRatio:
    """Galaxy-to-PSF size ratios ρ = R_gal / R_psf (intrinsic galaxy, R = det(M)^(1/4)) and weights."""

    ratios: tuple[float, ...]
    weights: tuple[float, ...]

    @property
    def effective(self) -> float:
        """ρ_eff = ⟨ρ⁻²⟩_w^(−1/2): the single ratio giving the same mean m and c."""
        total = math.fsum(self.weights)
        mean_inverse_square = math.fsum(w / r**2 for r, w in zip(self.ratios, self.weights, strict=True)) / total
        return 1.0 / math.sqrt(mean_inverse_square)

    def to_dict(self) -> float | dict:
        """One number for a single ratio, else the distribution and its effective ratio."""
        if len(self.ratios) == 1:
            return self.ratios[0]
        return {"ratios": list(self.ratios), "weights": list(self.weights), "effective": self.effective}


def check_size_ratio(value, name: str = "size_ratio") -> SizeRatio:
    """A ratio, or a distribution of them, from what a user may give.

    Accepted: a number; a list of numbers (equal weights); a list of (ratio, weight) pairs; a
    ``{"ratios": [...], "weights": [...]}`` mapping; a string holding any of ``"1.5"``,
    ``"1.2:0.3,1.5:0.5,2:0.2"`` (ratio:weight, comma separated; a bare ratio weighs 1) or
    ``"@FILE"`` (a text file of lines ``ratio [weight]``, separated by spaces or a comma, ``#``
    comments); or a :class:`SizeRatio`.
    """
    if isinstance(value, SizeRatio):
        pairs = list(zip(value.ratios, value.weights, strict=True))
    elif isinstance(value, str):
        pairs = _parse_text(value, name)
    elif isinstance(value, dict):
        if set(value) - {"ratios", "weights"} or "ratios" not in value:
            raise InputError(name, f"a mapping needs 'ratios' and optionally 'weights', got keys {sorted(value)}")
        ratios = list(value["ratios"])
        weights = list(value.get("weights") or [1.0] * len(ratios))
        if len(weights) != len(ratios):
            raise InputError(name, f"{len(ratios)} ratios but {len(weights)} weights")
        pairs = list(zip(ratios, weights, strict=True))
    elif isinstance(value, numbers.Real) and not isinstance(value, bool):
        pairs = [(value, 1.0)]
    elif isinstance(value, (list, tuple)):
        pairs = [tuple(item) if isinstance(item, (list, tuple)) else (item, 1.0) for item in value]
        if any(len(p) != 2 for p in pairs):
            raise InputError(name, "each entry must be a ratio or a (ratio, weight) pair")
    else:
        raise InputError(name, f"must be a number, a list of ratios or (ratio, weight) pairs, got {shown(value)}")
    if not pairs:
        raise InputError(name, "give at least one ratio")
    if len(pairs) > MAX_SIZE_RATIOS:
        raise InputError(name, f"at most {MAX_SIZE_RATIOS} ratios, got {len(pairs)}")
    ratios = tuple(check_number(r, name, *SIZE_RATIO_RANGE) for r, _ in pairs)
    weights = tuple(check_number(w, name, 0.0, MAX_WEIGHT) for _, w in pairs)
    if math.fsum(weights) <= 0:
        raise InputError(name, "the weights sum to zero")
    return SizeRatio(ratios, weights)


def _parse_text(text: str, name: str) -> list[tuple[float, float]]:
    text = text.strip()
    if text.startswith("@"):
        path = Path(text[1:]).expanduser()
        try:
            lines = path.read_text().splitlines()
        except OSError as error:
            raise InputError(name, f"cannot read {path}: {error.strerror or error}") from None
        entries = [line.split("#", 1)[0].replace(",", " ").split() for line in lines]
        entries = [e for e in entries if e]
    else:
        entries = [item.split(":") for item in text.split(",") if item.strip()]
    pairs = []
    for entry in entries:
        if len(entry) not in (1, 2):
            raise InputError(name, f"expected 'ratio' or 'ratio weight', got {shown(' '.join(entry))}")
        try:
            numbers_ = [float(x) for x in entry]
        except ValueError:
            raise InputError(name, f"not a number in {shown(':'.join(entry))}") from None
        pairs.append((numbers_[0], numbers_[1] if len(numbers_) == 2 else 1.0))
    return pairs


def check_budget(value, name: str) -> float:
    """|m| or |c|: the sign of a budget does not matter for a tolerance."""
    number = check_number(value, name)
    return check_number(abs(number), name, *BUDGET_RANGE)


def size_tolerance(m: float, size_ratio: SizeRatio) -> float:
    """ΔR/R of the PSF model that produces a multiplicative shear bias |m|: |m| ρ_eff² / 2."""
    return abs(m) * size_ratio.effective**2 / 2.0


def ellipticity_tolerance(c: float, size_ratio: SizeRatio, responsivity: float = RESPONSIVITY) -> float:
    """Δe (one component, or the modulus) that produces an additive shear bias |c|: P |c| ρ_eff²."""
    return responsivity * abs(c) * size_ratio.effective**2


def multiplicative_bias(d_r_over_r: float, size_ratio: SizeRatio) -> float:
    """m from a PSF size error ΔR/R (sign as derived: a PSF model too large, ΔR/R > 0, gives m > 0)."""
    return 2.0 * d_r_over_r / size_ratio.effective**2


def additive_bias(d_e: float, size_ratio: SizeRatio, responsivity: float = RESPONSIVITY) -> float:
    """c from a PSF ellipticity error Δe (a model too elongated along +e gives c < 0)."""
    return -d_e / (responsivity * size_ratio.effective**2)


@dataclass(frozen=True)
class Budget:
    """A shear-bias budget for one metric and the PSF tolerance it implies."""

    kind: str  # "m" or "c"
    value: float
    size_ratio: SizeRatio
    tolerance: float
    responsivity: float = RESPONSIVITY

    def to_dict(self) -> dict:
        out = {
            self.kind: self.value,
            "size_ratio": self.size_ratio.to_dict(),
            "effective_size_ratio": self.size_ratio.effective,
            "tolerance": self.tolerance,
            "relation": "dR/R = |m| rho^2 / 2" if self.kind == "m" else f"de = {self.responsivity:g} |c| rho^2",
        }
        if self.kind == "c":
            out["responsivity"] = self.responsivity
        return out


def budget_for(metric: str, shear_m=None, shear_c=None, size_ratio=None) -> Budget:
    """Validate a shear budget for ``metric`` (the public entry point's checks, naming the field)."""
    if shear_m is not None and shear_c is not None:
        raise InputError("shear_c", "give shear_m (for the size metric) or shear_c (for e1, e2, e), not both")
    kind = "m" if shear_m is not None else "c"
    field = f"shear_{kind}"
    if BUDGET_FOR_METRIC[metric] != kind:
        other = "shear_m" if kind == "c" else "shear_c"
        what = "multiplicative" if kind == "m" else "additive"
        raise InputError(field, f"a {what} budget does not apply to the {metric} metric; use {other}")
    if size_ratio is None:
        raise InputError("size_ratio", f"{field} needs the galaxy-to-PSF size ratio R_gal/R_psf")
    value = check_budget(shear_m if kind == "m" else shear_c, field)
    ratio = check_size_ratio(size_ratio)
    tolerance = size_tolerance(value, ratio) if kind == "m" else ellipticity_tolerance(value, ratio)
    return Budget(kind, value, ratio, tolerance)
