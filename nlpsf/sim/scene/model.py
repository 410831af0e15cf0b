"""The scene description: :class:`SceneModel` (every effect off by default, each field checked
once here), what its SED means for the optics (the spectrum, how many wavelengths), and the
first-order limits of its detector models.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from functools import lru_cache

import numpy as np

from nlpsf import roman
from nlpsf.checks import InputError, check_integer, check_number
from nlpsf.frozen import replaced
from nlpsf.roman import seds

from .registry import (
    EFFECTS,
    IPC_ORDERS,
    MAX_BACKGROUND_E,
    MAX_BFE,
    MAX_DIFFUSION_PX,
    MAX_JITTER_ARCSEC,
    MAX_NL_ORDER,
    NOMINAL,
    REGISTRY,
    SED_UNITS,
    SLOPE_BINNING_FACTOR,
    WAVELENGTH_ACCURACY,
)


def _tuple_of_floats(values, name: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise InputError(name, f"must be a list of numbers, got {values!r}") from None
    if not all(math.isfinite(v) for v in out):
        raise InputError(name, f"must be finite, got {values!r}")
    return out


def _checked_position(position) -> tuple[float, float]:
    pos = _tuple_of_floats(position, "position")
    if len(pos) != 2:
        raise InputError("position", f"give two pixel coordinates X,Y, got {position!r}")
    for v in pos:
        check_number(v, "position", 1.0, float(roman.SCA_PIXELS))
    return pos


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
            object.__setattr__(self, "position", _checked_position(self.position))
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
            object.__setattr__(self, "ipc", check_kernel(self.ipc))
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

    def at(self, position) -> SceneModel:
        """This scene at ``position`` (pixels, checked; None: no position), its name kept:
        ``replace(self, position=position)``, without checking again the fields it had checked
        (a request's JSON position, an SCA range's nodes). What it worked out (which effects are
        on, its description) is worked out again: the position is among them."""
        moved = replaced(self, position=None if position is None else _checked_position(position))
        for worked_out in [key for key in moved.__dict__ if key.startswith("_")]:
            del moved.__dict__[worked_out]
        return moved

    # --- which effects are on -------------------------------------------------------------
    def effects_on(self) -> dict[str, bool]:
        """Each effect of the registry, on or off in this scene: worked out once (the scene is
        frozen; an answer asks several times) and handed out as a dict of its own."""
        found = self.__dict__.get("_effects_on")
        if found is None:
            found = tuple((name, effect.is_on(self)) for name, effect in REGISTRY.items())
            object.__setattr__(self, "_effects_on", found)
        return dict(found)

    @property
    def no_effects(self) -> bool:
        """Every effect off: the paper's idealised scene (at any position the ``position`` effect allows)."""
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
        # Every field is a number, a string, None or a tuple of numbers (``__post_init__`` makes them
        # so): ``dataclasses.asdict``'s dict without its deep copy of each (most of what an answer's conditions cost).
        out = {name: getattr(self, name) for name in _field_names()}
        out["effects_on"] = self.effects_on()
        return out

    def describe(self) -> str:
        """The scene in a line (worked out once: the scene is frozen, a string is shared safely)."""
        found = self.__dict__.get("_description")
        if found is None:
            found = self._description()
            object.__setattr__(self, "_description", found)
        return found

    def _description(self) -> str:
        if self.no_effects:
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


@lru_cache(maxsize=1)
def _field_names() -> tuple[str, ...]:
    """The scene's field names, in order (``dataclasses.fields`` looked up once)."""
    return tuple(f.name for f in fields(SceneModel))


def _check_sed(sed: str, table) -> str:
    if not isinstance(sed, str):
        raise InputError("sed", f"must be flat, blackbody:TEFF, {SED_NAMES} or file:NAME, got {sed!r}")
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
    raise InputError("sed", f"unknown SED {sed!r}: use flat, blackbody:TEFF, {SED_NAMES} or a two-column file (nm, flux)")


#: The vendored spectra's names, for messages.
SED_NAMES = " | ".join(seds.NAMED)


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


def check_kernel(kernel) -> tuple[tuple[float, ...], ...]:
    """A 3x3 IPC kernel checked and normalised to unit sum (a kernel given as tuples is checked once:
    every scene built from another, ``dataclasses.replace``, checks its kernel again)."""
    if isinstance(kernel, tuple) and all(isinstance(row, tuple) for row in kernel):
        return _checked_kernel(kernel)
    return _check_kernel(kernel)


@lru_cache(maxsize=256)
def _checked_kernel(kernel: tuple) -> tuple[tuple[float, ...], ...]:
    return _check_kernel(kernel)


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
    from nlpsf.sim.optics import photon_weights_fine

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
