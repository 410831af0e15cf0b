"""The Roman default's model uncertainty: what its scene still leaves out, as named parts.

The default (``nlpsf.request.presets``) simulates a Roman star as it is observed. What it cannot
know, or does not simulate, is measured here as the relative change of the NL slope, one named
part at a time, inside the full default scene (linear response, the same centroid draws with and
without, so the differences are systematic, not noise):

choices and vintage (the default's value is a best estimate; the truth lies in a range)
    - ``optical_model``: the optical model's vintage. nlpsf's PSF under the official conditions
      (their K0V star as the vendored Pickles K0V, the default's own star) against the official
      post-CDR statistics (``psfstats``): the Gaussian variance that closes the
      N_eff gap or the FWHM gap, whichever is larger, added to the default's jitter; the slope change
      it causes (a gap that asks for a sharper PSF is measured as the same variance added and the
      sign turned, linear in the variance). SCAs without official statistics take the larger gap
      of the SCAs that have them (1 and 18).
    - ``sed``: the stars people fit PSF models with, 3500-10000 K blackbodies (M-dwarfs to A-stars)
      against the default's Pickles K0V spectrum; the larger change of the two ends.
    - ``jitter``: 3.4 mas (the official PSF products' 8 mas FWHM) and 14 mas (GalSim's) rms against
      the default's 6 mas; the larger.
    - ``charge_diffusion``: 0.30 px rms (STPSF's 0.033", the alternative nlpsf/data/SOURCES.md
      quotes) against the default's 0.332 px (Givans et al. 2022, one detector).
    - ``pupil_scale``: the pupil-mask scale rule, ``header`` against the ``official`` one used.
effects left out (present in every real star, with a sign the physics fixes)
    - ``brighter_fatter``: a ramp refuses it (``ramps.RAMP_REFUSES``), so it is measured on the
      default scene read as one final frame of the same exposure: with the nearest-neighbour
      coefficient a = 3.54e-7 per electron, against without. Source: Freudenburg et al. 2020
      (PASP 132, 074504; arXiv:2003.05978), whose abstract quotes the BFE as the increase of a
      pixel's effective area per electron deposited in a neighbouring pixel, for SCA 20829, not
      IPC-deconvolved. The paper, detector, quantity and "not IPC-deconvolved" are verified; the
      digits 3.54e-7 are not (the stored abstract text lost its numbers; nlpsf/data/SOURCES.md).
      A figure that is not IPC-deconvolved already carries IPC's smoothing of the BFE kernel
      ([K^2 a + K K^I]_<1,0> in Hirata & Choi's notation), while this scene applies IPC on its
      own, so the part is probably an underestimate (the IPC-deconvolved nearest-neighbour
      coefficient is ~1.4x larger for an SCA-20829-like kernel with alpha = 0.0169, and the part is
      linear in a to 2-11 % at twice a; not applied).
    - ``nl_shape``: the NL beyond the quadratic, b3 = 1e-13 and b4 = 1e-18 per e- (each 0.1 % of
      the signal at 1e5 e-), present in the image, against the quadratic alone. At the corrected
      state the slope hardly depends on the image's NL (it changes the image by ~0.1 %), so this
      part is small; the shape of the calibration *error* itself (a cubic error instead of a
      quadratic one) is a different question, not measured here.

How they combine (:func:`combine`): the choices are independent unknowns, so they add in
quadrature; the effects left out are present in every star with fixed signs, so their moduli add
linearly on top: ``relative = hypot(choices) + sum(|left out|)``. Each part is quoted at its worst
|value| of the two ends it was measured at (never the mean of the ends).

``size`` and ``e`` parts are relative to their own slope; ``e1`` and ``e2`` parts are the
component's change relative to |c_e| = hypot(c_e1, c_e2) (``model_part.model_at`` restates them
against the component's own slope at the answer's magnitude), as the paper scene's file does.

Measured by ``scripts/model_uncertainty_roman.py`` into ``nlpsf/data/roman_model_uncertainty.json``.
This module's reading side is light (json only); the measuring side imports the simulator lazily.
"""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import dataclass, replace
from functools import lru_cache
from importlib import resources
from pathlib import Path

#: Where the shipped measurement lives (nlpsf/data/).
FILE = "roman_model_uncertainty.json"
METRICS = ("size", "e1", "e2", "e")
MODES = ("bias", "scatter")
#: Blackbody temperatures [K] bracketing the stars PSF models are fitted with (M0V 3850 K to F0V
#: 7220 K in Pecaut & Mamajek 2013, widened to 3500-10000 K).
SED_RANGE_K = (3500.0, 10000.0)
#: Jitter per axis [arcsec rms]: the official PSF products' 8 mas FWHM and GalSim's 14 mas.
JITTER_RANGE_ARCSEC = (0.0034, 0.014)
#: The other charge diffusion [native px rms]: STPSF's 0.033" on 0.11" pixels.
DIFFUSION_ALTERNATIVE_PX = 0.30
#: The other pupil-scale rule.
PUPIL_ALTERNATIVE = "header"
#: Brighter-fatter nearest-neighbour coefficient [1/e-]: Freudenburg et al. 2020 (PASP 132, 074504),
#: SCA 20829, the area change of a pixel per electron in a neighbour, not IPC-deconvolved. The
#: value's digits are unverified (see the module docstring and nlpsf/data/SOURCES.md).
BFE_COEFFICIENT = 3.54e-7
#: b3, b4 of the NL beyond the quadratic [e-^-2, e-^-3]: each 0.1 % of the signal at 1e5 e-.
NL_SHAPE_COEFFICIENTS = (1e-13, 1e-18)


@dataclass(frozen=True)
class Part:
    name: str
    kind: str  # "choice" (quadrature) or "left_out" (linear)
    measured_as: str


PARTS: tuple[Part, ...] = (
    Part(
        "optical_model",
        "choice",
        "Gaussian variance closing nlpsf's N_eff or FWHM gap to the official SummaryPSFstats (the larger; official "
        "conditions, their K0V star as the Pickles K0V), added to the jitter; sign turned where the official PSF is sharper",
    ),
    Part("sed", "choice", "blackbody 3500 K and 10000 K against the default's K0V (Pickles 1998); the larger"),
    Part("jitter", "choice", "3.4 mas and 14 mas rms against the default's 6 mas; the larger"),
    Part("charge_diffusion", "choice", "0.30 px (STPSF's 0.033\") against the default's 0.332 px rms"),
    Part("pupil_scale", "choice", "pupil-mask scale rule header against official (used)"),
    Part(
        "brighter_fatter",
        "left_out",
        "final frame of the same exposure with a = 3.54e-7 /e- (Freudenburg et al. 2020) against without; "
        "a ramp refuses BFE (ramps.RAMP_REFUSES)",
    ),
    Part("nl_shape", "left_out", "b3 = 1e-13, b4 = 1e-18 /e- (0.1 % each at 1e5 e-) against the quadratic alone"),
)
PART_NAMES = tuple(p.name for p in PARTS)
KINDS = {p.name: p.kind for p in PARTS}
COMBINATION = (
    "hypot of the choices (optical_model, sed, jitter, charge_diffusion, pupil_scale: independent unknowns) plus "
    "the plain sum of the effects left out (brighter_fatter, nl_shape: present in every star, signs fixed)"
)


def combine(values: dict[str, float | None], kinds: dict[str, str] | None = None) -> float:
    """The rule (:data:`COMBINATION`): quadrature over the choices, then the left-out effects'
    moduli added. Parts that are None (not measured) or absent count zero; the caller names them.
    ``kinds`` names the kind ("choice" or "left_out") of parts that are not among :data:`PARTS`
    (an ``accuracy`` answer's left-out set, a measured shift with a fixed sign: "left_out")."""
    kind = {**KINDS, **(kinds or {})}
    choices = [abs(v) for name, v in values.items() if v is not None and kind.get(name, "choice") == "choice"]
    left_out = [abs(v) for name, v in values.items() if v is not None and kind.get(name) == "left_out"]
    return math.sqrt(math.fsum(v * v for v in choices)) + math.fsum(left_out)


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


def at_magnitude(by_magnitude: list[list[float]], magnitude: float | None) -> float | None:
    """A part's |value| at ``magnitude`` from its measured [[m, value], ...]: the larger of the two
    measured magnitudes around it (the nearest end outside them); None: the worst of all."""
    points = sorted((m, abs(v)) for m, v in by_magnitude if v is not None)
    if not points:
        return None
    if magnitude is None:
        return max(v for _, v in points)
    if magnitude <= points[0][0]:
        return points[0][1]
    if magnitude >= points[-1][0]:
        return points[-1][1]
    for (m0, v0), (m1, v1) in itertools.pairwise(points):
        if m0 <= magnitude <= m1:
            return max(v0, v1)
    return max(v for _, v in points)  # not reached


# --- measuring (scripts/model_uncertainty_roman.py and the tests) ------------------------------


def _metric_values(result) -> dict:
    """{mode: {metric: (value, error)}} of one experiment.SlopeResult; e = hypot(e1, e2)."""
    out = {"bias": {}, "scatter": {}}
    b = {k: (result.bias[k].mean, result.bias[k].stderr) for k in ("dR_over_R", "de1", "de2")}
    s = {k: (result.scatter[k]["value"], result.scatter[k]["uncertainty"]) for k in ("dR_over_R", "de1", "de2")}
    for mode, values in (("bias", b), ("scatter", s)):
        if any(v[0] is None or not math.isfinite(v[0]) for v in values.values()):
            out[mode] = None
            continue
        (r, re), (e1, e1e), (e2, e2e) = values["dR_over_R"], values["de1"], values["de2"]
        modulus = math.hypot(e1, e2)
        out[mode] = {
            "size": (r, re or 0.0),
            "e1": (e1, e1e or 0.0),
            "e2": (e2, e2e or 0.0),
            "e": (modulus, math.hypot((e1 * (e1e or 0.0)), (e2 * (e2e or 0.0))) / modulus if modulus else 0.0),
        }
    return out


def relative_change(base: dict, variant: dict) -> dict:
    """{metric: (change, error)} of ``variant`` against ``base`` (:func:`_metric_values` of one
    mode): size and e against their own base slope, e1 and e2 against the base |c_e|. The error is
    the two slopes' statistical errors in quadrature (ignoring that the draws are shared)."""
    if base is None or variant is None:
        return dict.fromkeys(METRICS)
    modulus = base["e"][0]
    out = {}
    for metric in METRICS:
        (b, be), (v, ve) = base[metric], variant[metric]
        scale = abs(modulus) if metric in ("e1", "e2") else abs(b)
        out[metric] = None if scale == 0 else ((v - b) / scale, math.hypot(be, ve) / scale)
    return out


def default_config(band: str, sca: int, realizations: int, seed: int, position=None):
    """The Roman default's simulation at (band, sca, position), as ``tablebuild`` builds it."""
    from nlpsf.slopes import tablebuild

    return tablebuild.TableSettings.roman(realizations=realizations, seed=seed).config(band, sca, position=position)


def variant_configs(config, optical_variance_arcsec2: float | None) -> dict[str, list[tuple[object, float]]]:
    """The configurations each part compares against the default, with the sign to apply to the
    change: {part: [(config, sign), ...]}; brighter-fatter's pair is built by :func:`bfe_pair`."""
    from nlpsf.request import presets as roman_default

    scene = config.scene
    out: dict[str, list[tuple[object, float]]] = {}
    if optical_variance_arcsec2 is not None:
        jitter = math.sqrt(roman_default.JITTER_ARCSEC**2 + abs(optical_variance_arcsec2))
        sign = 1.0 if optical_variance_arcsec2 >= 0 else -1.0
        out["optical_model"] = [(replace(config, scene=replace(scene, jitter_arcsec=jitter)), sign)]
    out["sed"] = [(replace(config, scene=replace(scene, sed=f"blackbody:{t:g}")), 1.0) for t in SED_RANGE_K]
    out["jitter"] = [(replace(config, scene=replace(scene, jitter_arcsec=j)), 1.0) for j in JITTER_RANGE_ARCSEC]
    out["charge_diffusion"] = [(replace(config, scene=replace(scene, charge_diffusion_px=DIFFUSION_ALTERNATIVE_PX)), 1.0)]
    out["pupil_scale"] = [(replace(config, pupil_scale=PUPIL_ALTERNATIVE), 1.0)]
    out["nl_shape"] = [(replace(config, scene=replace(scene, nl_coefficients=NL_SHAPE_COEFFICIENTS)), 1.0)]
    return out


def bfe_pair(config):
    """(final frame without BFE, with BFE): the default scene read as one final frame of the same
    exposure, the comparison brighter-fatter is measured by (a ramp refuses it)."""
    frame = replace(config, ramp=None)
    return frame, replace(frame, scene=replace(frame.scene, bfe_coefficient=BFE_COEFFICIENT))


def _slopes(config, magnitudes, linearise_at):
    from nlpsf.sim import experiment

    try:
        return [_metric_values(r) for r in experiment.slopes(config, list(magnitudes), linearise_at=linearise_at)]
    except Exception as error:  # a variant the simulator refuses is recorded, not fatal
        return [{"error": f"{type(error).__name__}: {error}"} for _ in magnitudes]


def measure_point(
    band: str,
    sca: int,
    magnitudes,
    realizations: int = 50,
    seed: int = 1,
    optical_variance_arcsec2: float | None = None,
    parts: tuple[str, ...] = PART_NAMES,
) -> dict:
    """Every part's signed relative change at (band, sca) for each magnitude and mode:
    {"parts": {part: {mode: {metric: [[m, change, error, which_end], ...]}}}, "base": ...}.
    For a two-ended part both ends are kept (``ends``) and the larger |change| is the part's."""
    from nlpsf.request import presets as roman_default

    linearise = roman_default.LINEARISE_AT
    config = default_config(band, sca, realizations, seed)
    base = _slopes(config, magnitudes, linearise)
    configs = variant_configs(config, optical_variance_arcsec2)
    runs: dict[str, list[tuple[list, list, float]]] = {}
    for name, variants in configs.items():
        if name in parts:
            runs[name] = [(base, _slopes(c, magnitudes, linearise), sign) for c, sign in variants]
    if "brighter_fatter" in parts:
        frame, with_bfe = bfe_pair(config)
        runs["brighter_fatter"] = [(_slopes(frame, magnitudes, linearise), _slopes(with_bfe, magnitudes, linearise), 1.0)]
    out: dict = {"band": band, "sca": sca, "magnitudes": list(magnitudes), "parts": {}, "errors": {}}
    for name, pairs in runs.items():
        per_mode: dict = {mode: {metric: [] for metric in METRICS} for mode in MODES}
        for index, magnitude in enumerate(magnitudes):
            for mode in MODES:
                ends = []
                for end, (reference, variant, sign) in enumerate(pairs):
                    r, v = reference[index], variant[index]
                    if "error" in r or "error" in v:
                        out["errors"][name] = r.get("error") or v.get("error")
                        continue
                    change = relative_change(r[mode], v[mode])
                    ends.append({m: None if c is None else (sign * c[0], c[1], end) for m, c in change.items()})
                for metric in METRICS:
                    values = [e[metric] for e in ends if e[metric] is not None]
                    if not values:
                        per_mode[mode][metric].append([magnitude, None, None, None])
                        continue
                    worst = max(values, key=lambda c: abs(c[0]))
                    per_mode[mode][metric].append([magnitude, worst[0], worst[1], worst[2]])
        out["parts"][name] = per_mode
    out["base"] = {
        str(m): {mode: None if b.get(mode) is None else {k: v[0] for k, v in b[mode].items()} for mode in MODES}
        for m, b in zip(magnitudes, base, strict=True)
        if "error" not in b
    }
    return out
