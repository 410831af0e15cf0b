"""The simulation configuration: everything a simulation depends on apart from magnitude and beta."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np

from nlpsf import defaults, roman
from nlpsf._version import __version__
from nlpsf.checks import InputError, check_choice, check_exptime, check_full_well, check_integer
from nlpsf.roman import photometry
from nlpsf.sim import moments, optics, ramps, render
from nlpsf.sim.levels import level_name

from .. import scene as scenes

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
    #: The scene effects (``nlpsf.sim.scene``); the default is the paper's scene.
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
        check_integer(self.seed, "seed", *defaults.SEED_RANGE)
        render.Grid(self.oversampling, self.stamp)
        if self.realizations * self.stamp**2 * 8 > MAX_STAMP_BYTES:
            raise InputError(
                "realizations",
                f"{self.realizations} realizations of {self.stamp}x{self.stamp} stamps need "
                f"{self.realizations * self.stamp**2 * 8 / 1e9:.1f} GB; the limit is {MAX_STAMP_BYTES / 1e9:.1f} GB",
            )
        check_exptime(self.exptime_s)
        check_full_well(self.full_well_e)
        scenes.check_first_order(self.scene, self.full_well_e)  # the same refusal as the service's, at every entry
        check_choice(self.method, "method", METHODS)
        check_choice(self.pupil_scale, "pupil_scale", roman.PUPIL_SCALE_RULES)
        moments.MomentSettings(weight_cut_rho2=self.weight_cut_rho2)
        optics_config = self.optics  # validates n_wavelengths and pupil_bin
        if not self.scene.no_effects:
            optics_config.wavelengths_and_weights()  # a SED table must cover the band: refuse it here, not mid-run
        if self.ramp is not None:
            if not isinstance(self.ramp, ramps.Ramp):
                raise InputError("ramp", f"must be a ramps.Ramp, got {type(self.ramp).__name__}")
            self.ramp.check_exposure(self.exptime_s)
            ramps.check_scene(self.scene)  # the one rule of what a ramp combines with

    @classmethod
    def from_settings(cls, settings: Mapping | Any, **changes) -> SimulationConfig:
        """The one constructor from a record of settings: a mapping (the CLI's options, a table's
        settings) or a dataclass (``tablebuild.TableSettings``, ``fidelity.LevelSettings``), of which
        the keys that name a field of this configuration are taken, then ``changes`` on top (a key
        whose meaning differs from the field's, e.g. the CLI's ``--scene`` preset name, must be
        given in ``changes``). Every value is validated by ``__post_init__``."""
        if not isinstance(settings, Mapping):
            settings = {f.name: getattr(settings, f.name) for f in fields(settings)}
        names = {f.name for f in fields(cls)}
        return cls(**{**{k: v for k, v in settings.items() if k in names}, **changes})

    @classmethod
    def from_table(cls, settings: Mapping, **changes) -> SimulationConfig:
        """The simulation a slope table was built with (``SlopeTable.settings``: realizations, seed,
        grid, weight cut, pupil rule), with ``changes`` (band, SCA, method, exposure, ...)."""
        built = {
            "realizations": int(settings["realizations"]),
            "seed": int(settings["seed"]),
            "oversampling": int(settings["oversampling"]),
            "stamp": int(settings["stamp"]),
            "weight_cut_rho2": float(settings["weight_cut_rho2"]),
            "pupil_scale": str(settings["pupil_scale"]),
        }
        return cls.from_settings(built, **changes)

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
        return level_name(self.method, 2 if polychromatic else 1) + ("" if self.scene.no_effects else "+scene")

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
            pupil_scale_source=roman.PUPIL_SCALE_SOURCES[self.pupil_scale],
            data_version=roman.DATA_VERSION,
            code_version=__version__,
        )
        return out


#: The measured quantities (``defaults.MEASURED``; not the requirement metrics, ``defaults.METRICS``).
METRICS = defaults.MEASURED
