"""The Roman default: the star, optics, detector and readout an answer is for unless the request
says ``scene="paper"``.

One owner of every value of the default, each with its source (the decision records in
``docs/optics.md`` and ``docs/ramps.md``; provenance of the data in ``nlpsf/data/SOURCES.md``):
the scene (:func:`scene`), the readout and its exposure (:func:`readout`), the pupil-scale rule
and the state a slope is linearised at. The table build (``tablebuild.TableSettings.roman``), the
field grid and the solver all read them here, and every answer quotes :func:`conditions`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cache, lru_cache

from nlpsf.roman import backgrounds
from nlpsf.sim import scene as scenes

#: Name of the default scene (``--scene roman``; ``--scene paper`` is the paper's idealised one).
NAME = "roman"

#: Pointing jitter per axis [arcsec rms]: STPSF's value for Roman. The official PSF products' 8 mas
#: FWHM (3.4 mas rms) and GalSim's 14 mas bracket it (docs/optics.md).
JITTER_ARCSEC = 0.006
#: Charge diffusion [native pixels rms]: sqrt((C11 + C22) / 2) of Givans et al. 2022 (PASP,
#: arXiv:2110.08155; C11 = 0.1066, C22 = 0.1136 px^2), measured on Roman detectors.
CHARGE_DIFFUSION_PX = 0.332
#: The star: a K0V, the official PSF products' star, as the vendored Pickles (1998, PASP 110, 863)
#: K0V spectrum (``nlpsf.roman.seds``, ``--sed k0v``; its provenance and terms in nlpsf/data/SOURCES.md).
#: Selectable (``--sed``); the spread over other stars is the ``sed`` part of ``roman_uncertainty``.
SED = "k0v"
#: Background preset (``backgrounds.PRESETS``): twice the minimum zodiacal light, thermal and dark.
BACKGROUND = backgrounds.DEFAULT_PRESET
#: romanisim's default imaging MultiAccum table (romanisim-4) and romancal's likelihood ramp fit.
MA_TABLE = "C2A_IMG_HLWAS"
RAMP_FIT = "optimal"
#: Pupil-mask scale rule reproducing the official clear area of each mask and SCA.
PUPIL_SCALE = "official"
#: The state a slope is taken at: "corrected" (the pipeline removes the NL before the ramp fit, so a
#: calibration error acts on an almost linear detector; docs/ramps.md). The paper's is "beta0".
LINEARISE_AT = "corrected"
#: How the calibration error acts in that state (``experiment.correction.RESIDUAL_MODELS``): the
#: pipeline's linearity correction evaluated on every resultant of the measured, IPC-coupled signal, as
#: romancal's linearity step applies it ("per_read_beta", a residual beta on every read before IPC, is the
#: earlier model; docs/ramps.md).
RESIDUAL_NL = "per_resultant_correction"


@dataclass(frozen=True)
class DefaultValue:
    """One value of the default, as answers quote it."""

    name: str
    value: object
    unit: str
    source: str

    def as_dict(self) -> dict:
        return {"name": self.name, "value": self.value, "unit": self.unit, "source": self.source}


VALUES: tuple[DefaultValue, ...] = (
    DefaultValue(
        "optics", "Zernikes at the star's position", "", "GalSim 2.8.5 Roman Cycle-9 aberrations, bilinear across the SCA"
    ),
    DefaultValue("pupil_scale", PUPIL_SCALE, "", "roman-technical-information PupilMasks clear areas (CC0)"),
    DefaultValue(
        "sed",
        SED,
        "",
        "K0V (the official PSF products' star): the Pickles 1998 (PASP 110, 863) K0V spectrum pickles_uk_31, "
        "400-2500 nm, STScI CDBS via EXOSIMS; no licence statement, cite Pickles 1998 (nlpsf/data/SOURCES.md)",
    ),
    DefaultValue("jitter", JITTER_ARCSEC, "arcsec rms per axis", "STPSF's Roman jitter"),
    DefaultValue("charge_diffusion", CHARGE_DIFFUSION_PX, "native px rms", "Givans et al. 2022, PASP, arXiv:2110.08155"),
    DefaultValue("ipc", "galsim.roman.ipc_kernel, after the NL", "", "GalSim 2.8.5 roman.ipc_kernel"),
    DefaultValue("background", BACKGROUND, "e- per pixel over the exposure", backgrounds.SOURCE_VERSION),
    DefaultValue("readout", MA_TABLE, "", "romanisim 0.15.0 imaging MA table 4 (BSD)"),
    DefaultValue("ramp_fit", RAMP_FIT, "", "romancal's likelihood ramp fit, saturation on the read signal"),
    DefaultValue("linearise_at", LINEARISE_AT, "", "romancal corrects the NL before the ramp fit (docs/ramps.md)"),
    DefaultValue(
        "residual_nl",
        RESIDUAL_NL,
        "",
        "romancal's linearity step (stcal linearity_correction) evaluates the correction on each resultant of the "
        "measured, IPC-coupled signal (docs/ramps.md, docs/calibration.md)",
    ),
)


@dataclass(frozen=True)
class Readout:
    """The default's readout for one SCA and the background over its exposure."""

    ramp: object  # ramps.Ramp
    exptime_s: float
    background_e: float


def exptime_s() -> float:
    """The default's exposure: the MA table's last read (139.1 s for C2A_IMG_HLWAS)."""
    from nlpsf.sim import ramps

    return float(ramps.load_ma_table(MA_TABLE).duration_s)


@lru_cache(maxsize=1024)
def readout(band: str, sca: int, exptime: float | None = None) -> Readout:
    """The HLWAS ramp (likelihood fit, the SCA's official read noise, romancal's rules) and the
    background over its exposure; ``exptime`` None: the table's own exposure."""
    from nlpsf.sim import ramps

    ramp, exposure = ramps.build(ma_table=MA_TABLE, fit=RAMP_FIT, sca=sca, exptime_s=exptime)
    return Readout(ramp, exposure, backgrounds.background_electrons(BACKGROUND, band, sca, exposure))


@cache
def base_scene() -> scenes.SceneModel:
    """The default's scene effects without position or background (those depend on the point)."""
    return scenes.SceneModel(
        sed=SED,
        jitter_arcsec=JITTER_ARCSEC,
        charge_diffusion_px=CHARGE_DIFFUSION_PX,
        ipc=scenes.ROMAN_IPC_KERNEL,
        ipc_label="roman",
        ipc_order="after",
        name=NAME,
    )


@lru_cache(maxsize=4096)
def scene(position: tuple[float, float] | None, background_e: float) -> scenes.SceneModel:
    """The default scene at ``position`` (None: the SCA centre) with ``background_e`` per pixel."""
    return replace(base_scene(), position=position, background_e=float(background_e))


def conditions() -> list[dict]:
    """Every value of the default with its source, as an answer's conditions quote them."""
    return [v.as_dict() for v in VALUES]


# --- what a request leaves unset -------------------------------------------------------------

#: The scene presets a request may name: the Roman default; the paper's idealised scene (today's
#: answers, bit for bit); GalSim's Roman constants (jitter 0.014", diffusion 0.1 px, flat f_nu, IPC,
#: on the paper's final frame), the scene the GalSim cross-checks use.
PRESETS: tuple[str, ...] = (NAME, "paper", "galsim-roman")


@dataclass(frozen=True)
class Policy:
    """What a preset means for an answer, as data: the solver, the slope providers and the answer's
    conditions ask these, never the preset's name."""

    name: str
    #: Answered from the Roman default's shipped field grid where it covers the request.
    field_grid: bool
    #: Without a position, the answer is the SCA's range over its field grid's nodes.
    ranges_over_sca: bool
    #: The shipped measurements (fidelity errors, model parts) its answers read: "roman" or "paper".
    measured_as: str
    #: Its answers keep the paper tables' own saturation limits whatever they simulate (bit for bit).
    tables_limits: bool
    #: Its answers quote the Roman default's values (``conditions``).
    quotes_default: bool
    #: The ramp fit of a readout the request gives without a fit.
    ramp_fit: str
    #: Its scene holds a sky over the exposure (filled where the request changes the scene but not its sky).
    sky: bool
    #: The detector state its slopes are taken at unless a request says.
    linearise_at: str


#: Each preset's policy (:data:`PRESETS`).
POLICIES: dict[str, Policy] = {
    NAME: Policy(NAME, field_grid=True, ranges_over_sca=True, measured_as="roman", tables_limits=False,
                 quotes_default=True, ramp_fit=RAMP_FIT, sky=True, linearise_at=LINEARISE_AT),
    "paper": Policy("paper", field_grid=False, ranges_over_sca=False, measured_as="paper", tables_limits=True,
                    quotes_default=False, ramp_fit="ols", sky=False, linearise_at="beta0"),
    "galsim-roman": Policy("galsim-roman", field_grid=False, ranges_over_sca=False, measured_as="paper",
                           tables_limits=False, quotes_default=False, ramp_fit="ols", sky=False, linearise_at="beta0"),
}  # fmt: skip


def policy(name: str) -> Policy:
    """The policy of a preset by name (:data:`POLICIES`)."""
    return POLICIES[check_preset(name)]


def preset_of(scene, preset: str | None = None) -> str:
    """The preset a request builds on: the one named, else the scene's own name where it is a preset,
    else the Roman default."""
    if preset is None:
        name = getattr(scene, "name", None)
        preset = name if name in PRESETS else NAME
    return check_preset(preset)


def named(text: str | None) -> str | None:
    """The preset a scene option names (``--scene roman``), None where it names none (a file, or nothing)."""
    if not isinstance(text, str):
        return None
    lowered = text.strip().lower()
    return lowered if lowered in PRESETS else None


#: The preset a scene read from a file builds on: its readout and state are the paper's.
FILE_PRESET = "paper"


def sky_base(preset: str, band: str, sca: int, exptime: float | None = None, ramp=None):
    """A preset's scene without a position, with its sky over the exposure where it has one
    (:attr:`Policy.sky`): the base the options a user gives change. Kept by what decides it (a
    frozen scene: every JSON request at a position builds on it)."""
    try:
        return _kept_sky_base(preset, band, sca, exptime, ramp)
    except TypeError:  # something unhashable (a bad value the request refuses later): built afresh
        return _sky_base(preset, band, sca, exptime, ramp)


@lru_cache(maxsize=1024)
def _kept_sky_base(preset: str, band: str, sca: int, exptime: float | None, ramp):
    return _sky_base(preset, band, sca, exptime, ramp)


def _sky_base(preset: str, band: str, sca: int, exptime: float | None, ramp):
    if not policy(preset).sky:
        return preset_base(preset)
    filled = fill(preset, band, sca, exptime, ramp, None, None)
    return replace(preset_base(preset), background_e=float(filled.background_e))


def default_fill(band: str, sca: int, exptime: float | None = None, ramp=None) -> Filled:
    """:func:`fill` of the Roman default (its readout, exposure and sky at ``band`` and ``sca``)."""
    return fill(NAME, band, sca, exptime, ramp, None, None)


def check_preset(name: str) -> str:
    from nlpsf.checks import InputError

    if not isinstance(name, str) or name.strip().lower() not in PRESETS:
        raise InputError("scene", f"unknown scene preset {name!r}; presets: {', '.join(PRESETS)}")
    return name.strip().lower()


@dataclass(frozen=True)
class Filled:
    """What a preset fills in where a request leaves it unset (None: keep the request's)."""

    exptime: float
    ramp: object  # ramps.Ramp | None
    pupil_scale: str | None
    linearise_at: str
    background_e: float | None


@lru_cache(maxsize=4096)
def fill(preset: str, band: str, sca: int, exptime: float | None, ramp, pupil_scale: str | None,
         linearise_at: str | None) -> Filled:  # fmt: skip
    """The request's readout, exposure, pupil rule and state with the preset's values where unset.

    ``roman``: the HLWAS readout unless a ramp is given (``--ramp`` / ``--ma-table`` replace it),
    its exposure (139.1 s) unless ``exptime`` is given (``ramps.build``'s rule: the table's last read
    must fall within it), the official pupil scale, the corrected state, and the background over
    that exposure. ``paper`` and ``galsim-roman``: the paper's final frame of 168.1 s, the tables'
    pupil rule and the state beta0 -- today's request exactly."""
    from nlpsf import defaults

    if preset != NAME:
        if exptime is None:
            exptime = float(ramp.table.duration_s) if ramp is not None else defaults.EXPTIME_S
        return Filled(exptime, ramp, pupil_scale, linearise_at or "beta0", None)
    if ramp is None:
        chosen = readout(band, sca, exptime)
        ramp, exptime, background = chosen.ramp, chosen.exptime_s, chosen.background_e
    else:
        exptime = float(ramp.table.duration_s) if exptime is None else exptime
        background = backgrounds.background_electrons(BACKGROUND, band, sca, exptime)
    return Filled(float(exptime), ramp, pupil_scale or PUPIL_SCALE, linearise_at or LINEARISE_AT, background)


def preset_scene(preset: str, position=None, background_e: float = 0.0) -> scenes.SceneModel | None:
    """The scene of a preset (None for ``paper``: the solver's plain path, today's answers)."""
    if preset == NAME:
        return scene(position, background_e)
    if preset == "galsim-roman":
        return replace(scenes.preset("galsim-roman"), position=position)
    return None if position is None else scenes.SceneModel(position=position)


def preset_base(name: str) -> scenes.SceneModel:
    """A preset's scene effects without position or sky: "roman" the default's (:func:`base_scene`),
    "paper" and "galsim-roman" ``scene.preset``'s."""
    name = check_preset(name)
    return base_scene() if name == NAME else scenes.preset(name)


def load_scene(name_or_path: str) -> scenes.SceneModel:
    """A preset's base scene (:func:`preset_base`) or a scene saved as JSON (``scene.load``)."""
    if isinstance(name_or_path, str) and name_or_path.strip().lower() in PRESETS:
        return preset_base(name_or_path)
    return scenes.load(name_or_path)


@lru_cache(maxsize=4096)
def is_default_scene(model, background_e: float) -> bool:
    """Whether ``model`` is the Roman default's scene (any position) with this background."""
    return model is not None and replace(model, position=None) == scene(None, background_e)


def fill_simulation(payload: dict, given: set[str], build_ramp=None) -> dict:
    """A simulation request (the service's ``POST /simulations`` body, JSON-shaped) with what it
    leaves unset filled as the CLI's ``simulate`` fills it: without a scene (or with preset "roman")
    the Roman default -- its scene at the request's position (the SCA centre otherwise), the HLWAS
    readout with the likelihood fit and its exposure unless a ramp, MA table or exptime is given,
    the official pupil scale, and its sky over that exposure unless ``scene.background`` is given.
    ``scene`` "paper" (or "galsim-roman"): the paper's final frame of 168.1 s, the OLS fit and the
    tables' pupil scale. The filled request names every value, so its hash says which scene was
    simulated. ``given``: the fields the client sent; ``build_ramp(reads, ma_table, fit, read_noise,
    exptime, sca)`` -> (ramp, exptime): ``ramps.build`` without files (the service passes its own,
    which reads a shipped table's name only from the package)."""
    from nlpsf import defaults
    from nlpsf.sim import ramps

    if build_ramp is None:

        def build_ramp(reads, ma_table, fit, read_noise, exptime, sca):
            return ramps.build(reads, ma_table, fit, read_noise, exptime, allow_files=False, sca=sca)

    payload = dict(payload)
    scene = payload.get("scene")
    scene = {"preset": scene} if isinstance(scene, str) else dict(scene or {})
    preset = scene.get("preset") or NAME
    if "exptime" not in given:
        payload["exptime"] = None  # the readout's last read (an MA table's), else the paper's 168.1 s
    if preset != NAME:
        # The paper's scene named alone is the request without a scene: the same hash as before.
        alone = all(v is None for k, v in scene.items() if k not in ("preset", "sed_units"))
        payload["scene"] = None if preset == "paper" and alone else scene
        payload["pupil_scale"] = payload.get("pupil_scale") or defaults.PUPIL_SCALE
        payload["ramp_fit"] = payload.get("ramp_fit") or "ols"
        return payload
    if payload.get("ramp") is None and payload.get("ma_table") is None:
        payload["ma_table"] = ramps.load_ma_table(MA_TABLE).name
    payload["ramp_fit"] = payload.get("ramp_fit") or RAMP_FIT
    payload["pupil_scale"] = payload.get("pupil_scale") or PUPIL_SCALE
    if scene.get("background") is None:
        _, exptime = build_ramp(
            payload.get("ramp"), payload.get("ma_table"), payload["ramp_fit"], payload.get("read_noise"),
            payload["exptime"], payload["sca"],
        )  # fmt: skip
        band = str(payload["band"]).upper()
        scene["background"] = backgrounds.background_electrons(BACKGROUND, band, payload["sca"], exptime)
    payload["scene"] = {**scene, "preset": NAME}
    return payload
