"""The scene model: what a real Roman star goes through besides the paper's idealised chain.

This module is the one owner of the scene effects. A :class:`SceneModel` is a frozen description
with every effect off by default (the paper's scene: SCA centre, one wavelength, the quadratic NL
only). The effects, in the order a photon meets them (DESIGN.md, "The scene model"):

``position``
    field position on the SCA in pixels (1-4088 each axis): the Zernikes are interpolated
    bilinearly between the SCA's corner field points exactly as ``galsim.roman.getPSF(SCA_pos=)``
    does (``nlpsf.roman.aberrations``).
``sed``
    the star's spectrum: ``flat`` (flat f_nu), ``blackbody:TEFF`` (kelvin), a vendored spectrum by
    name (``k0v``: ``nlpsf.seds``) or a two-column table (wavelength nm, f_lambda or f_nu as
    ``sed_units`` says). The PSF is the photon-weighted mean
    over the band: counts per unit wavelength proportional to A_eff(lambda) f_lambda lambda. The
    flux in electrons stays the one the AB magnitude in the band gives (a band AB magnitude is a
    photon count relative to a flat-f_nu source's, whatever the SED).
``jitter`` / ``charge_diffusion``
    Gaussian blurs (arcsec rms per axis; native pixels rms). A convolution with a Gaussian of rms
    sigma multiplies the Fourier coefficients of the effective PSF by exp(-2 pi^2 sigma^2 f^2),
    which is exact on the periodic field the optics are kept on (``optics.EffectivePSF``).
``ipc``
    interpixel capacitance: a 3x3 kernel coupling *native* pixels (GalSim's normalised
    ``roman.ipc_kernel``, a symmetric nearest-neighbour alpha, or a 3x3 file), applied ``after``
    (default, as GalSim's Roman pipeline) or ``before`` the NL.
``nl_coefficients``
    NL beyond the quadratic: S = Q - b2 Q^2 - b3 Q^3 - b4 Q^4 ..., paper sign convention; the
    field holds (b3, b4, ...), b2 is the simulation's beta (so per-pixel scatter applies to b2).
``bfe_coefficient``
    brighter-fatter (see :func:`brighter_fatter`), no default.
``background_e``
    sky plus dark charge per native pixel over the exposure, added before the NL and subtracted
    afterwards as a local sky estimate does: a star-free pixel's own level, its NL included
    (S(Q + B) - S(B); ``experiment.sky``).

The kernels that act on the stamps (blurs, IPC, brighter-fatter, the detector chain) are in
``nlpsf.scene_kernels``, re-exported here. Why the rest is one module of ~700 lines: the registry,
the description, its validation and its readers from user input (CLI strings, API objects, JSON
files) are the one owner of the scene's fields; each field's rule sits beside the field, so adding an
effect is one registry entry and the checks it needs, in one place.

Rescaling rules. The tables' exposure and beta0 rescaling rests on the metrics depending on beta
and flux only through beta Q. Position, SED, jitter, diffusion and IPC (either order) are linear in
the charge and keep that rule. Polynomial NL (b3 Q^3 ...), brighter-fatter (a charge-dependent
redistribution, ~ a Q^2) and a background (beta (Q + B)^2 has a beta B term at fixed B) each add a
flux dependence of their own, so :meth:`SceneModel.breaks_beta_q_scaling` names them and callers
must simulate at the request's exposure and beta0 instead of rescaling.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields, replace
from functools import lru_cache
from importlib import resources
from pathlib import Path

import numpy as np

from . import roman, seds
from .checks import InputError, check_integer, check_number
from .scene_kernels import (  # noqa: F401  (re-exported: the scene's public kernels)
    apply_ipc,
    apply_ipc_adjoint,
    blur,
    brighter_fatter,
    charge_before_nl,
    detector_chain,
    gaussian_transfer,
)

#: GalSim 2.8.5 ``galsim/roman/__init__.py`` ``ipc_kernel`` before its normalisation (rows are y,
#: columns x, as a GalSim Image's array); :data:`ROMAN_IPC_KERNEL` divides it by its sum as GalSim does.
_ROMAN_IPC_RAW = (
    (0.001269938, 0.015399776, 0.001199862),
    (0.013800177, 1.0, 0.015600367),
    (0.001270391, 0.016129619, 0.001200137),
)
ROMAN_IPC_KERNEL: tuple[tuple[float, ...], ...] = tuple(
    tuple(v / float(np.sum(_ROMAN_IPC_RAW)) for v in row) for row in _ROMAN_IPC_RAW
)
#: GalSim's Roman constants (``galsim.roman.jitter_rms``, ``charge_diffusion``).
ROMAN_JITTER_ARCSEC = 0.014
ROMAN_CHARGE_DIFFUSION_PX = 0.1

IPC_ORDERS = ("after", "before")
SED_UNITS = ("flambda", "fnu")
#: Limits a request may give (anything beyond is not a Roman scene).
MAX_JITTER_ARCSEC = 1.0
MAX_DIFFUSION_PX = 3.0
MAX_BACKGROUND_E = 1e5
MAX_BFE = 1e-4
MAX_NL_ORDER = 8
#: Largest nearest-neighbour IPC coupling alpha.
MAX_IPC_ALPHA = 0.2
#: Default relative accuracy the number of wavelengths is chosen for (see :func:`choose_wavelengths`).
WAVELENGTH_ACCURACY = 1e-2
#: Empirical factor between the relative error of the NL slopes from one wavelength and the band's
#: photon-weighted var / lambda^2 (measured on H158, W146 and R062 in
#: ``tests/library/test_scene.py::test_wavelength_count_meets_its_stated_accuracy``).
SLOPE_BINNING_FACTOR = 4.0


@dataclass(frozen=True)
class SceneEffect:
    """One scene effect: the one entry the presets, the impact report, the solver and the API read.

    ``fields``: the ``SceneModel`` fields that set it (copied together when a solve simulates it);
    ``off``: the values that switch it off; ``nominal``: the Roman value the impact report and the
    shipped model uncertainty try when a scene leaves it off (a None value: no default), with its
    ``source``; ``kind``: "optical" (acts on the PSF before the pixels) or "detector"; ``breaks_beta_q``:
    it adds a flux dependence of its own (the tables' beta x flux rescaling then does not hold);
    ``combines_with``: what it can be simulated together with; ``is_on``: whether a scene has it.
    """

    name: str
    fields: tuple[str, ...]
    off: dict
    nominal: dict
    source: str
    kind: str
    breaks_beta_q: bool
    combines_with: str
    is_on: Callable[[SceneModel], bool]
    #: Part of the "galsim-roman" preset (at its nominal value).
    in_roman_preset: bool = False


_EVERY = "every other effect, and a ramp"
#: The scene effects, in the order they act (the impact report's contract uses this order).
#: Adding an effect: one entry here, its kernel (``detector_chain`` or the optics) and its test.
REGISTRY: dict[str, SceneEffect] = {
    e.name: e
    for e in (
        SceneEffect(
            "position", ("position",), {"position": None}, {"position": (4.0, 4.0)},
            "a corner of the SCA (pixel 4, 4)", "optical", False, _EVERY, lambda s: s.position is not None, False,
        ),
        SceneEffect(
            "sed", ("sed", "sed_table", "sed_units", "n_wavelengths"), {"sed": None, "sed_table": None, "n_wavelengths": None},
            {"sed": "flat"}, "flat f_nu (the AB reference)", "optical", False, _EVERY, lambda s: s.sed is not None, True,
        ),
        SceneEffect(
            "jitter", ("jitter_arcsec",), {"jitter_arcsec": 0.0}, {"jitter_arcsec": ROMAN_JITTER_ARCSEC},
            "galsim.roman.jitter_rms", "optical", False, _EVERY, lambda s: s.jitter_arcsec > 0, True,
        ),
        SceneEffect(
            "charge_diffusion", ("charge_diffusion_px",), {"charge_diffusion_px": 0.0},
            {"charge_diffusion_px": ROMAN_CHARGE_DIFFUSION_PX}, "galsim.roman.charge_diffusion", "optical", False, _EVERY,
            lambda s: s.charge_diffusion_px > 0, True,
        ),
        SceneEffect(
            "ipc", ("ipc", "ipc_label", "ipc_order"), {"ipc": None, "ipc_label": None},
            {"ipc": ROMAN_IPC_KERNEL, "ipc_label": "roman"}, "galsim.roman.ipc_kernel", "detector", False, _EVERY,
            lambda s: s.ipc is not None, True,
        ),
        SceneEffect(
            "nl_polynomial", ("nl_coefficients",), {"nl_coefficients": ()}, {"nl_coefficients": (1e-13, 1e-18)},
            "b3, b4 each 0.1 % of the signal at 1e5 e- (the residual level quoted in issue 8)", "detector", True, _EVERY,
            lambda s: any(c != 0 for c in s.nl_coefficients),
        ),
        SceneEffect(
            "brighter_fatter", ("bfe_coefficient",), {"bfe_coefficient": 0.0}, {"bfe_coefficient": None},
            "no default: give a coefficient to measure it", "detector", True,
            "every other effect; not a ramp (ramps.RAMP_REFUSES)", lambda s: s.bfe_coefficient != 0,
        ),
        SceneEffect(
            "background", ("background_e",), {"background_e": 0.0}, {"background_e": 100.0},
            "100 e- per pixel, of the order of Roman's sky over 168 s", "detector", True, _EVERY,
            lambda s: s.background_e > 0,
        ),
    )
}  # fmt: skip
#: Names of the effects, in the order they act.
EFFECTS: tuple[str, ...] = tuple(REGISTRY)
#: Representative values the impact report tries for an effect the scene leaves off, with their
#: sources as ``note`` (read from :data:`REGISTRY`).
NOMINAL: dict[str, dict] = {name: {**e.nominal, "note": e.source} for name, e in REGISTRY.items()}


#: Where :func:`shipped_model_uncertainty` reads the shipped measurement.
MODEL_UNCERTAINTY_FILE = "scene_model_uncertainty.json"


@lru_cache(maxsize=1)
def shipped_model_uncertainty() -> dict:
    """What the paper's scene leaves out, measured by ``scripts/model_uncertainty.py`` (worst
    |impact| of each effect at its :data:`NOMINAL` value over SCA 1 and 18, two magnitudes; see
    the file's ``description``). The solver's answers without ``accuracy`` read their model part here."""
    path = Path(str(resources.files("nlpsf") / "data" / MODEL_UNCERTAINTY_FILE))
    return json.loads(path.read_text())


def _tuple_of_floats(values, name: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise InputError(name, f"must be a list of numbers, got {values!r}") from None
    if not all(math.isfinite(v) for v in out):
        raise InputError(name, f"must be finite, got {values!r}")
    return out


@dataclass(frozen=True)
class SceneModel:
    """Which scene effects a simulation includes; all off by default (the paper's scene).

    Build one from user strings with :func:`from_options`, a preset with :func:`preset`, or JSON
    with :func:`load`. Fields are validated here, once; kernels downstream trust them.
    """

    position: tuple[float, float] | None = None
    sed: str | None = None
    sed_table: tuple[tuple[float, ...], tuple[float, ...]] | None = None
    sed_units: str = "flambda"
    n_wavelengths: int | None = None
    wavelength_accuracy: float = WAVELENGTH_ACCURACY
    jitter_arcsec: float = 0.0
    charge_diffusion_px: float = 0.0
    ipc: tuple[tuple[float, ...], ...] | None = None
    ipc_label: str | None = None
    ipc_order: str = "after"
    nl_coefficients: tuple[float, ...] = ()
    bfe_coefficient: float = 0.0
    background_e: float = 0.0
    name: str | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        if self.position is not None:
            pos = _tuple_of_floats(self.position, "position")
            if len(pos) != 2:
                raise InputError("position", f"give two pixel coordinates X,Y, got {self.position!r}")
            for v in pos:
                check_number(v, "position", 1.0, float(roman.SCA_PIXELS))
            object.__setattr__(self, "position", pos)
        if self.sed is not None:
            object.__setattr__(self, "sed", _check_sed(self.sed, self.sed_table))
        if self.sed_units not in SED_UNITS:
            raise InputError("sed_units", f"must be one of {', '.join(SED_UNITS)}, got {self.sed_units!r}")
        if self.sed is not None and not self.sed.startswith("file"):
            # The units of a named SED are its definition's, not a file column's: a flat star is
            # flat in f_nu, a blackbody and the vendored spectra are tabulated as f_lambda.
            object.__setattr__(self, "sed_units", "fnu" if self.sed == "flat" else "flambda")
        if self.sed_table is not None:
            if self.sed is None or not self.sed.startswith("file"):
                raise InputError("sed", "a tabulated SED needs sed='file:NAME'")
            object.__setattr__(self, "sed_table", _check_table(self.sed_table))
        if self.n_wavelengths is not None:
            check_integer(self.n_wavelengths, "n_wavelengths", 1, 64)
        check_number(self.wavelength_accuracy, "wavelength_accuracy", 0.0, 1.0, open_low=True)
        check_number(self.jitter_arcsec, "jitter", 0.0, MAX_JITTER_ARCSEC)
        check_number(self.charge_diffusion_px, "charge_diffusion", 0.0, MAX_DIFFUSION_PX)
        if self.ipc is not None:
            object.__setattr__(self, "ipc", _check_kernel(self.ipc))
            if self.ipc_label is None:
                object.__setattr__(self, "ipc_label", "kernel")
        if self.ipc_order not in IPC_ORDERS:
            raise InputError("ipc_order", f"must be one of {', '.join(IPC_ORDERS)}, got {self.ipc_order!r}")
        coefficients = _tuple_of_floats(self.nl_coefficients, "nl_coefficients")
        if len(coefficients) > MAX_NL_ORDER - 2:
            raise InputError("nl_coefficients", f"at most {MAX_NL_ORDER - 2} coefficients beyond b2 (order {MAX_NL_ORDER})")
        object.__setattr__(self, "nl_coefficients", coefficients)
        check_number(self.bfe_coefficient, "bfe", -MAX_BFE, MAX_BFE)
        check_number(self.background_e, "background", 0.0, MAX_BACKGROUND_E)

    # --- which effects are on -------------------------------------------------------------
    def effects_on(self) -> dict[str, bool]:
        return {name: effect.is_on(self) for name, effect in REGISTRY.items()}

    @property
    def is_paper(self) -> bool:
        return not any(self.effects_on().values())

    @property
    def plain_detector(self) -> bool:
        """No detector effect beyond the quadratic NL: the experiment keeps the paper's expressions."""
        on = self.effects_on()
        return not any(on[name] for name, effect in REGISTRY.items() if effect.kind == "detector")

    def breaks_beta_q_scaling(self) -> list[str]:
        """Effects that add a flux dependence of their own, so beta and flux no longer enter only
        through beta Q (see the module docstring): the tables' rescaling must not be used."""
        on = self.effects_on()
        return [name for name, effect in REGISTRY.items() if effect.breaks_beta_q and on[name]]

    def without(self, effect: str) -> SceneModel:
        """This scene with one effect switched off."""
        if effect not in REGISTRY:
            raise InputError("effect", f"unknown effect {effect!r}; one of {', '.join(EFFECTS)}")
        return replace(self, name=None, **REGISTRY[effect].off)

    def with_nominal(self, effect: str) -> SceneModel | None:
        """This scene with ``effect`` at its :data:`NOMINAL` value (None when it has no default)."""
        values = {k: v for k, v in NOMINAL[effect].items() if k != "note"}
        if any(v is None for v in values.values()):
            return None
        return replace(self, name=None, **values)

    # --- optics ------------------------------------------------------------------------------
    def spectrum(self) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
        """f_lambda (arbitrary units) tabulated on wavelengths [nm], or None for flat f_nu."""
        if self.sed is None or self.sed == "flat":
            return None
        if self.sed.startswith("blackbody:"):
            temperature = float(self.sed.split(":", 1)[1])
            wave = np.linspace(300.0, 2600.0, 2301)
            return tuple(wave), tuple(planck_flambda(wave, temperature))
        if seds.is_named(self.sed):
            wave, flux = (np.asarray(v) for v in seds.table(self.sed))
            return tuple(wave), tuple(flux / flux.max())
        wave, flux = (np.asarray(v) for v in self.sed_table)
        if self.sed_units == "fnu":
            flux = flux / wave**2  # f_lambda = f_nu c / lambda^2
        return tuple(wave), tuple(flux / flux.max())

    def wavelengths(self, band: str, config_n_wavelengths: int = 1, sca: int = 18, source: str | None = None) -> int:
        """How many wavelengths the optics integrate (1: achromatic at the effective wavelength)."""
        if self.sed is None:
            return config_n_wavelengths
        if self.n_wavelengths is not None:
            return self.n_wavelengths
        if config_n_wavelengths > 1:
            return config_n_wavelengths
        return choose_wavelengths(band, self.spectrum(), self.wavelength_accuracy, sca, source)[0]

    def blur_sigma_arcsec(self) -> float:
        """Total rms of the Gaussian blurs (jitter and charge diffusion add in quadrature)."""
        return math.hypot(self.jitter_arcsec, self.charge_diffusion_px * roman.PIXEL_SCALE_ARCSEC)

    # --- description -------------------------------------------------------------------------
    def to_dict(self) -> dict:
        out = asdict(self)
        out["effects_on"] = self.effects_on()
        return out

    def describe(self) -> str:
        if self.is_paper:
            return "paper scene (SCA centre, one wavelength, quadratic NL only)"
        parts = []
        if self.position is not None:
            parts.append(f"position {self.position[0]:g},{self.position[1]:g}")
        if self.sed is not None:
            parts.append(f"SED {self.sed}")
        if self.jitter_arcsec:
            parts.append(f'jitter {self.jitter_arcsec:g}"')
        if self.charge_diffusion_px:
            parts.append(f"diffusion {self.charge_diffusion_px:g} px")
        if self.ipc is not None:
            parts.append(f"IPC {self.ipc_label} {self.ipc_order} NL")
        if self.effects_on()["nl_polynomial"]:
            parts.append("NL b3.. " + ",".join(f"{c:g}" for c in self.nl_coefficients))
        if self.bfe_coefficient:
            parts.append(f"BFE {self.bfe_coefficient:g}")
        if self.background_e:
            parts.append(f"background {self.background_e:g} e-")
        return (f"{self.name}: " if self.name else "") + ", ".join(parts)


def _check_sed(sed: str, table) -> str:
    if not isinstance(sed, str):
        raise InputError("sed", f"must be flat, blackbody:TEFF, {_NAMES} or file:NAME, got {sed!r}")
    text = sed.strip()
    if seds.is_named(text):
        return text.lower()
    if text == "flat" or text.startswith("file"):
        if text.startswith("file") and table is None:
            raise InputError("sed", "a file SED needs its table (load it with scene.read_sed)")
        return text
    if text.startswith("blackbody:"):
        try:
            temperature = float(text.split(":", 1)[1])
        except ValueError:
            raise InputError("sed", f"blackbody needs a temperature in K, got {sed!r}") from None
        check_number(temperature, "sed", 1000.0, 1e6)
        return f"blackbody:{temperature:g}"
    raise InputError("sed", f"unknown SED {sed!r}: use flat, blackbody:TEFF, {_NAMES} or a two-column file (nm, flux)")


#: The vendored spectra's names, for messages.
_NAMES = " | ".join(seds.NAMED)


def _check_table(table) -> tuple[tuple[float, ...], tuple[float, ...]]:
    try:
        wave, flux = (np.asarray(v, dtype=np.float64) for v in table)
    except (TypeError, ValueError):
        raise InputError("sed", "the SED table must be two columns of numbers") from None
    if wave.ndim != 1 or wave.shape != flux.shape or wave.size < 2:
        raise InputError("sed", "the SED table needs at least two rows of (wavelength nm, flux)")
    if not (np.all(np.isfinite(wave)) and np.all(np.isfinite(flux))):
        raise InputError("sed", "the SED table holds NaN or infinite values")
    if np.any(np.diff(wave) <= 0) or np.any(flux < 0) or not np.any(flux > 0):
        raise InputError("sed", "the SED table needs increasing wavelengths and non-negative flux, not all zero")
    return tuple(wave), tuple(flux)


def _check_kernel(kernel) -> tuple[tuple[float, ...], ...]:
    try:
        array = np.asarray(kernel, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("ipc", "the IPC kernel must be 3x3 numbers") from None
    if array.shape != (3, 3):
        raise InputError("ipc", f"the IPC kernel must be 3x3, got shape {array.shape}")
    if not np.all(np.isfinite(array)) or np.any(array < 0) or array.sum() <= 0:
        raise InputError("ipc", "the IPC kernel must be finite and non-negative")
    # Charge is conserved: normalise as GalSim's applyIPC does.
    array = array / array.sum()
    return tuple(tuple(float(v) for v in row) for row in array)


def planck_flambda(wavelength_nm: np.ndarray, temperature_k: float) -> np.ndarray:
    """Black-body f_lambda up to a constant: lambda^-5 / (exp(hc / lambda k T) - 1)."""
    hc_over_k_nm_k = 1.438776877e7  # h c / k in nm K (CODATA 2018)
    x = hc_over_k_nm_k / (np.asarray(wavelength_nm, dtype=np.float64) * temperature_k)
    lam = np.asarray(wavelength_nm, dtype=np.float64) / 1000.0
    return 1.0 / (lam**5 * np.expm1(x))


def binning_error(band: str, spectrum, n: int, sca: int = 18, source: str | None = None) -> float:
    """Estimated relative error of the NL slopes (size and |e|) from n photon-weighted wavelengths.

    The band is cut into n equal-width bins, each drawn at its photon-weighted mean wavelength. A
    diffraction PSF's size scales with lambda, so collapsing the whole band onto one wavelength
    misses var / lambda^2 of its squared size (var the photon-weighted variance of the wavelength);
    the slopes respond a few times more strongly (:data:`SLOPE_BINNING_FACTOR`). Measured, the
    error then falls as 1/n, not as the 1/n^2 of a smooth integrand
    (``tests/library/test_scene.py::test_wavelength_count_meets_its_stated_accuracy`` shows the convergence
    against 32 wavelengths), so the estimate is that single-bin figure divided by n. n = 1 with a
    flat f_nu SED is the achromatic PSF at the band's effective wavelength, which this does not cover.
    """
    from .optics import photon_weights_fine

    curve = roman.throughput(band, sca=sca, source=source or roman.DEFAULT_THROUGHPUT)
    fine, photons = photon_weights_fine(curve, spectrum, 1)
    weight = np.trapezoid(photons, fine)
    mean = np.trapezoid(photons * fine, fine) / weight
    var = np.trapezoid(photons * (fine - mean) ** 2, fine) / weight
    return SLOPE_BINNING_FACTOR * float(var / mean**2) / n


@lru_cache(maxsize=256)
def choose_wavelengths(band: str, spectrum, accuracy: float, sca: int = 18, source: str | None = None) -> tuple[int, float]:
    """Fewest wavelengths whose estimated slope error (:func:`binning_error`) is below ``accuracy``."""
    for n in range(2, 65):
        error = binning_error(band, spectrum, n, sca, source)
        if error <= accuracy:
            return n, error
    return 64, binning_error(band, spectrum, 64, sca, source)


# --- presets and JSON -------------------------------------------------------------------------


def preset(name: str) -> SceneModel:
    """A named scene of this module: "paper", the paper's idealised scene; "galsim-roman", GalSim's
    Roman constants (the registry's effects marked for it at their nominal values: jitter 0.014",
    diffusion 0.1 px, flat f_nu, GalSim's IPC), which the GalSim cross-checks use. The Roman
    default's scene ("roman") is ``nlpsf.roman_default``'s (``roman_default.preset_base``), which
    builds on this module."""
    galsim_values = {k: v for e in REGISTRY.values() if e.in_roman_preset for k, v in e.nominal.items()}
    presets = {"paper": SceneModel(name="paper"), "galsim-roman": SceneModel(name="galsim-roman", **galsim_values)}
    if name not in presets:
        hint = "; the Roman default's scene is nlpsf.roman_default.preset_base('roman')" if name == "roman" else ""
        raise InputError("scene", f"unknown scene preset {name!r}; presets: {', '.join(PRESETS)}, or a JSON file{hint}")
    return presets[name]


#: This module's scene presets by name ("roman", the default's scene, is ``nlpsf.roman_default``'s).
PRESETS = ("paper", "galsim-roman")


def to_json(scene: SceneModel) -> str:
    data = asdict(scene)
    return json.dumps(data, indent=1)


def from_dict(data: dict) -> SceneModel:
    if not isinstance(data, dict):
        raise InputError("scene", "a scene must be a JSON object")
    known = {f.name for f in fields(SceneModel)}
    unknown = sorted(set(data) - known - {"effects_on"})
    if unknown:
        raise InputError("scene", f"unknown scene fields {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    values = {k: v for k, v in data.items() if k in known}
    for key in ("position", "nl_coefficients"):
        if values.get(key) is not None:
            values[key] = tuple(values[key])
    if values.get("ipc") is not None:
        values["ipc"] = tuple(tuple(row) for row in values["ipc"])
    if values.get("sed_table") is not None:
        values["sed_table"] = tuple(tuple(col) for col in values["sed_table"])
    return SceneModel(**values)


def save(scene: SceneModel, path) -> None:
    Path(path).write_text(to_json(scene) + "\n")


def load(name_or_path: str) -> SceneModel:
    """A preset by name, or a scene saved as JSON."""
    if name_or_path in PRESETS:
        return preset(name_or_path)
    path = Path(name_or_path)
    if not path.is_file():
        raise InputError("scene", f"no preset or file named {name_or_path!r}; presets: {', '.join(PRESETS)}")
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise InputError("scene", f"cannot read {name_or_path}: {error}") from None
    return from_dict(data)


def read_table(path: str, name: str, columns: int) -> np.ndarray:
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # an empty file is refused below, by shape
            array = np.loadtxt(path, ndmin=2, dtype=np.float64)
    except (OSError, ValueError) as error:
        raise InputError(name, f"cannot read {path}: {error}") from None
    if columns and array.shape[1] != columns:
        raise InputError(name, f"{path} must have {columns} columns, has {array.shape[1]}")
    return array


def parse_ipc(text) -> tuple[tuple[tuple[float, ...], ...] | None, str | None]:
    """``roman`` | ``none`` | a nearest-neighbour alpha | a 3x3 file -> (kernel, label)."""
    if text is None:
        return None, None
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        text = repr(float(text))
    if not isinstance(text, str):
        raise InputError("ipc", f"must be roman, a coupling alpha or a 3x3 file, got {text!r}")
    lowered = text.strip().lower()
    if lowered in ("", "none", "off"):
        return None, None
    if lowered == "roman":
        return ROMAN_IPC_KERNEL, "roman"
    try:
        alpha = float(lowered)
    except ValueError:
        array = read_table(text, "ipc", 0)
        if array.shape != (3, 3):
            raise InputError("ipc", f"{text} must hold a 3x3 kernel, got shape {array.shape}") from None
        return _check_kernel(array), f"file:{Path(text).name}"
    alpha = check_number(alpha, "ipc", 0.0, MAX_IPC_ALPHA)
    kernel = ((0.0, alpha, 0.0), (alpha, 1.0 - 4 * alpha, alpha), (0.0, alpha, 0.0))
    return _check_kernel(kernel), f"alpha={alpha:g}"


def parse_sed(text: str | None, units: str = "flambda") -> dict:
    """``flat`` | ``blackbody:TEFF`` | a vendored name (``k0v``) | a two-column file -> SceneModel fields."""
    if text is None:
        return {}
    if not isinstance(text, str):
        raise InputError("sed", f"must be flat, blackbody:TEFF, {_NAMES} or a file, got {text!r}")
    stripped = text.strip()
    if stripped == "flat" or stripped.startswith("blackbody:") or seds.is_named(stripped):
        return {"sed": stripped}
    if not Path(stripped).is_file():
        raise InputError("sed", f"unknown SED {text!r}: use flat, blackbody:TEFF, {_NAMES} or a two-column file (nm, flux)")
    array = read_table(stripped, "sed", 2)
    return {"sed": f"file:{Path(stripped).name}", "sed_table": (tuple(array[:, 0]), tuple(array[:, 1])), "sed_units": units}


def parse_position(text) -> tuple[float, float] | None:
    if text is None:
        return None
    if isinstance(text, str):
        parts = text.replace(" ", "").split(",")
        if len(parts) != 2:
            raise InputError("position", f"give X,Y in SCA pixels (1-{roman.SCA_PIXELS}), got {text!r}")
        try:
            return float(parts[0]), float(parts[1])
        except ValueError:
            raise InputError("position", f"give X,Y in SCA pixels, got {text!r}") from None
    return tuple(text)


def parse_coefficients(text) -> tuple[float, ...]:
    if text is None:
        return ()
    if isinstance(text, str):
        try:
            return tuple(float(v) for v in text.split(",") if v.strip())
        except ValueError:
            raise InputError("nl_coefficients", f"give comma-separated numbers, got {text!r}") from None
    return tuple(text)


def from_options(
    base: SceneModel | str | None = None,
    *,
    position=None,
    sed=None,
    sed_units: str = "flambda",
    jitter=None,
    charge_diffusion=None,
    ipc=None,
    ipc_order: str | None = None,
    nl_coefficients=None,
    bfe=None,
    background=None,
    n_wavelengths: int | None = None,
) -> SceneModel:
    """A scene from a preset/file (``base``) overridden by user strings, as the CLI and API give them.

    ``nl_coefficients`` here are (b3, b4, ...); callers that accept b2 first split it off as beta0.
    """
    scene = base if isinstance(base, SceneModel) else (load(base) if base else SceneModel())
    changes: dict = {}
    if position is not None:
        changes["position"] = parse_position(position)
    if sed is not None:
        changes.update({"sed": None, "sed_table": None} | parse_sed(sed, sed_units))
    if jitter is not None:
        changes["jitter_arcsec"] = jitter
    if charge_diffusion is not None:
        changes["charge_diffusion_px"] = charge_diffusion
    if ipc is not None:
        changes["ipc"], changes["ipc_label"] = parse_ipc(ipc)
    if ipc_order is not None:
        changes["ipc_order"] = ipc_order
    if nl_coefficients is not None:
        changes["nl_coefficients"] = parse_coefficients(nl_coefficients)
    if bfe is not None:
        changes["bfe_coefficient"] = bfe
    if background is not None:
        changes["background_e"] = background
    if n_wavelengths is not None:
        changes["n_wavelengths"] = n_wavelengths
    return moved_or_changed(scene, changes)


def check_first_order(scene: SceneModel, full_well: float) -> None:
    """Refuse a scene whose detector effects leave the models' first-order regime inside the full
    well, where every moment fit fails and a simulation could only end in an error: the higher NL
    terms' share of the response slope, sum k |b_k| Q^(k-1), and the brighter-fatter area change
    |bfe| Q must both stay below 1 at Q = ``full_well`` (e-). InputError naming ``scene.FIELD``."""
    higher = sum(k * abs(b) * full_well ** (k - 1) for k, b in enumerate(scene.nl_coefficients, start=3))
    if not higher < 1.0:
        raise InputError(
            "scene.nl_coefficients",
            f"sum k |b_k| Q^(k-1) at the full well ({full_well:g} e-) is {higher:.3g}; it must stay below 1 "
            "(the higher NL terms are a perturbation of the response, and dS/dQ must stay positive)",
        )
    if not abs(scene.bfe_coefficient) * full_well < 1.0:
        raise InputError(
            "scene.bfe",
            f"|bfe| x full_well = {abs(scene.bfe_coefficient) * full_well:.3g}; it must stay below 1 "
            f"(the first-order brighter-fatter model), i.e. |bfe| < {1.0 / full_well:.3g} 1/e- at this full well",
        )


def from_request(fields_: dict | None, base: SceneModel | None = None) -> SceneModel:
    """A scene from the REST API's ``scene`` object (no files on a server: tables and kernels inline).

    Keys: ``preset`` (paper | roman), ``position`` [x, y], ``sed`` (flat | blackbody:TEFF | k0v),
    ``sed_table`` [[nm, flux], ...] with ``sed_units``, ``jitter``, ``charge_diffusion``, ``ipc``
    (roman | alpha | 3x3 rows), ``ipc_order``, ``nl_coefficients`` (b3, b4, ...), ``bfe``,
    ``background``, ``n_wavelengths``. Unset keys keep the preset's value. ``base``: the scene the
    keys change when the caller resolved the preset (``nlpsf.roman_default.preset_base``).
    """
    if not fields_:
        return base or SceneModel()
    data = {k: v for k, v in fields_.items() if v is not None}
    named = data.pop("preset", None)
    if base is None:
        base = preset(named) if named is not None else SceneModel()
    changes: dict = {}
    if "sed_table" in data:
        rows = data.pop("sed_table")
        if data.get("sed") not in (None,) and not str(data.get("sed", "")).startswith("file"):
            raise InputError("sed", "give either sed or sed_table, not both")
        data.pop("sed", None)
        try:
            columns = tuple(zip(*rows, strict=True))
        except (TypeError, ValueError):
            raise InputError("sed_table", "must be rows of [wavelength nm, flux]") from None
        if len(columns) != 2:
            raise InputError("sed_table", "must be rows of [wavelength nm, flux]")
        changes.update(sed="file:request", sed_table=columns, sed_units=data.pop("sed_units", "flambda"))
    if "ipc" in data:
        value = data.pop("ipc")
        if isinstance(value, (list, tuple)):
            changes["ipc"], changes["ipc_label"] = _check_kernel(value), "kernel"
        elif isinstance(value, str) and value.strip().lower() not in ("roman", "none", "off"):
            raise InputError("ipc", f"must be roman, a coupling alpha or 3x3 rows, got {value!r}")
        else:
            changes["ipc"], changes["ipc_label"] = parse_ipc(value)
    if "sed" in data:
        sed = data.pop("sed")
        if isinstance(sed, str) and sed.strip() != "flat" and not sed.strip().startswith("blackbody:") and not seds.is_named(sed):
            raise InputError("sed", f"unknown SED {sed!r}: use flat, blackbody:TEFF, {_NAMES} or sed_table")
        changes.update(sed=sed, sed_table=None)
    renames = {
        "jitter": "jitter_arcsec",
        "charge_diffusion": "charge_diffusion_px",
        "bfe": "bfe_coefficient",
        "background": "background_e",
    }
    for key, value in data.items():
        if key == "sed_units":
            changes["sed_units"] = value
        elif key in ("position", "nl_coefficients"):
            changes[key] = tuple(value)
        elif key in ("ipc_order", "n_wavelengths"):
            changes[key] = value
        elif key in renames:
            changes[renames[key]] = value
        else:
            raise InputError("scene", f"unknown scene field {key!r}")
    return moved_or_changed(base, changes)


def moved_or_changed(base: SceneModel, changes: dict) -> SceneModel:
    """``base`` with ``changes``, as every builder of a scene applies them: another scene, unnamed,
    when an effect changes; the same named scene when only its position moves (a preset at a point
    of the field is still that preset, as ``replace(scene, position=...)`` keeps it for the SCA range
    and the over-field answers), so that it describes itself alike however the position was given.
    A field given at the value it already has (an API body's ``sed_units`` default) changes nothing."""
    if not changes:
        return base
    same = all(getattr(base, key) == value for key, value in changes.items() if key != "position")
    return replace(base, name=base.name if same else None, **changes)
