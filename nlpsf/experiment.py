"""The experiment: Roman PSF -> oversampled stamps -> nonlinearity -> adaptive moments.

One :class:`SimulationConfig` fixes everything but the star and the detector (band, SCA,
realizations, seed, grid, exposure, optics and measurement settings). :func:`prepare` does the
work that does not depend on magnitude or beta, once: the optics, the rendered stamps for every
centroid realization (at unit flux) and their reference moments. It returns a :class:`Scene`,
the explicit cache the other calls take.

Magnitude and beta only scale and perturb the same rendered stamps: with I = s psi the charge
image (s = flux * N^2, psi the unit-flux stamp), NL gives s (psi - beta s psi^2), and adaptive
moments do not see the overall scale. So each (magnitude, beta) costs one perturbed fit per
realization, started from the reference fit, and the metrics depend on beta and flux only through
their product.

Up the ramp (``SimulationConfig.ramp``, see ``nlpsf.ramps``) the fitted image is s (psi - beta s psi^2
c_2) with c_2 the per-pixel ramp factor, still linear in beta (the fit's weights do not depend on it),
so both methods run unchanged on the pattern psi^2 c_2. The beta x flux rule then holds only while
c_2 is one number for the whole stamp (OLS fit, no resultant saturated); saturated resultants and the
optimal fit's charge-dependent weights break it.

Methods ("fidelity"):
- ``monte_carlo``: every realization fitted to convergence (the paper's procedure);
- ``linear``: the first-order response, metric = beta * s * g . (-psi^2) with g the gradient of the
  moment estimator with respect to pixel values (``moments.pixel_response``). Scatter from
  per-pixel beta is then sigma_beta * s * ||g (.) psi^2||, in closed form.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from functools import cached_property

import numpy as np

from . import __version__, defaults, detector, moments, optics, photometry, ramps, render, roman
from . import scene as scenes
from .checks import InputError, check_choice, check_exptime, check_full_well, check_integer, check_number, check_numbers
from .fidelity import level_name
from .flags import FlagCode, make
from .flags import codes as flag_codes
from .threads import single_blas

METHODS = defaults.METHODS
PAPER_SCENE = scenes.SceneModel()
MAX_REALIZATIONS = defaults.MAX_REALIZATIONS
#: The rendered stamps of a scene are kept in memory; this bounds them (realizations x stamp^2).
MAX_STAMP_BYTES = 1_500_000_000
PAPER_BETA_STEP = defaults.PAPER_BETA_STEP
#: Where a slope is taken (``slopes(linearise_at=...)``): "beta0", the uncorrected detector (the
#: paper's finite difference about beta0); "corrected", the detector after the pipeline's linearity
#: correction, where a calibration error acts on a residual NL of CORRECTED_RESIDUAL x beta0 while the
#: saturation flags stay those of the raw beta0 (romancal flags saturation before it corrects the NL).
LINEARISE_STATES: tuple[str, ...] = ("beta0", "corrected")
#: The residual NL of the "corrected" state, as a fraction of beta0: a 1 % calibration.
CORRECTED_RESIDUAL = 1e-2

#: progress(done, total, message); ``done`` may be fractional within a long step.
Progress = Callable[[float, int, str], None]


@dataclass(frozen=True)
class SimulationConfig:
    """Everything a simulation depends on apart from magnitude and beta. Defaults are the paper's."""

    band: str = defaults.BAND
    sca: int = defaults.SCA
    realizations: int = defaults.REALIZATIONS
    seed: int = defaults.SEED
    oversampling: int = defaults.OVERSAMPLING
    stamp: int = defaults.STAMP
    exptime_s: float = defaults.EXPTIME_S
    full_well_e: float = defaults.FULL_WELL_E
    n_wavelengths: int = 1
    weight_cut_rho2: float = defaults.PAPER_WEIGHT_CUT_RHO2
    pupil_scale: str = defaults.PUPIL_SCALE
    pupil_bin: int = 4
    method: str = "monte_carlo"
    throughput: str = roman.DEFAULT_THROUGHPUT
    #: Up-the-ramp exposure (MA table and slope fit); None: the paper's single final frame.
    ramp: ramps.Ramp | None = None
    #: The scene effects (``nlpsf.scene``); the default is the paper's scene.
    scene: scenes.SceneModel = PAPER_SCENE

    def __post_init__(self) -> None:
        if isinstance(self.scene, dict):
            object.__setattr__(self, "scene", scenes.from_dict(self.scene))
        if not isinstance(self.scene, scenes.SceneModel):
            raise InputError("scene", f"must be a scene description, got {type(self.scene).__name__}")
        object.__setattr__(self, "band", roman.check_band(self.band))
        object.__setattr__(self, "sca", roman.check_sca(self.sca))
        roman.check_throughput(self.throughput)
        check_integer(self.realizations, "realizations", 1, MAX_REALIZATIONS)
        check_integer(self.seed, "seed", 0, 2**63 - 1)
        render.Grid(self.oversampling, self.stamp)
        if self.realizations * self.stamp**2 * 8 > MAX_STAMP_BYTES:
            raise InputError(
                "realizations",
                f"{self.realizations} realizations of {self.stamp}x{self.stamp} stamps need "
                f"{self.realizations * self.stamp**2 * 8 / 1e9:.1f} GB; the limit is {MAX_STAMP_BYTES / 1e9:.1f} GB",
            )
        check_exptime(self.exptime_s)
        check_full_well(self.full_well_e)
        check_choice(self.method, "method", METHODS)
        check_choice(self.pupil_scale, "pupil_scale", roman.PUPIL_SCALE_RULES)
        moments.MomentSettings(weight_cut_rho2=self.weight_cut_rho2)
        optics_config = self.optics  # validates n_wavelengths and pupil_bin
        if not self.scene.is_paper:
            optics_config.wavelengths_and_weights()  # a SED table must cover the band: refuse it here, not mid-run
        if self.ramp is not None:
            if not isinstance(self.ramp, ramps.Ramp):
                raise InputError("ramp", f"must be a ramps.Ramp, got {type(self.ramp).__name__}")
            self.ramp.check_exposure(self.exptime_s)
            ramps.check_scene(self.scene)  # the one rule of what a ramp combines with

    @property
    def optics(self) -> optics.OpticsConfig:
        return optics.OpticsConfig(
            band=self.band,
            sca=self.sca,
            n_wavelengths=self.scene.wavelengths(self.band, self.n_wavelengths, self.sca, self.throughput),
            pupil_bin=self.pupil_bin,
            pupil_scale=self.pupil_scale,
            position_pixels=self.scene.position,
            spectrum=self.scene.spectrum(),
            throughput=self.throughput,
        )

    def electrons(self, magnitude) -> np.ndarray:
        """Electrons of a star of AB ``magnitude`` on this SCA and band over the exposure."""
        return photometry.magnitude_to_electrons(magnitude, self.band, self.exptime_s, sca=self.sca, throughput=self.throughput)

    @property
    def grid(self) -> render.Grid:
        return render.Grid(self.oversampling, self.stamp)

    @property
    def moment_settings(self) -> moments.MomentSettings:
        return moments.MomentSettings(weight_cut_rho2=self.weight_cut_rho2)

    @property
    def fidelity(self) -> str:
        polychromatic = self.n_wavelengths > 1 or self.scene.sed is not None
        return level_name(self.method, 2 if polychromatic else 1) + ("" if self.scene.is_paper else "+scene")

    def conditions(self) -> dict:
        """What every number computed under this configuration holds for."""
        out = asdict(self)
        out.pop("ramp")
        if self.ramp is not None:
            out["ramp"] = self.ramp.conditions(self.exptime_s)
        if not math.isfinite(self.weight_cut_rho2):
            out["weight_cut_rho2"] = None  # no cut (JSON has no infinity)
        out["scene"] = self.scene.to_dict()
        # The field holds the request (1 unless --n-wavelengths); a SED makes the optics integrate
        # the band anyway, so the conditions say how many wavelengths were actually evaluated.
        out["n_wavelengths_requested"] = self.n_wavelengths
        out["n_wavelengths"] = self.optics.n_wavelengths
        out.update(
            scene_description=self.scene.describe(),
            wavelengths_used=self.optics.n_wavelengths,
            fidelity=self.fidelity,
            pixel_scale_arcsec=roman.PIXEL_SCALE_ARCSEC,
            throughput_version=roman.THROUGHPUT_VERSIONS[self.throughput],
            data_version=roman.DATA_VERSION,
            code_version=__version__,
        )
        return out


@dataclass(frozen=True, eq=False)
class Scene:
    """The magnitude- and beta-independent part of a simulation (see :func:`prepare`)."""

    config: SimulationConfig
    psf: optics.EffectivePSF
    offsets: np.ndarray  # (R, 2) centroid offsets in fine pixels
    stamps: np.ndarray  # (R, n, n) unit-flux stamps
    reference: moments.Moments
    elapsed_s: float
    #: Unit-flux charge stamps before IPC (None: the same as ``stamps``, no IPC in the scene).
    unit_charge: np.ndarray | None = None

    @property
    def charge(self) -> np.ndarray:
        return self.stamps if self.unit_charge is None else self.unit_charge

    @cached_property
    def core_margin(self) -> int:
        """Pixels each side of the stamps can lose for a perturbed fit (``moments.core_margin``)."""
        return moments.core_margin(self.stamps.shape[-1], self.reference, self.config.weight_cut_rho2)

    @cached_property
    def peak_fraction(self) -> np.ndarray:
        """Largest fine-pixel value of each unit-flux stamp (of the centroids drawn)."""
        return self.stamps.max(axis=(1, 2))

    @cached_property
    def star_peak(self) -> tuple[float, tuple[float, float]]:
        """The star's brightest fine pixel (unit flux) over *every* sub-pixel centroid, and where
        the PSF peaks (x, y) [arcsec]: the maximum of the effective PSF (``optics.peak_value``),
        which does not depend on the centroids drawn. ``peak_fraction`` never exceeds it."""
        value, position = optics.peak_value(self.psf)
        return value * self.config.grid.scale_arcsec**2, position

    @property
    def star_peak_fraction(self) -> float:
        return self.star_peak[0]

    @cached_property
    def weighted_region(self) -> np.ndarray:
        """Pixels inside each reference fit's weight cut (where the moments look), (R, n, n)."""
        return _weighted_region(self.stamps.shape[-1], self.reference.parameters(), self.config.weight_cut_rho2)

    @cached_property
    def weighted_peak_fraction(self) -> np.ndarray:
        """Largest unit-flux value among the pixels that carry weight, per realization."""
        return np.where(self.weighted_region, self.stamps, 0.0).max(axis=(1, 2))


@single_blas
def prepare(config: SimulationConfig, progress: Progress | None = None) -> Scene:
    """Optics, stamps for every centroid realization, and their reference moments."""
    start = time.perf_counter()
    grid = config.grid
    if progress:
        progress(0, 3, "optics")
    psf = optics.effective_psf(config.optics, round(grid.field_arcsec(), 9))
    # Jitter and charge diffusion: Gaussian blurs, a multiplication of the Fourier coefficients.
    psf = scenes.blur(psf, config.scene.blur_sigma_arcsec())
    rng = np.random.default_rng(config.seed)
    offsets = render.draw_offsets(rng, config.realizations, config.oversampling)
    chunk = 256
    blocks = range(0, config.realizations, chunk)
    stamps = np.empty((config.realizations, grid.stamp, grid.stamp))
    for k, first in enumerate(blocks):
        if progress:
            progress(1 + k / len(blocks), 3, "rendering")
        stamps[first : first + chunk] = render.draw(psf, grid, offsets[first : first + chunk])
    unit_charge = None
    if config.scene.ipc is not None:
        # The linear image the moments are referred to is the IPC-coupled one.
        unit_charge, stamps = stamps, scenes.apply_ipc(stamps, config.scene.ipc, config.oversampling)
    parts = []
    for k, first in enumerate(blocks):
        if progress:
            progress(2 + k / len(blocks), 3, "reference moments")
        parts.append(moments.fit(stamps[first : first + chunk], config.moment_settings))
    reference = moments.concatenate(parts)
    return Scene(config, psf, offsets, stamps, reference, time.perf_counter() - start, unit_charge)


@dataclass(frozen=True)
class Statistic:
    """Mean, standard deviation and standard error of the mean over realizations (None if no data)."""

    mean: float | None
    std: float | None
    stderr: float | None
    count: int

    @classmethod
    def of(cls, values: np.ndarray) -> Statistic:
        values = np.asarray(values, dtype=np.float64)
        values = values[np.isfinite(values)]
        if values.size == 0:
            return cls(None, None, None, 0)
        std = float(values.std(ddof=1)) if values.size > 1 else 0.0
        return cls(float(values.mean()), std, std / math.sqrt(values.size), int(values.size))

    def to_dict(self) -> dict:
        return {"mean": self.mean, "std": self.std, "stderr": self.stderr}


@dataclass(frozen=True)
class SimulationResult:
    """NL-induced change of PSF size and ellipticity for one (magnitude, beta, sigma_beta)."""

    conditions: dict
    magnitude: float
    beta: float
    beta_convention: str
    beta_paper: float
    sigma_beta: float
    realizations: int
    flux_electrons: float
    #: The star's brightest pixel before the NL [e-], over every sub-pixel centroid (``star_peak_electrons``).
    peak_electrons: float
    reference: dict
    dR_over_R: Statistic
    de1: Statistic
    de2: Statistic
    failed_realizations: int
    flags: list[str]
    elapsed_s: float
    centroid_offset: list[float] | None = None
    extras: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        c = self.conditions
        return {
            "band": c["band"],
            "sca": c["sca"],
            "magnitude": self.magnitude,
            "beta": self.beta,
            "beta_convention": self.beta_convention,
            "beta_paper": self.beta_paper,
            "nl_model": detector.describe(self.beta_convention),
            "sigma_beta": self.sigma_beta,
            "realizations": self.realizations,
            "exptime_s": c["exptime_s"],
            "flux_electrons": self.flux_electrons,
            "peak_electrons": self.peak_electrons,
            "full_well_electrons": c["full_well_e"],
            "reference": self.reference,
            "dR_over_R": self.dR_over_R.to_dict(),
            "de1": self.de1.to_dict(),
            "de2": self.de2.to_dict(),
            "failed_realizations": self.failed_realizations,
            "flags": [str(f) for f in self.flags],
            "flag_codes": flag_codes(self.flags),
            "elapsed_s": self.elapsed_s,
            "fidelity": c["fidelity"],
            "centroid_offset_fine_pixels": self.centroid_offset,
            "conditions": c,
            **self.extras,
        }


def check_magnitudes(values) -> list[float]:
    return check_numbers(values, "magnitude", *defaults.MAGNITUDE_RANGE)


def check_sigma_beta(sigma_beta) -> float:
    return check_number(sigma_beta, "sigma_beta", 0.0, detector.MAX_ABS_BETA)


def _reference_summary(scene: Scene, index: slice | int | None = None) -> dict:
    ref = scene.reference
    pick = slice(None) if index is None else index
    ok = ref.ok[pick]
    e1, e2, sigma = (np.atleast_1d(getattr(ref, k)[pick])[np.atleast_1d(ok)] for k in ("e1", "e2", "sigma"))
    grid = scene.config.grid
    if e1.size == 0:
        return {"e1": None, "e2": None, "sigma": None, "sigma_arcsec": None}
    return {
        "e1": float(e1.mean()),
        "e2": float(e2.mean()),
        "sigma": float(sigma.mean()),
        "sigma_arcsec": float(sigma.mean() * grid.scale_arcsec),
    }


def _validity_flags(
    scene: Scene, charge_scale: float, beta_map: np.ndarray, peak_electrons: np.ndarray, index=None, ramp_effect=None
) -> list[str]:
    """Plain-language warnings: saturation and a non-monotonic quadratic where the weight is.

    With a ramp, saturation is judged per resultant (``ramp_effect`` carries those flags) and the
    quadratic only has to be monotonic up to the charge of the last read each pixel's fit uses."""
    flags: list[str] = []
    config = scene.config
    over = peak_electrons > config.full_well_e
    star_peak = star_peak_electrons(scene, charge_scale)
    if ramp_effect is not None:
        flags += ramp_effect.flags
    elif star_peak > config.full_well_e:
        # Judged on the star (its brightest pixel over every sub-pixel centroid), so that the flag
        # does not depend on which centroids were drawn.
        flags.append(
            make(
                FlagCode.SATURATED,
                peak_e=star_peak,
                full_well_e=config.full_well_e,
                over=int(over.sum()),
                realizations=int(over.size),
            )
        )
    model = config.scene
    if ramp_effect is not None:
        worst = float(np.min(1.0 - 2.0 * np.max(beta_map) * ramp_effect.used_peak_e))
    elif not model.plain_detector:
        # dS/dQ of the polynomial at the charge the NL acts on (background, BFE, IPC-before included).
        pick = slice(None) if index is None else slice(index, index + 1)
        charge = scenes.charge_before_nl(scene.charge[pick], charge_scale, model, config.oversampling)
        b2 = beta_map if beta_map.size > 1 else float(beta_map.ravel()[0])
        slope = detector.response_slope(charge, b2, model.nl_coefficients)
        weighted = np.broadcast_to(scene.weighted_region[pick], np.broadcast_shapes(slope.shape, charge.shape))
        worst = float(np.where(weighted, slope, np.inf).min())
    elif beta_map.size == 1:
        peak = scene.weighted_peak_fraction if index is None else scene.weighted_peak_fraction[index]
        worst = float(np.min(1.0 - 2.0 * float(beta_map.ravel()[0]) * charge_scale * peak))
    else:
        weighted = scene.weighted_region[index]
        slope = 1.0 - 2.0 * beta_map * charge_scale * scene.stamps[index]
        worst = float(np.where(weighted, slope, np.inf).min())
    if worst <= 0:
        plain = model.plain_detector
        flags.append(
            make(
                FlagCode.NL_NOT_MONOTONIC,
                slope_name="1 - 2 beta Q" if plain else "dS/dQ",
                worst=worst,
                model="the quadratic model S = Q - beta Q^2" if plain else "the NL model",
            )
        )
    elif beta_map.size == 1 and beta_map.ravel()[0] < 0:
        flags.append(make(FlagCode.NEGATIVE_BETA))
    elif np.any(beta_map < 0):
        flags.append(make(FlagCode.NEGATIVE_PIXEL_BETAS, percent=float(100 * np.mean(beta_map < 0))))
    return flags


def _weighted_region(n: int, params: np.ndarray, cut: float) -> np.ndarray:
    coords = np.arange(n) - (n - 1) / 2.0
    x0, y0, mxx, mxy, myy = params.T
    det = mxx * myy - mxy**2
    dx = coords[None, None, :] - x0[:, None, None]
    dy = coords[None, :, None] - y0[:, None, None]
    rho2 = (myy[:, None, None] * dx**2 - 2 * mxy[:, None, None] * dx * dy + mxx[:, None, None] * dy**2) / det[:, None, None]
    limit = cut if math.isfinite(cut) else 50.0
    return rho2 <= limit


def _scene_flags(scene: Scene) -> list[str]:
    """Flags about the configuration itself: a grid too coarse for the PSF, a stamp too small for the weight."""
    config = scene.config
    flags = []
    # Nyquist: the effective PSF is band-limited at D / lambda; a fine pixel coarser than
    # lambda / (2 D) aliases it. Measured (linear slopes at m = 20, against N = 6): at q = 0.69-0.84
    # (Z087, Y106 at N = 2) the size slope is off by 0.5-0.7 % and e1 by 9-13 %; R062 at N = 2 (q = 0.49)
    # by 3.5 % and 10 %; at N = 1 the moments fail. At q >= 1 the error is below 0.02 %, but R062 at
    # N = 3 (q = 0.74) is 0.14 % and 1.6 % off.
    wavelength_nm = float(np.min(scene.psf.wavelengths_nm))
    nyquist_arcsec = wavelength_nm * 1e-9 / (2 * roman.DIAMETER_M) * 206264.80624709636
    q = nyquist_arcsec / config.grid.scale_arcsec
    if q < 1.0:
        needed = math.ceil(config.oversampling / q)
        flags.append(
            make(
                FlagCode.UNDERSAMPLED,
                pixel_mas=config.grid.scale_arcsec * 1e3,
                nyquist_mas=nyquist_arcsec * 1e3,
                wavelength_nm=wavelength_nm,
                q=q,
                needed=needed,
            )
        )
    # The weight window must fit in the stamp: a cut weight is a different estimator.
    n = config.stamp
    ok = scene.reference.ok
    if np.any(ok):
        params = scene.reference.parameters()[ok]
        cut = config.weight_cut_rho2 if math.isfinite(config.weight_cut_rho2) else defaults.GALSIM_WEIGHT_CUT_RHO2
        coords = np.arange(n) - (n - 1) / 2.0
        border = np.concatenate(
            [
                np.stack([coords, np.full(n, coords[0])], 1),
                np.stack([coords, np.full(n, coords[-1])], 1),
                np.stack([np.full(n, coords[0]), coords], 1),
                np.stack([np.full(n, coords[-1]), coords], 1),
            ]
        )
        x0, y0, mxx, mxy, myy = params.T
        det = mxx * myy - mxy**2
        dx = border[None, :, 0] - x0[:, None]
        dy = border[None, :, 1] - y0[:, None]
        rho2 = (myy[:, None] * dx**2 - 2 * mxy[:, None] * dx * dy + mxx[:, None] * dy**2) / det[:, None]
        inside = int(np.sum(rho2.min(axis=1) < cut))
        if inside:
            flags.append(make(FlagCode.STAMP_TOO_SMALL, cut=cut, n=n, inside=inside, fitted=int(ok.sum())))
    return flags


def _failure_flag(status: np.ndarray) -> list[str]:
    bad = status != moments.MomentStatus.OK
    if not np.any(bad):
        return []
    reasons = sorted({moments.STATUS_REASONS[moments.MomentStatus(s)] for s in status[bad]})
    rest = "no statistics are left" if np.all(bad) else "the statistics use the others"
    return [make(FlagCode.MOMENTS_FAILED, failed=int(bad.sum()), total=int(bad.size), reasons="; ".join(reasons), rest=rest)]


def _metrics(fit: moments.Moments, reference: moments.Moments, ref_index=None):
    """Delta R / R, Delta e1, Delta e2 per realization (NaN where a fit failed) and the status."""
    if ref_index is not None:
        reference = moments.select(reference, np.full(len(fit), ref_index))
    ok = fit.ok & reference.ok
    d_r, d_e1, d_e2 = (np.where(ok, v, np.nan) for v in moments.differences(fit, reference))
    status = np.where(reference.ok, fit.status, reference.status)
    return d_r, d_e1, d_e2, status


@dataclass(frozen=True)
class RampEffect:
    """What the ramp fit does to the quadratic NL at one magnitude.

    ``factor`` is the per-pixel c_2 (``ramps.order_factors``): the fitted image is
    s (psi - beta s psi^2 c_2), so the final-frame machinery runs unchanged with -psi^2 replaced
    by -psi^2 c_2 (and d image / d beta = -s^2 psi^2 c_2 exactly: the weights do not depend on beta).
    """

    factor: np.ndarray
    usable: np.ndarray
    used_peak_e: float
    flags: list[str]
    extras: dict
    #: A scene with detector effects (IPC, background, polynomial NL): every order's factor and the
    #: charge the NL acts on (``ramps.scene_factors``); None for the paper's detector.
    scene_ramp: ramps.SceneRamp | None = None


def ramp_effect(scene: Scene, charge_scale: float, index: int | None = None, beta: float = 0.0) -> RampEffect:
    """Per-pixel ramp factors, resultants used, and the flags, for all realizations (or one).

    ``beta``: the quadratic NL the ramp's "signal" saturation rule sees (``ramps.usable_resultants``;
    the ramp's own ``saturation_beta`` wins when set); the factors do not depend on it."""
    config = scene.config
    ramp = config.ramp
    assert ramp is not None
    state = (beta, *config.scene.nl_coefficients)
    stamps = scene.stamps if index is None else scene.stamps[index : index + 1]
    weighted = scene.weighted_region if index is None else scene.weighted_region[index : index + 1]
    K = ramp.table.n_resultants
    last = ramp.table.last_read_fractions(config.exptime_s)
    if not config.scene.plain_detector:
        return _scene_ramp_effect(scene, charge_scale, index, state)
    peak = charge_scale * float(stamps.max())
    if ramp.fit == "ols" and peak * last[-1] <= config.full_well_e and (ramp.saturation == "charge" or beta >= 0):
        # Every pixel keeps every resultant and OLS weights do not depend on the charge: one factor
        # (the same number order_factors gives each pixel), no per-pixel work.
        factor, _ = ramps.order_factors(np.zeros(1), ramp, config.exptime_s, config.full_well_e, (2,))
        pixels = int(weighted.sum())
        summary = {"pixels": pixels, "resultants": K, "fitted_on_all": pixels, "fitted_on_fewer": 0, "unusable": 0}
        summary.update(pixels_by_resultants={str(K): pixels}, fewest_resultants=K, stamp_unusable=0, description=ramp.describe())
        weighted_peak = scene.weighted_peak_fraction if index is None else scene.weighted_peak_fraction[index : index + 1]
        used_peak = charge_scale * float(weighted_peak.max()) * last[-1]
        return RampEffect(factor.reshape(1, 1, 1), np.full(1, K), used_peak, [], {"ramp": summary})
    charge = charge_scale * stamps
    factors, usable = ramps.order_factors(charge, ramp, config.exptime_s, config.full_well_e, (2,), state=state)
    return _ramp_summary(scene, charge, factors[0], usable, weighted, None)


def _scene_ramp_effect(scene: Scene, charge_scale: float, index: int | None, state: tuple[float, ...]) -> RampEffect:
    """The ramp inside a scene with detector effects: ``ramps.scene_factors`` on Q = s psi + B."""
    config = scene.config
    model = config.scene
    pick = slice(None) if index is None else slice(index, index + 1)
    weighted = scene.weighted_region[pick]
    charge = charge_scale * scene.charge[pick] + model.background_e
    orders = tuple(range(2, 3 + len(model.nl_coefficients)))
    sr = ramps.scene_factors(
        charge, config.ramp, config.exptime_s, config.full_well_e, state, orders, model.ipc, model.ipc_order, config.oversampling
    )
    return _ramp_summary(scene, sr.charge, sr.factors[0], sr.usable, weighted, sr)


def _ramp_summary(scene: Scene, charge, factor, usable, weighted, scene_ramp) -> RampEffect:
    config = scene.config
    ramp = config.ramp
    K = ramp.table.n_resultants
    last = ramp.table.last_read_fractions(config.exptime_s)
    stamps = charge
    used_charge = charge * last[np.maximum(usable, 1) - 1]
    used_peak = float(np.where(weighted, used_charge, 0.0).max())
    summary = ramps.usage_summary(usable, K, weighted)
    summary["stamp_unusable"] = int(np.sum(usable == 0))
    summary["description"] = ramp.describe()
    flags = []
    needed = min(ramp.min_usable, K)
    first_end = ramp.table.resultants[needed - 1][-1] * ramp.table.frame_time_s
    if summary["unusable"]:
        hit = int(np.sum(np.any(weighted & (usable == 0), axis=(1, 2))))
        where = "in the first resultant" if needed == 1 else "by the second resultant (one gives no slope, as in romancal)"
        flags.append(
            make(
                FlagCode.RAMP_UNUSABLE_PIXELS,
                where=where,
                unusable=summary["unusable"],
                hit=hit,
                realizations=len(stamps),
                full_well_e=config.full_well_e,
                time_s=first_end,
            )
        )
    if summary["fitted_on_fewer"]:
        final_peak = float(charge.max())
        flags.append(
            make(
                FlagCode.RAMP_FEWER_RESULTANTS,
                fewer=summary["fitted_on_fewer"],
                pixels=summary["pixels"],
                resultants=K,
                fewest=summary["fewest_resultants"],
                peak_e=final_peak,
                full_well_e=config.full_well_e,
            )
        )
    return RampEffect(factor, usable, used_peak, flags, {"ramp": summary}, scene_ramp)


def _nl_shape(stamps: np.ndarray, factor: np.ndarray | None) -> np.ndarray:
    """psi^2 for the final frame, psi^2 c_2 after a ramp fit (``factor``, the ramp effect's c_2 on
    the same pixels): the pattern that -beta s multiplies."""
    return stamps**2 if factor is None else stamps**2 * factor


@single_blas
def simulate(
    config: SimulationConfig,
    magnitudes: Sequence[float] | float,
    betas: Sequence[float] | float,
    sigma_beta: float = 0.0,
    beta_convention: str = "paper",
    scene: Scene | None = None,
    progress: Progress | None = None,
    saturation_beta: float | None = None,
) -> list[SimulationResult]:
    """Change of ΔR/R, Δe1, Δe2 for every (magnitude, beta) pair, magnitude outermost.

    ``saturation_beta``: the raw detector's beta (paper convention) a ramp's "signal" saturation rule
    sees, when it is not the beta simulated (a residual NL after the linearity correction).

    With ``sigma_beta`` > 0 each fine pixel gets its own beta ~ N(beta, sigma_beta^2) and, as in
    the paper, the centroid is fixed (the first realization's) while the ``realizations`` are
    independent draws of the beta map; the metrics' ``std`` is then the scatter over those draws.
    """
    mags = check_magnitudes(magnitudes)
    given_betas = check_numbers(betas, "beta")
    paper_betas = [detector.to_paper_beta(b, beta_convention) for b in given_betas]
    sigma_beta = check_sigma_beta(sigma_beta)
    scene = scene or prepare(config)
    if scene.config != config:
        raise InputError("scene", "the scene was prepared for a different configuration")
    conditions = config.conditions()
    settings = config.moment_settings
    scene_flags = _scene_flags(scene)
    results: list[SimulationResult] = []
    total = len(mags) * len(paper_betas)
    share = scene.elapsed_s / total
    for m_index, magnitude in enumerate(mags):
        flux = float(config.electrons(magnitude))
        charge_scale = flux * config.oversampling**2
        for b_index, (beta_given, beta) in enumerate(zip(given_betas, paper_betas, strict=True)):
            start = time.perf_counter()
            if progress:
                progress(m_index * len(paper_betas) + b_index, total, f"m={magnitude:g} beta={beta_given:g}")
            if sigma_beta > 0:
                result = _simulate_scatter(
                    scene, charge_scale, beta, sigma_beta, settings, m_index * 7919 + b_index, saturation_beta
                )
            else:
                result = _simulate_bias(scene, charge_scale, beta, settings, saturation_beta)
            d_r, d_e1, d_e2, status, flags, peak, reference, offset, extras = result
            results.append(
                SimulationResult(
                    conditions=conditions,
                    magnitude=magnitude,
                    beta=beta_given,
                    beta_convention=beta_convention,
                    beta_paper=beta,
                    sigma_beta=sigma_beta,
                    realizations=config.realizations,
                    flux_electrons=flux,
                    peak_electrons=peak,
                    reference=reference,
                    dR_over_R=Statistic.of(d_r),
                    de1=Statistic.of(d_e1),
                    de2=Statistic.of(d_e2),
                    failed_realizations=int(np.sum(status != moments.MomentStatus.OK)),
                    flags=scene_flags + flags + _failure_flag(status) + _zero_flag(d_r),
                    elapsed_s=time.perf_counter() - start + share,
                    centroid_offset=offset,
                    extras=extras,
                )
            )
    if progress:
        progress(total, total, "done")
    return results


def _zero_flag(d_r: np.ndarray) -> list[str]:
    finite = d_r[np.isfinite(d_r)]
    if finite.size and np.all(finite == 0.0):
        return [make(FlagCode.NO_CHANGE)]
    return []


def nl_images(
    scene: Scene, charge_scale: float, beta, count: int | None = None, effect: RampEffect | None = None, margin: int = 0
):
    """The detector at one flux: (linear image, its reference fit, NL perturbation, d perturbation / d beta).

    All per unit flux, for the first ``count`` realizations (all by default). ``beta`` is b2, a
    scalar or per-pixel values. This is the one place the NL meets the stamps: the paper's scene
    keeps its plain expression (beta times the derivative -s psi^2); any other
    scene goes through ``scene.detector_chain`` (brighter-fatter, IPC before/after, polynomial NL,
    background). With brighter-fatter the NL-free image depends on the flux, and its reference fit
    is made here, from the stored one. Up the ramp (``effect``) the NL pattern is psi^2 c_2
    (``_nl_shape``); a ramp with the scene's detector effects is refused by the configuration.
    ``margin`` trims that many pixels from every side of the images (centre kept; see
    :func:`_perturbed_fit`); the paper's detector then computes only the core.
    """
    config = scene.config
    model = config.scene
    pick = slice(None) if count is None else slice(0, count)
    n = scene.stamps.shape[-1]
    core = (Ellipsis, slice(margin, n - margin), slice(margin, n - margin))
    reference = scene.reference if count is None else moments.select(scene.reference, pick)
    if model.plain_detector:
        stamps = scene.stamps[pick][core]
        # c_2 is per pixel (trimmed like the stamps), or one value broadcast over the stamp (a uniform ramp).
        factor = None if effect is None else effect.factor
        if factor is not None and factor.shape[-1] == n:
            factor = factor[core]
        shape = _nl_shape(stamps, factor)
        derivative = -charge_scale * shape
        return stamps, reference, beta * derivative, derivative
    stamps = scene.stamps[pick]
    if effect is not None and effect.scene_ramp is not None:
        # Up the ramp in a scene: each order's NL term times the measuring pixel's factor (ramps.scene_factors).
        sr = effect.scene_ramp
        if count is not None and sr.charge.shape[0] > count:
            sr = ramps.SceneRamp(sr.factors[:, :count], sr.usable[:count], sr.charge[:count], sr.orders)
        perturbation, derivative = ramps.scene_perturbation(
            sr, beta, model.nl_coefficients, model.ipc, model.ipc_order, config.oversampling
        )
        return stamps[core], reference, perturbation[core] / charge_scale, derivative[core] / charge_scale
    shift, perturbation, derivative = scenes.detector_chain(scene.charge[pick], charge_scale, beta, model, config.oversampling)
    if shift is not None:
        reference = moments.fit_perturbed(stamps, shift, reference, config.moment_settings)
        stamps = stamps + shift
    return stamps[core], reference, perturbation[core], derivative[core]


def _perturbed_fit(
    scene: Scene, charge_scale: float, beta: float, settings: moments.MomentSettings, effect: RampEffect | None = None
) -> tuple[moments.Moments, moments.Moments, np.ndarray, np.ndarray, np.ndarray]:
    """Adaptive moments of the NL images: (fit, reference fit, stamps, NL perturbation, d perturbation / d beta).

    The fits are made on the stamps' central core (``Scene.core_margin``), and the images returned
    are that core: the weight is zero beyond the cut, and a 96 x 96 stamp is mostly outside it,
    so building and adding the whole images cost more than the fits themselves. If any fit failed
    or left the core, the whole stamps are fitted instead; otherwise the answer is the one the
    whole stamps give.
    """
    margin = scene.core_margin
    stamps, reference, perturbation, derivative = nl_images(scene, charge_scale, beta, effect=effect, margin=margin)
    fit = moments.fit_perturbed(stamps, perturbation, reference, settings)
    if margin and not np.all(moments.within(fit, stamps.shape[-1], float(settings.weight_cut_rho2))):
        stamps, reference, perturbation, derivative = nl_images(scene, charge_scale, beta, effect=effect)
        fit = moments.fit_perturbed(stamps, perturbation, reference, settings)
    return fit, reference, stamps, perturbation, derivative


def _simulate_bias(
    scene: Scene, charge_scale: float, beta: float, settings: moments.MomentSettings, saturation_beta: float | None = None
):
    config = scene.config
    peak = _peak_electrons(scene, charge_scale)
    state = beta if saturation_beta is None else saturation_beta
    effect = ramp_effect(scene, charge_scale, beta=state) if config.ramp is not None else None
    flags = _validity_flags(scene, charge_scale, np.full(1, beta), peak, ramp_effect=effect)
    extras: dict = {} if effect is None else dict(effect.extras)
    if config.method == "monte_carlo":
        fit, reference, *_ = _perturbed_fit(scene, charge_scale, beta, settings, effect)
        d_r, d_e1, d_e2, status = _metrics(fit, reference)
    else:
        # First order at beta = 0: the gradient of the reference fit along the NL perturbation,
        # on the stamps' core when the reference fits' weight windows lie inside it.
        margin = scene.core_margin
        stamps, reference, perturbation, derivative = nl_images(scene, charge_scale, beta, effect=effect, margin=margin)
        if margin and not np.all(moments.within(reference, stamps.shape[-1], float(settings.weight_cut_rho2))):
            stamps, reference, perturbation, derivative = nl_images(scene, charge_scale, beta, effect=effect)
        if config.scene.plain_detector:
            linear = moments.response_to(stamps, reference, derivative, settings)[0] * beta
        else:
            linear = moments.response_to(stamps, reference, perturbation, settings)[0]
        ok = reference.ok
        d_r, d_e1, d_e2 = (np.where(ok, linear[:, k], np.nan) for k in range(3))
        status = reference.status
    return d_r, d_e1, d_e2, status, flags, star_peak_electrons(scene, charge_scale), _reference_summary(scene), None, extras


def star_peak_electrons(scene: Scene, charge_scale: float) -> float:
    """The star's brightest pixel before the NL [e-], over every sub-pixel centroid (background included).

    Plain detector: charge_scale times ``Scene.star_peak_fraction``, exact. With detector effects
    the charge before the NL is computed on one stamp whose fine-pixel centre sits on the PSF's
    peak: exact for a background and for IPC after the NL (neither moves the peak); with IPC
    before the NL or brighter-fatter it is the charge at the optical peak's centring.
    """
    model = scene.config.scene
    if model.plain_detector:
        return charge_scale * scene.star_peak_fraction
    grid = scene.config.grid
    centres = grid.pixel_centres_arcsec()
    x, y = scene.star_peak[1]
    # A fine-pixel centre c sees the PSF at c - offset: put the nearest centre on the peak.
    offset = np.array([[(centres[np.argmin(np.abs(centres - v))] - v) / grid.scale_arcsec for v in (x, y)]])
    stamp = render.draw(scene.psf, grid, offset)
    return float(scenes.charge_before_nl(stamp, charge_scale, model, scene.config.oversampling).max())


def _peak_electrons(scene: Scene, charge_scale: float, count: int | None = None) -> np.ndarray:
    """Largest charge in any pixel before the NL, per realization (background included)."""
    model = scene.config.scene
    if model.plain_detector:
        peak = charge_scale * scene.peak_fraction
        return peak if count is None else peak[:count]
    pick = slice(None) if count is None else slice(0, count)
    charge = scenes.charge_before_nl(scene.charge[pick], charge_scale, model, scene.config.oversampling)
    return charge.max(axis=(1, 2))


_SCATTER_CHUNK = 256


def _simulate_scatter(
    scene: Scene,
    charge_scale: float,
    beta: float,
    sigma_beta: float,
    settings: moments.MomentSettings,
    stream: int,
    saturation_beta: float | None = None,
):
    config = scene.config
    draws = config.realizations
    stamp = scene.stamps[0]
    rng = np.random.default_rng([config.seed, 1, stream])
    betas = detector.draw_pixel_betas(rng, beta, sigma_beta, (draws, *stamp.shape))
    peak = np.full(draws, float(_peak_electrons(scene, charge_scale, 1)[0]))
    state = beta if saturation_beta is None else saturation_beta
    effect = ramp_effect(scene, charge_scale, index=0, beta=state) if config.ramp is not None else None
    flags = _validity_flags(scene, charge_scale, betas, peak[:1], index=0, ramp_effect=effect)
    offset = [float(v) for v in scene.offsets[0]]
    extras: dict = {} if effect is None else dict(effect.extras)
    shape = _nl_shape(stamp, None if effect is None else effect.factor[0])
    model = config.scene
    stamp_ref, reference0, _, _ = nl_images(scene, charge_scale, beta, count=1)
    stamp = stamp_ref[0]
    ref_params = reference0.parameters()[0]
    single_reference = moments.Moments(
        *(np.full(draws, v) for v in ref_params),
        amplitude=np.full(draws, reference0.amplitude[0]),
        iterations=np.zeros(draws, dtype=np.int32),
        last_step=np.zeros(draws),
        status=np.full(draws, reference0.status[0], dtype=np.int8),
    )
    if config.method == "monte_carlo":
        parts = []
        for s in range(0, draws, _SCATTER_CHUNK):
            block = betas[s : s + _SCATTER_CHUNK]
            base = np.broadcast_to(stamp, block.shape)
            if model.plain_detector:
                perturbation = -(block * charge_scale) * shape
            else:
                perturbation = nl_images(scene, charge_scale, block, count=1)[2]
            parts.append(
                moments.fit_perturbed(
                    base,
                    perturbation,
                    moments.select(single_reference, slice(s, s + block.shape[0])),
                    settings,
                )
            )
        fit = moments.concatenate(parts)
        d_r, d_e1, d_e2, status = _metrics(fit, reference0, ref_index=0)
    else:
        if model.plain_detector:
            # First order about the uniform-beta image, as the linear slopes are (``slopes(method="linear")``):
            # metric(beta_k) = metric(beta) + g(I_beta) . (-(beta_k - beta) s psi^2), exact at the mean beta
            # (psi^2 c_2 after a ramp fit).
            reference0 = moments.select(scene.reference, slice(0, 1))
            uniform = -(beta * charge_scale) * shape[None]
            fit_beta = moments.fit_perturbed(stamp[None], uniform, reference0, settings)
            base = np.array(moments.differences(fit_beta, reference0))[:, 0]
            gradient = moments.pixel_response(stamp[None] + uniform, fit_beta, settings)[0]
            # The gradient of R is relative to R(beta); Delta R / R is relative to the unperturbed R0.
            gradient[0] *= float(fit_beta.sigma[0] / reference0.sigma[0])
            response = gradient * (-shape * charge_scale)  # d metric / d beta_k, shape (3, n, n)
        else:
            # The same about the scene's uniform-beta image; the per-pixel response goes back through IPC.
            stamps1, reference0, uniform, _ = nl_images(scene, charge_scale, beta, count=1)
            fit_beta = moments.fit_perturbed(stamps1, uniform, reference0, settings)
            base = np.array(moments.differences(fit_beta, reference0))[:, 0]
            gradient = moments.pixel_response(stamps1 + uniform, fit_beta, settings)[0]
            gradient[0] *= float(fit_beta.sigma[0] / reference0.sigma[0])
            response = _per_pixel_beta_response(scene, gradient, charge_scale, effect)
        linear = base[None, :] + np.einsum("kij,bij->bk", response, betas - beta)
        ok = bool(reference0.ok[0] and fit_beta.ok[0])
        d_r, d_e1, d_e2 = (np.full(draws, np.nan) if not ok else linear[:, k] for k in range(3))
        status = np.full(draws, reference0.status[0] if not fit_beta.ok[0] else fit_beta.status[0])
        closed = np.sqrt(np.sum(response**2, axis=(1, 2))) * sigma_beta
        extras["linear_scatter_closed_form"] = {"dR_over_R": float(closed[0]), "de1": float(closed[1]), "de2": float(closed[2])}
    if config.method == "monte_carlo":
        spread = np.array([np.nanstd(v) for v in (d_r, d_e1, d_e2)])
        flags += _noise_floor_flag(scene, charge_scale, beta, sigma_beta, settings, spread, shape)
    return d_r, d_e1, d_e2, status, flags, star_peak_electrons(scene, charge_scale), _reference_summary(scene, 0), offset, extras


def _per_pixel_beta_response(
    scene: Scene, gradient: np.ndarray, charge_scale: float, effect: RampEffect | None = None
) -> np.ndarray:
    """d metric / d beta_k for the per-pixel beta of pixel k, (3, n, n), at the first centroid.

    The NL of pixel k changes it by -Q_k^2 (Q the charge it acts on); IPC after the NL then spreads
    that change to the neighbours, so the gradient is carried back through IPC's transpose. Up the
    ramp the measuring pixel's factor c_2 multiplies the gradient first (``ramps.scene_factors``).
    """
    model = scene.config.scene
    charge = scenes.charge_before_nl(scene.charge[:1], charge_scale, model, scene.config.oversampling)[0]
    pulled = gradient
    if effect is not None and effect.scene_ramp is not None:
        pulled = gradient * effect.scene_ramp.factors[0][0]
    if model.ipc is not None and model.ipc_order == "after":
        pulled = scenes.apply_ipc_adjoint(pulled, model.ipc, scene.config.oversampling)
    return pulled * (-(charge**2) / charge_scale)


#: Smallest spread of a metric (Delta R / R, Delta e) that the Monte Carlo resolves: the differences of
#: two converged float64 fits carry ~1e-16 of noise, so a spread expected below 1e-13 is at least
#: 0.1 % noise (measured: at sigma_beta = 1e-20 the Monte Carlo gives 13368 per unit sigma_beta where
#: the linear response gives 2692).
MONTE_CARLO_SPREAD_FLOOR = 1e-13


def _noise_floor_flag(
    scene: Scene,
    charge_scale: float,
    beta: float,
    sigma_beta: float,
    settings: moments.MomentSettings,
    measured: np.ndarray,
    shape: np.ndarray | None = None,
) -> list[str]:
    """Flag a Monte Carlo scatter whose expected spread is below what float64 fits resolve.
    ``shape``: the NL pattern psi^2 (psi^2 c_2 after a ramp fit)."""
    stamp = scene.stamps[0]
    shape = stamp**2 if shape is None else shape
    reference0 = moments.select(scene.reference, slice(0, 1))
    if not reference0.ok[0]:
        return []
    gradient = moments.pixel_response(stamp[None], reference0, settings)[0]
    expected = np.sqrt(np.sum((gradient * shape) ** 2, axis=(1, 2))) * charge_scale * sigma_beta
    if np.all(expected >= MONTE_CARLO_SPREAD_FLOOR):
        return []
    return [
        make(
            FlagCode.BELOW_MONTE_CARLO_RESOLUTION,
            sigma_beta=sigma_beta,
            expected=", ".join(f"{n} {v:.2g}" for n, v in zip(METRICS, expected, strict=True)),
            floor=MONTE_CARLO_SPREAD_FLOOR,
            measured=", ".join(f"{v:.2g}" for v in measured),
            expected_spread=[float(v) for v in expected],
        )
    ]


#: The measured quantities (``defaults.MEASURED``; not the requirement metrics, ``defaults.METRICS``).
METRICS = defaults.MEASURED


@dataclass(frozen=True)
class SlopeResult:
    """Slopes at one magnitude: the paper's Fig. 3 (bias) and Fig. 5 (scatter) ordinates.

    ``bias[metric]``: d(metric)/d(beta) at beta0, a statistic over centroid realizations.
    ``scatter[metric]``: sigma(metric) / sigma_beta for independent per-pixel beta, with its
    uncertainty; ``scatter_basis`` says how it was obtained.
    """

    conditions: dict
    magnitude: float
    beta0: float
    beta_convention: str
    flux_electrons: float
    #: The star's brightest pixel before the NL [e-], over every sub-pixel centroid (``star_peak_electrons``).
    peak_electrons: float
    bias: dict[str, Statistic]
    scatter: dict[str, dict[str, float | None]]
    scatter_basis: str
    failed_realizations: int
    flags: list[str]
    elapsed_s: float
    extras: dict = field(default_factory=dict)

    def slope(self, mode: str, parts: Sequence[str]) -> tuple[float | None, float | None]:
        """(slope, its standard error) of one metric (``parts`` one of METRICS) or of |e| (parts
        ``("de1", "de2")``, combined in quadrature); (None, None) where the simulation failed."""
        values, errors = [], []
        for part in parts:
            if mode == "bias":
                values.append(self.bias[part].mean)
                errors.append(self.bias[part].stderr or 0.0)
            else:
                values.append(self.scatter[part]["value"])
                errors.append(self.scatter[part]["uncertainty"] or 0.0)
        if any(v is None for v in values):
            return None, None
        if len(values) == 1:
            return float(values[0]), float(errors[0])
        value = math.hypot(*values)
        error = math.hypot(values[0] * errors[0], values[1] * errors[1]) / value if value > 0 else math.hypot(*errors)
        return value, error

    def to_dict(self) -> dict:
        c = self.conditions
        return {
            "band": c["band"],
            "sca": c["sca"],
            "magnitude": self.magnitude,
            "beta0": self.beta0,
            "beta_convention": self.beta_convention,
            "exptime_s": c["exptime_s"],
            "flux_electrons": self.flux_electrons,
            "peak_electrons": self.peak_electrons,
            "bias_slope": {k: v.to_dict() for k, v in self.bias.items()},
            "scatter_slope": self.scatter,
            "scatter_basis": self.scatter_basis,
            "failed_realizations": self.failed_realizations,
            "flags": [str(f) for f in self.flags],
            "flag_codes": flag_codes(self.flags),
            "elapsed_s": self.elapsed_s,
            "fidelity": c["fidelity"],
            "conditions": c,
            **self.extras,
        }


@single_blas
def slopes(
    config: SimulationConfig,
    magnitudes: Sequence[float] | float,
    beta0: float = defaults.BETA0,
    sigma_beta: float | None = None,
    beta_convention: str = "paper",
    scene: Scene | None = None,
    progress: Progress | None = None,
    linearise_at: str = "beta0",
) -> list[SlopeResult]:
    """Bias and scatter slopes at ``beta0`` for each magnitude (paper Figs. 3 and 5).

    ``linearise_at`` (:data:`LINEARISE_STATES`): "beta0", the paper's, the slope of the uncorrected
    detector at beta0; "corrected", the slope a calibration error acts through once the pipeline has
    corrected the NL: taken at the residual CORRECTED_RESIDUAL x beta0, with a ramp's saturation flags
    those of the raw beta0 (docs/ramps.md). The scatter keeps sigma_beta (a per-pixel calibration error).

    ``monte_carlo``: the paper's method. The bias slope is the finite difference over
    beta0 * {0.99, 1.01} (identical to its 3-point linear fit) for each centroid; the scatter slope
    is the spread of the metrics over ``realizations`` draws of per-pixel beta ~ N(beta0,
    sigma_beta^2) at a fixed centroid, divided by sigma_beta (default sigma_beta = 0.1 beta0), with
    the standard error of a standard deviation.

    ``linear``: exact derivatives at beta0 from the gradient of the moments at the NL-distorted
    image: slope = g(I_beta0) . dI/dbeta and scatter slope = ||g (.) dI/dbeta||, averaged over the
    centroid realizations (uncertainty: their standard error).
    """
    mags = check_magnitudes(magnitudes)
    check_choice(linearise_at, "linearise_at", LINEARISE_STATES)
    raw = detector.to_paper_beta(beta0, beta_convention)
    if raw == 0:
        raise InputError("beta0", "slopes are taken at beta0, which must not be zero")
    # The beta the slope is taken at; the raw beta0 still sets what saturates.
    beta = raw if linearise_at == "beta0" else CORRECTED_RESIDUAL * raw
    if sigma_beta is None:
        sigma_beta = defaults.SIGMA_BETA_FRACTION * abs(raw)
    sigma_beta = check_sigma_beta(sigma_beta)
    if sigma_beta == 0:
        raise InputError("sigma_beta", "the scatter slope needs sigma_beta > 0")
    scene = scene or prepare(config)
    if scene.config != config:
        raise InputError("scene", "the scene was prepared for a different configuration")
    conditions = config.conditions()
    if linearise_at != "beta0":
        conditions["linearised_at"] = {"state": linearise_at, "beta": beta, "saturation_beta": raw}
    settings = config.moment_settings
    scene_flags = _scene_flags(scene)
    out: list[SlopeResult] = []
    share = scene.elapsed_s / len(mags)
    for index, magnitude in enumerate(mags):
        start = time.perf_counter()
        if progress:
            progress(index, len(mags), f"m={magnitude:g}")
        flux = float(config.electrons(magnitude))
        charge_scale = flux * config.oversampling**2
        peak = _peak_electrons(scene, charge_scale)
        effect = ramp_effect(scene, charge_scale, beta=raw) if config.ramp is not None else None
        flags = scene_flags + _validity_flags(
            scene, charge_scale, np.full(1, raw * (1 + PAPER_BETA_STEP)), peak, ramp_effect=effect
        )
        if config.method == "monte_carlo":
            bias, status = _finite_difference_slopes(scene, charge_scale, beta, settings, effect)
            flags += _cut_jump_flags(scene, charge_scale, beta, settings, bias, effect)
            scatter_runs = simulate(config, [magnitude], [beta], sigma_beta=sigma_beta, scene=scene, saturation_beta=raw)[0]
            scatter = {}
            for name in METRICS:
                stat: Statistic = getattr(scatter_runs, name)
                if stat.std is None or stat.count < 2:
                    scatter[name] = {"value": None, "uncertainty": None}
                else:
                    value = stat.std / sigma_beta
                    scatter[name] = {"value": value, "uncertainty": value / math.sqrt(2 * (stat.count - 1))}
            basis = (
                f"Monte Carlo: spread over {config.realizations} per-pixel beta maps with sigma_beta={sigma_beta:g} "
                "at a fixed centroid (the paper's method)"
            )
            flags += [f for f in scatter_runs.flags if f not in flags]
        else:
            bias, scatter, status = _linear_slopes(scene, charge_scale, beta, settings, effect)
            basis = "linear response at beta0: ||g . dI/dbeta|| averaged over centroid realizations"
        out.append(
            SlopeResult(
                conditions=conditions,
                magnitude=magnitude,
                beta0=beta0,
                beta_convention=beta_convention,
                flux_electrons=flux,
                peak_electrons=star_peak_electrons(scene, charge_scale),
                bias=bias,
                scatter=scatter,
                scatter_basis=basis,
                failed_realizations=int(np.sum(status != moments.MomentStatus.OK)),
                flags=flags + _failure_flag(status),
                elapsed_s=time.perf_counter() - start + share,
                extras={} if effect is None else dict(effect.extras),
            )
        )
    if progress:
        progress(len(mags), len(mags), "done")
    return out


def _finite_difference_slopes(
    scene: Scene, charge_scale: float, beta: float, settings: moments.MomentSettings, effect: RampEffect | None = None
):
    values = []
    statuses = []
    for factor in (1 - PAPER_BETA_STEP, 1 + PAPER_BETA_STEP):
        fit, reference, *_ = _perturbed_fit(scene, charge_scale, beta * factor, settings, effect)
        d_r, d_e1, d_e2, status = _metrics(fit, reference)
        values.append(np.stack([d_r, d_e1, d_e2]))
        statuses.append(status)
    slope = (values[1] - values[0]) / (2 * PAPER_BETA_STEP * beta)
    status = np.where(statuses[0] != moments.MomentStatus.OK, statuses[0], statuses[1])
    return {name: Statistic.of(slope[k]) for k, name in enumerate(METRICS)}, status


def _cut_jump_flags(
    scene: Scene,
    charge_scale: float,
    beta: float,
    settings: moments.MomentSettings,
    bias: dict[str, Statistic],
    effect: RampEffect | None = None,
) -> list[str]:
    """Flag finite-difference slopes that a hard weight cut made jumpy.

    With the weight cut at rho^2 = 25, a pixel that crosses the cut between beta0 x 0.99 and x 1.01
    changes the moments by a step (w = e^-12.5 of its value), which the 2 % beta step turns into a
    slope error; the symmetric difference itself is otherwise exact to (1 %)^2. The exact derivative
    at beta0 (the linear method) has no such step, so the two are compared and a difference above
    0.1 % is reported. Measured (50 centroids, H158/J129/F184, m = 18.5-22.5): the two agree to 1e-8
    unless a realization crosses the cut, which moves the e slopes by 0.1-1.8 % and, being one
    outlier, also sets the stated standard error (the difference is then 1.0 standard error).
    """
    if not math.isfinite(scene.config.weight_cut_rho2):
        return []
    exact, _, _ = _linear_slopes(scene, charge_scale, beta, settings, effect)
    off = []
    for name in METRICS:
        fd, lin = bias[name], exact[name]
        if fd.mean is None or lin.mean is None or lin.mean == 0:
            continue
        difference = abs(fd.mean - lin.mean)
        if difference > 1e-3 * abs(lin.mean):
            off.append(f"{name} {100 * difference / abs(lin.mean):.2g} %")
    if not off:
        return []
    return [make(FlagCode.JUMPY_FINITE_DIFFERENCE, differences=", ".join(off), cut=scene.config.weight_cut_rho2)]


def _linear_slopes(
    scene: Scene, charge_scale: float, beta: float, settings: moments.MomentSettings, effect: RampEffect | None = None
):
    # Everything at unit flux: the distorted image is psi - beta s psi^2 (moments ignore scale),
    # and d/d beta of the charge image divided by s is -s psi^2 (times c_2 after a ramp fit; scene
    # effects: ``nl_images``).
    fit, reference, stamps, perturbation, derivative = _perturbed_fit(scene, charge_scale, beta, settings, effect)
    distorted = stamps + perturbation
    bias_values, scatter_values = (v.T.copy() for v in moments.response_to(distorted, fit, derivative, settings))
    ok = fit.ok & reference.ok
    # The gradient of R is relative to R(beta0); Delta R / R is relative to the unperturbed R0.
    size_scale = fit.sigma / reference.sigma
    bias_values[0] *= size_scale
    scatter_values[0] *= size_scale
    bias = {name: Statistic.of(np.where(ok, bias_values[k], np.nan)) for k, name in enumerate(METRICS)}
    scatter = {}
    for k, name in enumerate(METRICS):
        stat = Statistic.of(np.where(ok, scatter_values[k], np.nan))
        scatter[name] = {"value": stat.mean, "uncertainty": stat.stderr}
    status = np.where(fit.ok, reference.status, fit.status)
    return bias, scatter, status
