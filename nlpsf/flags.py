"""Result flags as codes with a message: the one owner of every warning a result can carry.

A flag is a :class:`Flag`: a ``str`` (its message, so text output, joins and ``in`` tests read as
before) that also carries its :class:`FlagCode` and the values the message quotes. Each code has
one :class:`FlagSpec` in :data:`CATALOGUE`: the message template (``str.format`` fields named by the
values), the names of the values it quotes, and a sentence saying what it means, for a page that
wants to explain or filter flags.

Serialised results (``to_dict`` of simulation results, slope results and solutions, hence the CLI's
``--json`` and the API) keep ``flags``, the list of messages, unchanged, and add ``flag_codes``, the
list of codes in the same order (``flag_codes[i]`` is the code of ``flags[i]``). Tests assert codes
(:func:`codes`), never the English.

Adding a warning: one member of :class:`FlagCode`, one :data:`CATALOGUE` entry, and ``make(code, ...)``
where it is raised.
"""

from __future__ import annotations

import math
import string
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from enum import StrEnum
from types import MappingProxyType


class FlagCode(StrEnum):
    """Stable codes of result flags (the value is what JSON carries)."""

    # Simulations (nlpsf.sim.experiment)
    SATURATED = "saturated"
    NL_NOT_MONOTONIC = "nl_not_monotonic"
    NEGATIVE_BETA = "negative_beta"
    NEGATIVE_PIXEL_BETAS = "negative_pixel_betas"
    UNDERSAMPLED = "undersampled"
    STAMP_TOO_SMALL = "stamp_too_small"
    MOMENTS_FAILED = "moments_failed"
    RAMP_UNUSABLE_PIXELS = "ramp_unusable_pixels"
    RAMP_FEWER_RESULTANTS = "ramp_fewer_resultants"
    NO_CHANGE = "no_change"
    BELOW_MONTE_CARLO_RESOLUTION = "below_monte_carlo_resolution"
    JUMPY_FINITE_DIFFERENCE = "jumpy_finite_difference"
    # Solutions (nlpsf.solve.solver, nlpsf.slopes.fidelity, nlpsf.request.shear)
    FIDELITY_CHOSEN = "fidelity_chosen"
    FIDELITY_NONE_MEETS = "fidelity_none_meets"
    FIDELITY_ERROR_UNKNOWN = "fidelity_error_unknown"
    FIDELITY_FROM_PAPER = "fidelity_from_paper"
    ACCURACY_SCENE = "accuracy_scene"
    ACCURACY_CENTROIDS = "accuracy_centroids"
    SCENE_SIMULATED = "scene_simulated"
    PUPIL_SCALE_SIMULATED = "pupil_scale_simulated"
    BETA_Q_RULE_BROKEN = "beta_q_rule_broken"
    THROUGHPUT_RELABELLED = "throughput_relabelled"
    ERROR_AT_SATURATION = "error_at_saturation"
    SATURATION_BINDS = "saturation_binds"
    BETWEEN_SATURATION_LIMITS = "between_saturation_limits"
    RAMP_SATURATED = "ramp_saturated"
    STAR_SATURATED = "star_saturated"
    EXTRAPOLATED_FAINT = "extrapolated_faint"
    EXTRAPOLATED_ANSWER = "extrapolated_answer"
    FAINTER_THAN_40 = "fainter_than_40"
    BELOW_TOLERANCE_EVERYWHERE = "below_tolerance_everywhere"
    SLOPE_CHANGES_SIGN = "slope_changes_sign"
    SLOPE_CONSISTENT_WITH_ZERO = "slope_consistent_with_zero"
    E_COMPONENT_SMALL = "e_component_small"
    QUADRATIC_NOT_MONOTONIC = "quadratic_not_monotonic"
    OUTSIDE_LINEAR_REGIME = "outside_linear_regime"
    SHEAR_CROSS_TERM = "shear_cross_term"
    WORST_OVER_FIELD = "worst_over_field"
    # The Roman default (nlpsf.request.presets)
    DEFAULT_FROM_GRID = "default_from_grid"
    DEFAULT_SIMULATED = "default_simulated"
    DEFAULT_BETWEEN_LIMITS = "default_between_limits"
    LINEARISED_SIMULATED = "linearised_simulated"
    SCA_RANGE = "sca_range"


@dataclass(frozen=True)
class FlagSpec:
    """A code's message template, the values it quotes, and what it means."""

    template: str
    quotes: tuple[str, ...]
    meaning: str


_UNPHYSICAL = "so the numbers describe an unphysical case"

CATALOGUE: dict[FlagCode, FlagSpec] = {
    FlagCode.SATURATED: FlagSpec(
        "saturated: the star's brightest pixel reaches {peak_e:.4g} e- (the maximum over sub-pixel centroids), "
        "above the full well of {full_well_e:.4g} e-, and passes it in {over} of the {realizations} "
        "realizations drawn; a real detector would clip this star, " + _UNPHYSICAL,
        ("peak_e", "full_well_e", "over", "realizations"),
        "The simulated star's brightest pixel passes the full well: a real detector would clip it.",
    ),
    FlagCode.NL_NOT_MONOTONIC: FlagSpec(
        "nonlinearity not monotonic: {slope_name} reaches {worst:.3g} in pixels that carry weight in the moments; "
        "{model} is invalid at this charge, so the result is not physical",
        ("slope_name", "worst", "model"),
        "The detector response stops growing with charge where the moments look: the NL model is invalid there.",
    ),
    FlagCode.NEGATIVE_BETA: FlagSpec(
        "beta < 0 in the paper's convention: the simulated response is super-linear (brightening)",
        (),
        "A negative beta (paper convention) brightens the pixels instead of dimming them.",
    ),
    FlagCode.NEGATIVE_PIXEL_BETAS: FlagSpec(
        "{percent:.2g} % of the per-pixel beta values are negative (super-linear pixels): sigma_beta is comparable to beta",
        ("percent",),
        "The per-pixel beta spread is so wide that some pixels are super-linear.",
    ),
    FlagCode.UNDERSAMPLED: FlagSpec(
        "undersampled: fine pixels of {pixel_mas:.1f} mas are coarser than the Nyquist sampling "
        "lambda/2D = {nyquist_mas:.1f} mas at {wavelength_nm:.0f} nm (q = {q:.2f}); moments of an aliased PSF are "
        "biased (measured: up to 3.5 % in size and 13 % in e at q = 0.5-0.85); use --oversampling {needed} or more",
        ("pixel_mas", "nyquist_mas", "wavelength_nm", "q", "needed"),
        "The fine grid aliases the PSF: the moments are biased; a larger oversampling fixes it.",
    ),
    FlagCode.STAMP_TOO_SMALL: FlagSpec(
        "stamp too small: the adaptive-moment weight window (rho^2 <= {cut:.4g}) reaches past the {n}x{n} stamp edge in "
        "{inside} of {fitted} realizations, so the moments are those of a truncated image; use a larger --stamp",
        ("cut", "n", "inside", "fitted"),
        "The moments' weight window is cut by the stamp edge: a larger stamp fixes it.",
    ),
    FlagCode.MOMENTS_FAILED: FlagSpec(
        "adaptive moments failed in {failed} of {total} realizations ({reasons}); {rest}",
        ("failed", "total", "reasons", "rest"),
        "Some (or all) adaptive-moment fits failed; the statistics use the others.",
    ),
    FlagCode.RAMP_UNUSABLE_PIXELS: FlagSpec(
        "saturated {where}: {unusable} pixels that carry weight in the moments (in {hit} of "
        "{realizations} realizations) pass the saturation level of {full_well_e:.4g} e- by t = {time_s:.4g} s; "
        "they are unusable (their value here is the first resultant's), " + _UNPHYSICAL,
        ("where", "unusable", "hit", "realizations", "full_well_e", "time_s"),
        "Up the ramp, weighted pixels saturate before the resultants a slope needs: they are unusable.",
    ),
    FlagCode.RAMP_FEWER_RESULTANTS: FlagSpec(
        "ramp: {fewer} of {pixels} pixels that carry weight were fitted on fewer than "
        "{resultants} resultants (down to {fewest}; saturated resultants dropped, as the ground pipeline "
        "does); a single final frame would be saturated (peak {peak_e:.4g} e- > full well {full_well_e:.4g} e-)",
        ("fewer", "pixels", "resultants", "fewest", "peak_e", "full_well_e"),
        "Up the ramp, some weighted pixels drop saturated resultants (as the ground pipeline does).",
    ),
    FlagCode.NO_CHANGE: FlagSpec(
        "no change: the nonlinearity is exactly zero for this beta",
        (),
        "beta is zero: the images are unchanged.",
    ),
    FlagCode.BELOW_MONTE_CARLO_RESOLUTION: FlagSpec(
        "below the Monte Carlo's resolution: sigma_beta={sigma_beta:g} should spread the metrics by only "
        "{expected}, under the ~{floor:g} that differences of converged float64 fits resolve; the measured spread "
        "({measured}) is numerical noise. The linear method is exact here (the response is linear in sigma_beta).",
        ("sigma_beta", "expected", "floor", "measured"),
        "The expected Monte Carlo scatter is below float64 resolution: the measured spread is noise.",
    ),
    FlagCode.JUMPY_FINITE_DIFFERENCE: FlagSpec(
        "jumpy finite difference: the Monte Carlo slope differs from the exact derivative at beta0 by {differences}: "
        "pixels cross the hard weight cut at rho^2 = {cut:g} between "
        "beta0 x 0.99 and x 1.01; the linear method (or --weight-cut none) has no such step",
        ("differences", "cut"),
        "Pixels crossing the hard weight cut make the Monte Carlo finite difference jump.",
    ),
    FlagCode.FIDELITY_CHOSEN: FlagSpec(
        "fidelity {level} chosen for accuracy {accuracy:g}: its measured relative error on {band} {metric} {mode} "
        "slopes is {error:.2g} ({date})",
        ("level", "accuracy", "band", "metric", "mode", "error", "date"),
        "The accuracy asked for picked this fidelity level (the cheapest whose measured error meets it).",
    ),
    FlagCode.FIDELITY_NONE_MEETS: FlagSpec(
        "no fidelity level meets accuracy {accuracy:g} for {band} {metric} {mode}; using the most accurate, {level}, whose "
        "measured relative error is {error:.2g}",
        ("accuracy", "band", "metric", "mode", "level", "error"),
        "No fidelity level meets the accuracy asked for; the most accurate is used.",
    ),
    FlagCode.FIDELITY_ERROR_UNKNOWN: FlagSpec(
        "no measured fidelity error for this band is shipped, so the uncertainty is statistical only",
        (),
        "The fidelity level's error is not measured here: the uncertainty lacks that part.",
    ),
    FlagCode.FIDELITY_FROM_PAPER: FlagSpec(
        "no measured fidelity errors for the {scene} scene are shipped: level {level} is chosen on the paper scene's "
        "measurement (relative error {error:.2g})",
        ("scene", "level", "error"),
        "The fidelity level's error is read from the paper scene's measurement, not the simulated scene's own.",
    ),
    FlagCode.ACCURACY_SCENE: FlagSpec(
        "accuracy {accuracy:g}: fidelity {level} (measured error {level_error:.2g}); left out of the full scene: "
        "{left_out} (measured together: {impact:+.2g}); total {total:.2g}",
        ("accuracy", "level", "level_error", "left_out", "impact", "total"),
        "What an accuracy answer simulates: its level's error and the measured impact of the effects it leaves out.",
    ),
    FlagCode.ACCURACY_CENTROIDS: FlagSpec(
        "pixels lose resultants at m={magnitude:.2f}: the slope's statistical error over {pilot} centroids is "
        "{pilot_error:.2g} of it, so {used} centroids are simulated (its statistical error: {errors}; "
        "target {target:.2g}: {verdict})",
        ("magnitude", "pilot", "pilot_error", "used", "errors", "target", "verdict"),
        "Where pixels lose resultants an accuracy answer simulates enough centroids for its statistical error to fit "
        "its target (or says it cannot).",
    ),
    FlagCode.SCENE_SIMULATED: FlagSpec(
        "the tables hold the paper's scene only (at the SCA centre and its corner field points): "
        "the scene's effects are simulated (fidelity linear)",
        (),
        "A table-level request with scene effects is simulated with the linear response.",
    ),
    FlagCode.PUPIL_SCALE_SIMULATED: FlagSpec(
        "the tables hold the {table_rule} pupil scale: the slopes are simulated with pupil scale {rule} (fidelity linear)",
        ("table_rule", "rule"),
        "Another pupil-scale rule than the tables' is simulated with the linear response.",
    ),
    FlagCode.BETA_Q_RULE_BROKEN: FlagSpec(
        "{effects} {verb} a flux dependence of its own: slopes are simulated at this exposure and beta0 (afresh, "
        "or at the field grid's nodes), never rescaled from the tables (the beta Q rule does not hold)",
        ("effects", "verb"),
        "A scene effect depends on the flux by itself: slopes are not rescaled between exposures.",
    ),
    FlagCode.THROUGHPUT_RELABELLED: FlagSpec(
        "the {source} tables read with {throughput} photometry (magnitudes {shift:+.3f}); their achromatic PSF keeps "
        "the {source} curve's wavelength, up to {percent:.1f} % on the slope, added to the optical-model uncertainty",
        ("source", "throughput", "shift", "percent"),
        "The tables are relabelled for another throughput; the error that leaves is in the uncertainty.",
    ),
    FlagCode.ERROR_AT_SATURATION: FlagSpec(
        "at the saturation magnitude the {metric} {mode} error is {error:.3g} (tolerance {tolerance:g})",
        ("metric", "mode", "error", "tolerance"),
        "Saturation sets the answer; this is the NL error there.",
    ),
    FlagCode.SATURATION_BINDS: FlagSpec(
        "saturation binds: stars brighter than m={m_sat:.2f} saturate before the nonlinearity matters{where}; "
        "at the saturation magnitude the NL error is below the tolerance",
        ("m_sat", "where"),
        "The brightest usable star is set by saturation, not by the nonlinearity.",
    ),
    FlagCode.BETWEEN_SATURATION_LIMITS: FlagSpec(
        "between the saturation limits: at m={magnitude:.2f} a single final frame would saturate (m < {m_sat_final:.2f}) "
        "but the ramp keeps its early resultants (usable down to m={m_sat:.2f}); the answer uses the ramp fit with "
        "saturated resultants dropped",
        ("magnitude", "m_sat_final", "m_sat"),
        "A final frame would saturate, the ramp's early resultants do not: saturated resultants are dropped.",
    ),
    FlagCode.RAMP_SATURATED: FlagSpec(
        "saturated: at m={magnitude:g} the brightest pixel saturates already in the resultant a slope needs "
        "(ramp saturation at m={m_sat:.2f}); such a star cannot be used for the PSF model at all",
        ("magnitude", "m_sat"),
        "The star saturates in the resultants a ramp slope needs: it cannot be used.",
    ),
    FlagCode.STAR_SATURATED: FlagSpec(
        "saturated: at m={magnitude:g} the brightest pixel exceeds the full well (saturation at m={m_sat:.2f}); "
        "such a star cannot be used for the PSF model at all",
        ("magnitude", "m_sat"),
        "The star saturates: it cannot be used for the PSF model.",
    ),
    FlagCode.EXTRAPOLATED_FAINT: FlagSpec(
        "extrapolated: m={magnitude:g} is fainter than the table (m <= {faintest:.2f}); the slope is scaled in proportion "
        "to the flux, which is exact in the linear regime these faint stars are in",
        ("magnitude", "faintest"),
        "Fainter than the tables: the slope is scaled with flux (exact in the linear regime).",
    ),
    FlagCode.EXTRAPOLATED_ANSWER: FlagSpec(
        "extrapolated: the tolerance is only met fainter than the table (m > {faintest:.2f}); m={magnitude:.2f} follows "
        "from the slope scaling with flux, exact in the linear regime",
        ("faintest", "magnitude"),
        "The answer lies fainter than the tables: it follows from the slope scaling with flux.",
    ),
    FlagCode.FAINTER_THAN_40: FlagSpec(
        "the answer is fainter than m = 40: no usable PSF star can meet this tolerance at this precision",
        (),
        "No real PSF star can meet the tolerance at this precision.",
    ),
    FlagCode.BELOW_TOLERANCE_EVERYWHERE: FlagSpec(
        "the NL error stays below the tolerance {where}",
        ("where",),
        "No magnitude reaches the tolerance: saturation sets the brightest usable star.",
    ),
    FlagCode.SLOPE_CHANGES_SIGN: FlagSpec(
        "the {metric} slope changes sign {where}; the answer uses |c| and is the brightest magnitude "
        "whose error stays within the tolerance for every fainter star",
        ("metric", "where"),
        "An ellipticity slope passes through zero: the answer uses |c| and holds for every fainter star.",
    ),
    FlagCode.SLOPE_CONSISTENT_WITH_ZERO: FlagSpec(
        "the {metric} slope at m={magnitude:g} is consistent with zero ({slope:.3g} ± {error:.2g}): "
        "this metric is insensitive to beta here, so no calibration precision is needed for it",
        ("metric", "magnitude", "slope", "error"),
        "The metric is insensitive to beta here: no precision is needed for it.",
    ),
    FlagCode.E_COMPONENT_SMALL: FlagSpec(
        "the {metric} slope at m={magnitude:.2f} is {why}: c_{metric} = {slope:.3g} ± {error:.2g} against "
        "|c_e| = {modulus:.3g}; the model's errors (optics, diffusion, jitter) move the two e components "
        "together, so they move c_{metric} by a large fraction of itself and its relative uncertainty is large. "
        "For a requirement on the PSF's ellipticity ask for --metric e (the modulus hypot(c_e1, c_e2)), which "
        "they do not make small",
        ("metric", "magnitude", "why", "slope", "error", "modulus"),
        "An ellipticity component whose slope is small against the modulus |c_e| (or consistent with zero): "
        "its relative uncertainty is large; --metric e gives the modulus.",
    ),
    FlagCode.QUADRATIC_NOT_MONOTONIC: FlagSpec(
        "nonlinearity not monotonic: 2 beta0 Q_peak = {value:.2f} >= 1 at m={magnitude:g}; the quadratic model "
        "is invalid for this star, so the slope is not physical",
        ("value", "magnitude"),
        "At this star's peak the quadratic NL stops being monotonic: the slope is not physical.",
    ),
    FlagCode.OUTSIDE_LINEAR_REGIME: FlagSpec(
        "outside the linear regime: delta_beta * Q_peak = {value:.2g} > {limit}; "
        "T = c p beta0 assumes the PSF error grows linearly with delta_beta, so expect corrections of that order",
        ("value", "limit"),
        "The calibration error is large enough that the PSF error is no longer linear in it.",
    ),
    FlagCode.SHEAR_CROSS_TERM: FlagSpec(
        "the additive bias from a size error of an elliptical PSF, c ~ e_psf * dR/R / rho^2, is not in the e tolerance; "
        "it is of order e_psf times the size error and belongs to the size budget",
        (),
        "An e budget does not hold the additive bias a size error of an elliptical PSF makes.",
    ),
    FlagCode.WORST_OVER_FIELD: FlagSpec(
        "worst over {points} field points ({where}): SCA {sca} at pixel ({x:.0f}, {y:.0f}); {solved} ranges "
        "{low:.4g} to {high:.4g}",
        ("points", "where", "sca", "x", "y", "solved", "low", "high"),
        "The answer is that of the most demanding field point; the range over the points follows.",
    ),
    FlagCode.DEFAULT_FROM_GRID: FlagSpec(
        "slopes from the Roman default's field grid ({grid} x {grid} nodes, {scheme} across the SCA) at pixel ({x:.0f}, {y:.0f})",
        ("grid", "scheme", "x", "y"),
        "The Roman default's slope is read from the shipped field grid of its scene, interpolated to the position.",
    ),
    FlagCode.DEFAULT_SIMULATED: FlagSpec(
        "no shipped field grid holds the Roman default at this point ({why}): its scene is simulated (fidelity linear)",
        ("why",),
        "The Roman default is not in a shipped table here, so its slope is a fresh linear-response simulation.",
    ),
    FlagCode.DEFAULT_BETWEEN_LIMITS: FlagSpec(
        "between the saturation limits at pixel ({x:.0f}, {y:.0f}): m={magnitude:.2f} lies between the ramp's limit "
        "m={m_sat:.2f} and the final frame's m={m_sat_final:.2f}, where pixels lose resultants and the slope changes with "
        "each that does; the field grid's interpolation misses a fresh simulation there (docs/field.md), so the slope is "
        "simulated afresh at this position with {realizations} centroids (fidelity linear): {centroids}",
        ("x", "y", "magnitude", "m_sat", "m_sat_final", "realizations", "centroids"),
        "Between the saturation limits the Roman default's slope at a position is simulated afresh, not read from "
        "the field grid (whose interpolation misses there).",
    ),
    FlagCode.LINEARISED_SIMULATED: FlagSpec(
        "the tables hold the slope at beta0: linearised at {state}, the slopes are simulated (fidelity linear)",
        ("state",),
        "A slope taken at another detector state than the tables' is simulated with the linear response.",
    ),
    FlagCode.SCA_RANGE: FlagSpec(
        "no position given: the answer holds everywhere on SCA {sca}, the most demanding of {points} positions, at pixel "
        "({x:.0f}, {y:.0f}); {solved} ranges {least:.4g} (least demanding, at ({lx:.0f}, {ly:.0f})) to {most:.4g}",
        ("sca", "points", "x", "y", "solved", "least", "lx", "ly", "most"),
        "Without a position the Roman default answers for the SCA's most demanding grid node; the least demanding "
        "node and every node's value are in conditions['sca_range'].",
    ),
}


class _Words(string.Formatter):
    """The catalogue's templates filled with a number that is not finite as a word, not Python's
    "inf" / "nan": a precision no slope limits (the slope consistent with zero) is "unbounded", an
    error no slope gives is "undefined". The flag's ``values`` keep the numbers."""

    def format_field(self, value, format_spec):
        if isinstance(value, float) and not math.isfinite(value):
            return "undefined" if math.isnan(value) else "unbounded" if value > 0 else "-unbounded"
        return super().format_field(value, format_spec)


_WORDS = _Words()


class Flag(str):
    """A flag: its message (the string itself), its ``code`` and the ``values`` the message quotes."""

    code: FlagCode
    #: Read-only: a plan's flags are shared by the answers made from it (kept plans, a node's flag).
    values: Mapping[str, object]

    def __new__(cls, code: FlagCode | str, **values) -> Flag:
        code = code if type(code) is FlagCode else FlagCode(code)  # the enum's look-up only for a string
        spec = CATALOGUE[code]
        if not all(name in values for name in spec.quotes):
            missing = set(spec.quotes) - set(values)
            raise TypeError(f"flag {code.value} needs {', '.join(sorted(missing))}")
        finite = all(not isinstance(v, float) or math.isfinite(v) for v in values.values())
        text = spec.template.format(**values) if finite else _WORDS.vformat(spec.template, (), values)
        self = super().__new__(cls, text)
        self.code = code
        self.values = MappingProxyType(values)
        return self

    def __reduce__(self):  # pickles (jobs, dask) as code + values
        return (_rebuild, (self.code.value, dict(self.values)))

    def to_dict(self) -> dict:
        return {"code": self.code.value, "message": str(self), "values": dict(self.values)}


def _rebuild(code: str, values: dict) -> Flag:
    return Flag(code, **values)


def make(code: FlagCode | str, **values) -> Flag:
    """The flag of ``code`` with its message filled from ``values``."""
    return Flag(code, **values)


def code_of(flag: str) -> str | None:
    """The code of a flag (None for a plain string, e.g. one read back from a file)."""
    return flag.code.value if isinstance(flag, Flag) else None


def codes(flags: Iterable[str]) -> list[str | None]:
    """The codes of ``flags``, in order: what serialised results carry as ``flag_codes``."""
    return [code_of(f) for f in flags]


def catalogue() -> list[dict]:
    """Every code with its template, the values it quotes and its meaning (for the API and page)."""
    return [
        {"code": code.value, "template": spec.template, "quotes": list(spec.quotes), "meaning": spec.meaning}
        for code, spec in CATALOGUE.items()
    ]
