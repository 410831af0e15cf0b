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

from . import backgrounds
from . import scene as scenes

#: Name of the default scene (``--scene roman``; ``--scene paper`` is the paper's idealised one).
NAME = "roman"

#: Pointing jitter per axis [arcsec rms]: STPSF's value for Roman. The official PSF products' 8 mas
#: FWHM (3.4 mas rms) and GalSim's 14 mas bracket it (docs/optics.md).
JITTER_ARCSEC = 0.006
#: Charge diffusion [native pixels rms]: sqrt((C11 + C22) / 2) of Givans et al. 2022 (PASP,
#: arXiv:2110.08155; C11 = 0.1066, C22 = 0.1136 px^2), measured on Roman detectors.
CHARGE_DIFFUSION_PX = 0.332
#: The star: a K0V spectral type (the official PSF products'); a 5270 K blackbody stands in for the
#: spectrum (Pecaut & Mamajek's K0V temperature), as ``psfstats`` does. Selectable per request.
SED = "blackbody:5270"
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
    DefaultValue("sed", SED, "K", "K0V (the official PSF products' star), a 5270 K blackbody stand-in (Pecaut & Mamajek)"),
    DefaultValue("jitter", JITTER_ARCSEC, "arcsec rms per axis", "STPSF's Roman jitter"),
    DefaultValue("charge_diffusion", CHARGE_DIFFUSION_PX, "native px rms", "Givans et al. 2022, PASP, arXiv:2110.08155"),
    DefaultValue("ipc", "galsim.roman.ipc_kernel, after the NL", "", "GalSim 2.8.5 roman.ipc_kernel"),
    DefaultValue("background", BACKGROUND, "e- per pixel over the exposure", backgrounds.SOURCE_VERSION),
    DefaultValue("readout", MA_TABLE, "", "romanisim 0.15.0 imaging MA table 4 (BSD)"),
    DefaultValue("ramp_fit", RAMP_FIT, "", "romancal's likelihood ramp fit, saturation on the read signal"),
    DefaultValue("linearise_at", LINEARISE_AT, "", "romancal corrects the NL before the ramp fit (docs/ramps.md)"),
)


@dataclass(frozen=True)
class Readout:
    """The default's readout for one SCA and the background over its exposure."""

    ramp: object  # ramps.Ramp
    exptime_s: float
    background_e: float


def exptime_s() -> float:
    """The default's exposure: the MA table's last read (139.1 s for C2A_IMG_HLWAS)."""
    from . import ramps

    return float(ramps.load_ma_table(MA_TABLE).duration_s)


def readout(band: str, sca: int, exptime: float | None = None) -> Readout:
    """The HLWAS ramp (likelihood fit, the SCA's official read noise, romancal's rules) and the
    background over its exposure; ``exptime`` None: the table's own exposure."""
    from . import ramps

    ramp, exposure = ramps.build(ma_table=MA_TABLE, fit=RAMP_FIT, sca=sca, exptime_s=exptime)
    return Readout(ramp, exposure, backgrounds.background_electrons(BACKGROUND, band, sca, exposure))


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


def scene(position: tuple[float, float] | None, background_e: float) -> scenes.SceneModel:
    """The default scene at ``position`` (None: the SCA centre) with ``background_e`` per pixel."""
    return replace(base_scene(), position=position, background_e=float(background_e))


def conditions() -> list[dict]:
    """Every value of the default with its source, as an answer's conditions quote them."""
    return [v.as_dict() for v in VALUES]
