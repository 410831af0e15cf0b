"""The Roman default's model uncertainty: each part from what a source states, not from two guesses.

The default (``nlpsf.request.presets``) simulates a Roman star as it is observed. What it cannot
know is a *part* of its uncertainty: a physical parameter whose value a source gives with an
uncertainty, carried to the slope by the slope's measured sensitivity (linear response inside the
full default scene, the same centroid draws with and without, so the differences are systematic,
not noise). What varies from star to star is a *range*, not an uncertainty. What the default leaves
out of every star is a *shift* with the sign the physics gives it.

standard uncertainties (one standard deviation each, combined in quadrature)
    - ``optics``: the optical model (GalSim's Cycle-9 Zernikes and pupil masks) against the official
      post-CDR PSF statistics of SCA 1 and 18 (``SummaryPSFstats_{center,corner}``: FWHM, N_eff and
      peak at both centrings, and the flux inside the ~7" image, EE), fitted jointly
      (``roman_uncertainty_measure.fit_optics``): two parameters, a Gaussian variance ``v`` added to nlpsf's PSF and the
      pupil's log scale ``ln s`` (the official clear-area rule against the header rule), with the
      statistics' rounding as their stated error and an intrinsic scatter fitted so that chi^2 per
      degree of freedom is 1 (the two parameters cannot describe everything the newer model
      changes, and that scatter says how much). The part is the slope's change to the fitted
      (v, ln s), which the default does not apply, and the fit's covariance carried through the
      slope's sensitivities: sqrt((S theta)^2 + S C S^T).
    - ``jitter``: 6 mas rms per axis (STPSF's "representative predicted average"); GSFC states that
      the 8 mas requirement "is exceeded in under 1 % of the present simulations" (STPSF issue 111,
      2025; the requirement: roman-technical-information PR 58). A normal distribution about 6 mas
      with 1 % above 8 mas has sigma = 2 mas / 2.326 = 0.86 mas; the slope's sensitivity is measured
      at 8 mas and is linear in the variance.
    - ``charge_diffusion``: 0.332 px = sqrt((C11 + C22) / 2) from Givans et al. 2022 (SCA 20829,
      C11 = 0.1066 +- 0.0011, C22 = 0.1136 +- 0.0012 px^2, statistical). Macbeth et al. 2026
      (arXiv:2604.26114, another flight-lot detector, laser speckle) find 0.3279 +0.0043/-0.0042
      (stat) +- 0.0093 (sys) px per axis, no wavelength dependence over 850-2000 nm. The standard
      uncertainty is those stated errors and the two detectors' spread in quadrature
      (:data:`DIFFUSION_SIGMA_PX`, 0.0107 px); the slope's change is measured at 0.332 + 0.0107 px.
shifts (present in every star, a fixed sign; added linearly)
    - ``diffusion_profile``: Macbeth et al. 2026 prefer a hyperbolic-secant profile strongly over a
      Gaussian; the default's is Gaussian. Measured: the same per-axis sigma as a separable sech
      profile (its transfer function sech(2 pi sigma k) per axis) against the Gaussian.
    - ``brighter_fatter``: a ramp refuses BFE, so it is measured on the default scene read as one
      final frame of the same exposure. Freudenburg et al. 2020 (PASP 132, 074504) quote the
      nearest-neighbour area change per electron for SCA 20829 "not IPC-deconvolved"; the value used
      before, 3.54e-7, could not be checked against the paper's text (nlpsf/data/SOURCES.md). This
      scene applies IPC itself, so the coefficient it needs is the deconvolved one: measured here on
      an SCA-20829-like kernel, IPC smooths the nearest-neighbour coefficient to 0.72 of itself, so
      the part uses 3.54e-7 / 0.72 = 4.9e-7 (:data:`BFE_COEFFICIENT`).
    - ``nl_shape``: the NL beyond the quadratic, b3 = 1e-13 and b4 = 1e-18 per e- (0.1 % each of the
      signal at 1e5 e-), against the quadratic alone.
ranges (star to star, not an uncertainty; stated beside the answer)
    - ``sed``: blackbodies of 3500 K and 10000 K (M-dwarfs to A-stars, the stars PSF models are
      fitted with) against the default's Pickles K0V; the slope's change at each end.

How they combine (:func:`combine`): ``relative = hypot(standard parts) + sum(|shifts|)``. ``size``
and ``e`` parts are relative to their own slope; ``e1`` and ``e2`` are the component's change
relative to |c_e| = hypot(c_e1, c_e2) (``model_part.model_at`` restates them against the
component's own slope). The reading side is a function of (band, SCA, mode, metric, magnitude)
that takes arrays (:func:`relative`); the measuring side (``roman_uncertainty_measure``, ``scripts/model_uncertainty_roman.py``,
``nlpsf/data/roman_model_uncertainty.json``) imports the simulator lazily.

About 600 lines, kept as one module: the sources' stated values, the parts built from them, the
reader that answers read them with and the measurement that ships them share those constants, and
a part's reading must follow its measuring exactly.
"""

from __future__ import annotations

import bisect
import json
import math
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from statistics import NormalDist

import numpy as np

from nlpsf.request import presets

#: Where the shipped measurement lives (nlpsf/data/).
FILE = "roman_model_uncertainty.json"
METRICS = ("size", "e1", "e2", "e")
MODES = ("bias", "scatter")

# --- what the sources state ------------------------------------------------------------------

#: Jitter [arcsec rms per axis]: the default's (STPSF's "representative predicted average"), the
#: requirement, and the fraction of GSFC's simulations above it (STPSF issue 111, 2025-08).
JITTER_ARCSEC = presets.JITTER_ARCSEC
JITTER_REQUIREMENT_ARCSEC = 0.008
JITTER_EXCEEDED_FRACTION = 0.01
#: The jitter's standard uncertainty: a normal about the default with the stated fraction above
#: the requirement, (8 - 6) mas / z_0.99 = 0.86 mas.
JITTER_SIGMA_ARCSEC = (JITTER_REQUIREMENT_ARCSEC - JITTER_ARCSEC) / NormalDist().inv_cdf(1 - JITTER_EXCEEDED_FRACTION)
#: Where the jitter's sensitivity is measured (the requirement); the part scales it by the variance.
JITTER_PROBE_ARCSEC = JITTER_REQUIREMENT_ARCSEC

#: Charge diffusion [native px rms]: Givans et al. 2022 (PASP, arXiv:2110.08155), SCA 20829 at
#: 0.5 um, C11 and C22 with their statistical errors [px^2]; Macbeth et al. 2026 (arXiv:2604.26114),
#: a flight-lot detector, 850-2000 nm, the sech profile's per-axis sigma and its errors [px].
GIVANS_C11_PX2, GIVANS_C11_ERR_PX2 = 0.1066, 0.0011
GIVANS_C22_PX2, GIVANS_C22_ERR_PX2 = 0.1136, 0.0012
MACBETH_SIGMA_PX, MACBETH_STAT_PX, MACBETH_SYS_PX = 0.3279, 0.0043, 0.0093
DIFFUSION_PX = presets.CHARGE_DIFFUSION_PX


def diffusion_uncertainty() -> dict[str, float]:
    """The charge diffusion's standard uncertainty [px] and its pieces: Givans's statistical error
    carried to sigma = sqrt((C11 + C22) / 2), Macbeth's statistical and systematic errors, and the
    spread of the two detectors' values (the standard deviation of two, |difference| / sqrt 2)."""
    givans_sigma = math.sqrt((GIVANS_C11_PX2 + GIVANS_C22_PX2) / 2)
    givans_stat = math.hypot(GIVANS_C11_ERR_PX2, GIVANS_C22_ERR_PX2) / 2 / (2 * givans_sigma)
    spread = abs(givans_sigma - MACBETH_SIGMA_PX) / math.sqrt(2)
    pieces = {
        "givans_statistical": givans_stat,
        "macbeth_statistical": MACBETH_STAT_PX,
        "macbeth_systematic": MACBETH_SYS_PX,
        "detector_spread": spread,
    }
    return {**pieces, "total": math.sqrt(math.fsum(v * v for v in pieces.values())), "givans_sigma": givans_sigma}


#: The diffusion's standard uncertainty [px] (:func:`diffusion_uncertainty`), where its
#: sensitivity is measured: the default's 0.332 px plus it.
DIFFUSION_SIGMA_PX = diffusion_uncertainty()["total"]

#: The optics fit: the SCAs the official statistics cover, their star, the probing Gaussian
#: variance [arcsec^2] and the pupil rule the scale's direction is probed with.
OPTICS_SCAS = (1, 18)
OFFICIAL_SED = "K0V"
OPTICS_BLUR_PROBE_ARCSEC2 = 1.0e-4
OPTICS_PUPIL_PROBE = "header"
#: The official tables' rounding (half a unit of their last digit) by statistic: a uniform error of
#: that half-width, standard deviation half-width / sqrt 3.
OFFICIAL_ROUNDING = {"fwhm_arcsec": 5e-4, "n_eff_pixels": 5e-3, "peak_fraction": 5e-6, "total_flux": 5e-6}

#: The SED range's ends: blackbodies bracketing the stars PSF models are fitted with (M0V 3850 K
#: to F0V 7220 K in Pecaut & Mamajek 2013, widened to 3500-10000 K).
SED_RANGE = ("blackbody:3500", "blackbody:10000")
SED_RANGE_K = (3500.0, 10000.0)

#: Brighter-fatter: the published nearest-neighbour coefficient (Freudenburg et al. 2020, SCA
#: 20829, not IPC-deconvolved; digits not verified against the paper's text), the factor IPC
#: smooths it by (measured here on solid-waffle's SCA-20829-like kernel with alpha = 0.0169;
#: nlpsf/data/SOURCES.md), and the deconvolved coefficient the part uses [1/e-].
BFE_COEFFICIENT_PUBLISHED = 3.54e-7
BFE_IPC_SMOOTHING = 0.72
BFE_COEFFICIENT = BFE_COEFFICIENT_PUBLISHED / BFE_IPC_SMOOTHING
#: The residual model the brighter-fatter pair is measured with: the per-resultant correction the
#: default uses is not modelled with BFE (``experiment.correction``), so the pair (final frame with
#: and without BFE) takes the residual on every read, and the part is the difference BFE makes there.
BFE_RESIDUAL_NL = "per_read_beta"
#: b3, b4 of the NL beyond the quadratic [e-^-2, e-^-3]: each 0.1 % of the signal at 1e5 e-.
NL_SHAPE_COEFFICIENTS = (1e-13, 1e-18)

#: Kinds: "standard" parts add in quadrature, "left_out" shifts add linearly.
STANDARD, LEFT_OUT = "standard", "left_out"


@dataclass(frozen=True)
class Part:
    name: str
    kind: str  # STANDARD or LEFT_OUT
    measured_as: str
    source: str


PARTS: tuple[Part, ...] = (
    Part(
        "optics",
        STANDARD,
        "the slope's change to the jointly fitted (Gaussian variance, pupil log scale) that brings nlpsf's PSF to the "
        "official statistics of SCA 1 and 18, with the fit's covariance: sqrt((S theta)^2 + S C S^T)",
        "roman-technical-information 1.5.0 SummaryPSFstats_{center,corner} (post-CDR, K0V, 8 mas FWHM jitter)",
    ),
    Part(
        "jitter",
        STANDARD,
        f"sigma {1e3 * JITTER_SIGMA_ARCSEC:.2f} mas about 6 mas: the slope's change at 8 mas scaled by the variance",
        "GSFC via STPSF issue 111 (2025): 6 mas typical, the 8 mas requirement exceeded in under 1 % of simulations",
    ),
    Part(
        "charge_diffusion",
        STANDARD,
        f"sigma {DIFFUSION_SIGMA_PX:.4f} px about 0.332 px: the slope's change at 0.332 px plus it",
        "Givans et al. 2022 (C11, C22 with statistical errors, SCA 20829); Macbeth et al. 2026 (0.3279 px, stat and sys)",
    ),
    Part(
        "diffusion_profile",
        LEFT_OUT,
        "a separable hyperbolic-secant profile of the same per-axis sigma against the default's Gaussian",
        "Macbeth et al. 2026: the sech profile is strongly preferred over the Gaussian",
    ),
    Part(
        "brighter_fatter",
        LEFT_OUT,
        f"final frame of the same exposure with a = {BFE_COEFFICIENT:.3g} /e- (3.54e-7, not IPC-deconvolved, / 0.72) "
        "against without; a ramp refuses BFE",
        "Freudenburg et al. 2020 (PASP 132, 074504), SCA 20829; the IPC deconvolution measured here",
    ),
    Part(
        "nl_shape",
        LEFT_OUT,
        "b3 = 1e-13, b4 = 1e-18 /e- (0.1 % each at 1e5 e-) against the quadratic alone",
        "the residual level of scene.NOMINAL['nl_polynomial']",
    ),
)
PART_NAMES = tuple(p.name for p in PARTS)
KINDS = {p.name: p.kind for p in PARTS}
#: Star-to-star ranges stated beside the answer (not in its uncertainty).
RANGES = ("sed",)
COMBINATION = (
    "hypot of the standard uncertainties (optics, jitter, charge_diffusion: one standard deviation each, from the "
    "sources' stated uncertainties) plus the plain sum of the shifts left out (diffusion_profile, brighter_fatter, "
    "nl_shape: present in every star, signs fixed); the SED is a range, not a part"
)


def combine(values: dict[str, float | None], kinds: dict[str, str] | None = None) -> float:
    """The rule (:data:`COMBINATION`): quadrature over the standard parts, then the left-out
    shifts' moduli added. Parts that are None (not measured) or absent count zero; the caller names
    them. ``kinds`` names the kind of parts that are not among :data:`PARTS` (an ``accuracy``
    answer's left-out set: "left_out"); any kind but "left_out" is a standard part."""
    kind = {**KINDS, **(kinds or {})}
    standard = [abs(v) for name, v in values.items() if v is not None and kind.get(name, STANDARD) != LEFT_OUT]
    left_out = [abs(v) for name, v in values.items() if v is not None and kind.get(name) == LEFT_OUT]
    return math.sqrt(math.fsum(v * v for v in standard)) + math.fsum(left_out)


def split(values: dict[str, float | None], kinds: dict[str, str] | None = None) -> tuple[float, float]:
    """(the standard parts in quadrature, the shifts' sum): the two pieces :func:`combine` adds."""
    kind = {**KINDS, **(kinds or {})}
    standard = [abs(v) for name, v in values.items() if v is not None and kind.get(name, STANDARD) != LEFT_OUT]
    left_out = [abs(v) for name, v in values.items() if v is not None and kind.get(name) == LEFT_OUT]
    return math.sqrt(math.fsum(v * v for v in standard)), math.fsum(left_out)


# --- reading the shipped measurement ---------------------------------------------------------


def _path() -> Path:
    return Path(str(resources.files("nlpsf") / "data" / FILE))


@lru_cache(maxsize=1)
def shipped() -> dict:
    """The shipped measurement (``scripts/model_uncertainty_roman.py --write``)."""
    return json.loads(_path().read_text())


def entry(band: str, sca: int, mode: str, metric: str) -> tuple[dict, str]:
    """The shipped parts for (band, sca, mode, metric) and where they were measured: the SCA's own
    when it was measured, otherwise the worst over the measured SCAs."""
    data = shipped()
    per_band = data["per_band"][band][mode][metric]
    own = per_band["per_sca"].get(str(sca))
    if own is not None:
        return own, f"SCA {sca}"
    scas = ", ".join(sorted(per_band["per_sca"], key=int))
    return per_band["worst"], f"the worst over SCA {scas} (SCA {sca} is not measured)"


#: Each part's measured rows sorted for a look-up, by the rows' list (``id``, the list kept with
#: them so that the id is not reused): the Roman default's model parts share their rows between
#: answers (``model_part.roman_default_model``), read-only, and an answer looks each up several times.
_SORTED: dict[int, tuple[list, list[float], list[float]]] = {}


def _sorted_rows(by_magnitude: list[list[float]]) -> tuple[list[float], list[float]]:
    """(measured magnitudes ascending, |value| at each) of a part's rows with a value."""
    kept = _SORTED.get(id(by_magnitude))
    if kept is not None and kept[0] is by_magnitude:
        return kept[1], kept[2]
    rows = sorted((r[0], abs(r[1])) for r in by_magnitude if r[1] is not None)
    knots, values = [r[0] for r in rows], [r[1] for r in rows]
    if len(_SORTED) >= 4096:
        _SORTED.clear()
    _SORTED[id(by_magnitude)] = (by_magnitude, knots, values)
    return knots, values


def at_magnitude(by_magnitude: list[list[float]], magnitude: float | None) -> float | None:
    """A part's |value| at ``magnitude`` from its measured [[m, value, ...], ...]: the larger of
    the two measured magnitudes around it (the nearest end outside them); None: the worst of all."""
    knots, values = _sorted_rows(by_magnitude)
    if magnitude is None:
        return max(values, default=None)
    if not knots or not math.isfinite(magnitude):
        value = at_magnitudes(by_magnitude, np.asarray([magnitude], dtype=np.float64))[0]
        return None if not np.isfinite(value) else float(value)
    # at_magnitudes' look-up in plain Python: the same two neighbours
    upper, lower = min(bisect.bisect_left(knots, magnitude), len(knots) - 1), max(bisect.bisect_right(knots, magnitude) - 1, 0)
    pair = (float(values[lower]), float(values[upper]))
    return max(pair) if all(math.isfinite(v) for v in pair) else None


def at_magnitudes(by_magnitude: list[list[float]], magnitudes: np.ndarray, column: int = 1) -> np.ndarray:
    """:func:`at_magnitude` for an array of magnitudes (NaN where nothing is measured)."""
    if column == 1:
        knots_of, values_of = _sorted_rows(by_magnitude)
    else:
        rows = sorted((r[0], abs(r[column])) for r in by_magnitude if r[column] is not None)
        knots_of, values_of = [r[0] for r in rows], [r[1] for r in rows]
    m = np.asarray(magnitudes, dtype=np.float64)
    if not knots_of:
        return np.full(m.shape, np.nan)
    knots, values = np.array(knots_of), np.array(values_of)
    upper = np.minimum(np.searchsorted(knots, m, side="left"), len(knots) - 1)
    lower = np.maximum(np.searchsorted(knots, m, side="right") - 1, 0)
    return np.maximum(values[lower], values[upper])


def at_magnitudes_of(parts_rows: list[list[list[float]]], magnitudes: np.ndarray) -> np.ndarray:
    """(parts, magnitudes): :func:`at_magnitudes` of each part's rows, the parts measured at the
    same magnitudes looked up together (the same neighbours, the same numbers)."""
    m = np.asarray(magnitudes, dtype=np.float64)
    out = np.full((len(parts_rows), m.size), np.nan)
    one = float(m.reshape(-1)[0]) if m.size == 1 else math.nan
    for knots, knots_of, members, values in _lookup_groups(parts_rows):
        if math.isfinite(one):  # one magnitude: searchsorted's neighbours found by bisect (the same two)
            upper = min(bisect.bisect_left(knots_of, one), len(knots_of) - 1)
            lower = max(bisect.bisect_right(knots_of, one) - 1, 0)
            out[members] = np.maximum(values[:, lower : lower + 1], values[:, upper : upper + 1])
            continue
        upper = np.minimum(np.searchsorted(knots, m, side="left"), len(knots) - 1)
        lower = np.maximum(np.searchsorted(knots, m, side="right") - 1, 0)
        out[members] = np.maximum(values[:, lower], values[:, upper])
    return out


#: :func:`_lookup_groups` of a list of parts' rows, by their identities (the lists kept with them, as
#: in ``_SORTED``): the Roman default's parts share their rows between answers.
_GROUPS: dict[tuple[int, ...], tuple[tuple, list]] = {}


def _lookup_groups(parts_rows: list[list[list[float]]]) -> list[tuple[np.ndarray, list[float], list[int], np.ndarray]]:
    """(knots, the same as a list, the parts measured at them, their |values| (parts, knots)) of each set of measured
    magnitudes the parts share (a part with nothing measured is in none: NaN), built once."""
    key = tuple(id(rows) for rows in parts_rows)
    kept = _GROUPS.get(key)
    if kept is not None and all(a is b for a, b in zip(kept[0], parts_rows, strict=True)):
        return kept[1]
    groups: dict[tuple[float, ...], list[int]] = {}
    for p, rows in enumerate(parts_rows):
        groups.setdefault(tuple(_sorted_rows(rows)[0]), []).append(p)
    built = []
    for knots_of, members in groups.items():
        if not knots_of:
            continue  # nothing measured: NaN
        values = np.array([_sorted_rows(parts_rows[p])[1] for p in members])
        knots = np.array(knots_of)
        knots.flags.writeable = values.flags.writeable = False
        built.append((knots, list(knots_of), members, values))
    if len(_GROUPS) >= 4096:
        _GROUPS.clear()
    _GROUPS[key] = (tuple(parts_rows), built)
    return built


def optics_value(fit: dict, sensitivity: np.ndarray, log_scale_offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(the optics part, its offset) from the band's joint fit and the slope's sensitivities
    ``sensitivity`` [..., 2] = (d slope / d v [per arcsec^2], d slope / d ln s), relative: the offset
    S theta (theta the fitted (v, ln s) less ``log_scale_offset`` in ln s, for an answer whose pupil
    rule sits that far from the official one) and sqrt(offset^2 + S C S^T)."""
    theta = np.asarray(fit["theta"], dtype=np.float64) - np.array([0.0, log_scale_offset])
    covariance = np.asarray(fit["covariance"], dtype=np.float64)
    s = np.asarray(sensitivity, dtype=np.float64)
    offset = s @ theta
    spread = np.einsum("...i,ij,...j->...", s, covariance, s)
    return np.sqrt(offset**2 + spread), offset


def relative(band: str, sca: int, mode: str, metric: str, magnitude, pupil_log_scale_offset: float = 0.0, position=None) -> dict:
    """The Roman default's relative model uncertainty at ``magnitude`` (a number or an array), as a
    function of (band, SCA, mode, metric): every part's |value| (e1 / e2 against |c_e|), the
    standard parts in quadrature and the shifts' sum, their combination (:func:`combine`) and the
    SED range's two ends (signed). Vectorised over magnitudes; an unmeasured SCA reads the worst
    over the measured ones. ``pupil_log_scale_offset``: ln(s_rule / s_official) of the answer's pupil
    rule (0: the official rule the default uses). ``position``: accepted for any pixel position;
    the parts are measured at the SCA centre and stand for every position on it (re-measured at two
    others: the combination within 1.2 % of |c_e|, docs/validation.md, "Off the SCA centre")."""
    del position  # the centre's parts stand for the SCA (see above)
    own, where = entry(band, sca, mode, metric)
    m = np.atleast_1d(np.asarray(magnitude, dtype=np.float64))
    parts = {}
    for part in PARTS:
        rows = own["parts"][part.name]["by_magnitude"]
        if part.name == "optics" and pupil_log_scale_offset:
            fit = shipped()["optics_fit"][band]
            s = np.stack([at_signed(own["optics_sensitivity"], m, 1), at_signed(own["optics_sensitivity"], m, 2)], -1)
            parts[part.name] = optics_value(fit, s, pupil_log_scale_offset)[0]
        else:
            parts[part.name] = at_magnitudes(rows, m)
    standard = np.sqrt(sum(np.nan_to_num(parts[p.name]) ** 2 for p in PARTS if p.kind == STANDARD))
    shifts = sum(np.nan_to_num(parts[p.name]) for p in PARTS if p.kind == LEFT_OUT)
    ranges = {name: (at_signed(own["ranges"][name]["by_magnitude"], m, 1), at_signed(own["ranges"][name]["by_magnitude"], m, 2))
              for name in RANGES}  # fmt: skip
    return {"parts": parts, "standard": standard, "shifts": shifts, "model": standard + shifts, "ranges": ranges,
            "where": where}  # fmt: skip


def at_signed(by_magnitude: list[list[float]], magnitudes: np.ndarray, column: int) -> np.ndarray:
    """A signed column of [[m, ...], ...] at ``magnitudes``, linear between the measured ones and
    constant outside them (the ranges' ends and the optics' sensitivities are smooth in m)."""
    knots, values = _signed_rows(by_magnitude, column)
    m = np.asarray(magnitudes, dtype=np.float64)
    if not knots:
        return np.full(m.shape, np.nan)
    return np.interp(m, knots, values)


#: :func:`_signed_rows` by the rows' identity and the column (the rows kept with them, as in ``_SORTED``).
_SIGNED: dict[tuple[int, int], tuple[list, list[float], list[float]]] = {}


def _signed_rows(by_magnitude: list[list[float]], column: int) -> tuple[list[float], list[float]]:
    """(measured magnitudes ascending, the signed ``column`` at each) of the rows stating it, sorted once."""
    kept = _SIGNED.get((id(by_magnitude), column))
    if kept is not None and kept[0] is by_magnitude:
        return kept[1], kept[2]
    rows = sorted((r[0], r[column]) for r in by_magnitude if r[column] is not None)
    knots, values = [r[0] for r in rows], [r[1] for r in rows]
    if len(_SIGNED) >= 4096:
        _SIGNED.clear()
    _SIGNED[(id(by_magnitude), column)] = (by_magnitude, knots, values)
    return knots, values


def pupil_log_scale(band: str, sca: int, rule: str, reference: str = "official") -> float:
    """ln(s_rule / s_reference) of the binned pupil's metres per pixel (``roman.pupil``)."""
    from nlpsf import roman

    return math.log(roman.pupil(sca, band, 4, rule).scale_m / roman.pupil(sca, band, 4, reference).scale_m)
