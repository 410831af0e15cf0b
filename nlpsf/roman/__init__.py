"""Roman Wide Field Instrument: constants, bands, SCAs and the shipped optical data.

Optical numbers are the ones GalSim 2.8 uses (``galsim.roman``), because GalSim's Roman module is
the reference optical model this project is checked against (data in ``nlpsf/data/roman``). The
throughput (effective area per band) comes by default from the official per-detector curves of
STScI's ``roman-technical-information`` 1.5.0 (``nlpsf/data/roman_technical_information``); the
GalSim 2021 table, one curve for all SCAs, stays available as ``"galsim-2021"``. See
``nlpsf/data/SOURCES.md`` for provenance.
"""

from __future__ import annotations

import gzip
import json
import math
from dataclasses import dataclass
from functools import cache
from importlib import resources
from pathlib import Path

import numpy as np

from nlpsf import defaults
from nlpsf.checks import InputError, check_integer, shown

#: Native WFI pixel scale [arcsec / pixel].
PIXEL_SCALE_ARCSEC = defaults.PIXEL_SCALE_ARCSEC
#: Nominal telescope diameter [m]; also the radius scale of the Zernike disc.
DIAMETER_M = 2.36
#: Linear central obscuration (only used by GalSim as a sampling hint; the masks carry the truth).
OBSCURATION = 0.32
#: Nominal collecting area [cm^2] (Cycle 7); throughput = effective area / this.
COLLECTING_AREA_CM2 = 3.757e4
#: Detector pixel pitch [mm], used to place the Zernike field points on an SCA.
PIXEL_PITCH_MM = 0.01
#: Active pixels per SCA side.
SCA_PIXELS = 4088
#: Number of SCAs in the focal plane.
N_SCA = defaults.N_SCA
#: Wavelength at which the Zernike coefficients are given [nm].
ZERNIKE_REFERENCE_WAVELENGTH_NM = 1293.0

BANDS = defaults.BANDS
PAPER_BANDS = defaults.PAPER_BANDS
#: F184 and K213 use the long-wavelength (cold) pupil mask.
LONG_WAVELENGTH_BANDS: frozenset[str] = frozenset({"F184", "K213"})

#: Throughput data sets by name, newest first, with the version every answer's conditions quote.
THROUGHPUT_VERSIONS: dict[str, str] = {
    "roman-2024": "roman-technical-information 1.5.0: WFI effective areas v8 per SCA (2024-03-01)",
    "galsim-2021": "GalSim 2.8.5 share/roman: Roman_effarea_20210614, one curve for every SCA",
}
THROUGHPUTS = defaults.THROUGHPUTS
#: Newest official data by default; "galsim-2021" is what GalSim's Roman module and the
#: cross-check tests use.
DEFAULT_THROUGHPUT = defaults.THROUGHPUT
#: The official files name the bands by filter (F062, ...); GalSim and nlpsf by band.
OFFICIAL_FILTER_NAMES: dict[str, str] = {
    "R062": "F062",
    "Z087": "F087",
    "Y106": "F106",
    "J129": "F129",
    "H158": "F158",
    "F184": "F184",
    "W146": "F146",
    "K213": "F213",
}
#: Version of the optical (and throughput) data a result depends on; caches key on it.
DATA_VERSION = (
    "GalSim 2.8.5 share/roman: Cycle-9 Zernikes (082623), RST_WIM pupil masks, effarea 20210614; "
    "roman-technical-information 1.5.0: effarea v8 per SCA (20240301)"
)


def check_band(band: str) -> str:
    if not isinstance(band, str) or band.upper() not in BANDS:
        raise InputError("band", f"unknown band {shown(band)}; choose one of {', '.join(BANDS)}")
    return band.upper()


def check_sca(sca: int) -> int:
    return check_integer(sca, "sca", 1, N_SCA)


def check_throughput(name: str) -> str:
    if not isinstance(name, str) or name not in THROUGHPUT_VERSIONS:
        raise InputError("throughput", f"unknown throughput data {shown(name)}; choose one of {', '.join(THROUGHPUTS)}")
    return name


def _data_dir() -> Path:
    return Path(str(resources.files("nlpsf") / "data" / "roman"))


def official_data_dir() -> Path:
    """The vendored files of ``roman-technical-information`` (see ``nlpsf/data/SOURCES.md``)."""
    return Path(str(resources.files("nlpsf") / "data" / "roman_technical_information"))


@cache
def _optical_model_uncertainty() -> dict:
    path = Path(str(resources.files("nlpsf") / "data" / "optical_model_uncertainty.json"))
    return json.loads(path.read_text())


def optical_model_uncertainty(band: str, metric: str) -> float:
    """Relative uncertainty of ``band``'s NL slopes from nlpsf's optical model (Cycle-9 Zernikes)
    against the official post-CDR PSFs, measured by ``scripts/psf_statistics.py``.

    ``metric`` "size": relative to the size slope. "e1", "e2", "e": the change of the ellipticity
    slopes relative to their modulus |c_e| (scale it by |c_e| / |c_e1| for one component).
    """
    per_band = _optical_model_uncertainty()["per_band"]
    entry = per_band[band] if band in per_band else per_band[check_band(band)]  # a request's band: checked once
    return float(entry["size" if metric == "size" else "e"])


@dataclass(frozen=True)
class Throughput:
    """Effective-area curve of one band: wavelength [nm] and effective area [m^2].

    ``sca`` is the detector the curve belongs to (None for SCA-independent data) and ``source``
    the throughput data set (a key of ``THROUGHPUT_VERSIONS``).
    """

    band: str
    wavelength_nm: np.ndarray
    effective_area_m2: np.ndarray
    sca: int | None = None
    source: str = "galsim-2021"

    @property
    def throughput(self) -> np.ndarray:
        """Dimensionless throughput relative to the nominal collecting area (GalSim's convention)."""
        return self.effective_area_m2 * 1e4 / COLLECTING_AREA_CM2

    @property
    def effective_wavelength_nm(self) -> float:
        """Throughput-weighted mean wavelength, GalSim's ``Bandpass.effective_wavelength``."""
        t = self.effective_area_m2
        return float(np.trapezoid(self.wavelength_nm * t, self.wavelength_nm) / np.trapezoid(t, self.wavelength_nm))

    @property
    def blue_limit_nm(self) -> float:
        return float(self.wavelength_nm[0])

    @property
    def red_limit_nm(self) -> float:
        return float(self.wavelength_nm[-1])


def throughput(band: str, *, sca: int, source: str = DEFAULT_THROUGHPUT) -> Throughput:
    """Effective-area curve of ``band`` on detector ``sca`` from the throughput data ``source``.

    Trimmed to where it is non-zero plus one zero on each side (as GalSim's trim does), which
    changes no integral. "galsim-2021" has one curve for every SCA; its ``sca`` is None.
    """
    band = check_band(band)
    sca = check_sca(sca)
    source = check_throughput(source)
    return _throughput(band, sca if source != "galsim-2021" else None, source)


@cache
def _throughput(band: str, sca: int | None, source: str) -> Throughput:
    if source == "galsim-2021":
        names, data = _galsim_effective_areas()
    else:
        names, data = _official_effective_areas(sca)
    wave_nm = 1000.0 * data[:, names.index("Wave")]
    area = data[:, names.index(band if source == "galsim-2021" else OFFICIAL_FILTER_NAMES[band])]
    nonzero = np.flatnonzero(area > 0)
    lo, hi = max(nonzero[0] - 1, 0), min(nonzero[-1] + 1, area.size - 1)
    wave_nm, area = wave_nm[lo : hi + 1].copy(), area[lo : hi + 1].copy()
    wave_nm.setflags(write=False)
    area.setflags(write=False)
    return Throughput(band, wave_nm, area, sca, source)


@cache
def _galsim_effective_areas() -> tuple[list[str], np.ndarray]:
    table = np.genfromtxt(_data_dir() / "Roman_effarea_20210614.txt", names=True)
    names = list(table.dtype.names)
    return names, np.column_stack([np.asarray(table[n], dtype=np.float64) for n in names])


@cache
def _official_effective_areas(sca: int) -> tuple[list[str], np.ndarray]:
    """Columns of ``Roman_effarea_v8_SCAnn_20240301.ecsv`` (wavelength in um, areas in m^2).

    The files' headers carry a free-text line that is not valid ECSV YAML, so astropy's ECSV
    reader refuses them; the body is plain comma-separated values under a header row.
    """
    path = official_data_dir() / f"Roman_effarea_v8_SCA{sca:02d}_20240301.ecsv.gz"
    with gzip.open(path, "rt") as handle:
        lines = [line for line in handle if line.strip() and not line.startswith("#")]
    names = [name.strip() for name in lines[0].split(",")]
    data = np.loadtxt(lines[1:], delimiter=",", dtype=np.float64)
    return names, data


@dataclass(frozen=True)
class Pupil:
    """Binned pupil transmission on a square grid (rows = v, columns = u) at ``scale_m`` per pixel.

    Coordinates follow GalSim's Aperture: pixel index ``i`` sits at ``(i - n/2) * scale_m``.
    """

    sca: int
    mask_kind: str  # "short" or "long"
    transmission: np.ndarray
    scale_m: float

    @property
    def coordinates_m(self) -> np.ndarray:
        n = self.transmission.shape[0]
        return (np.arange(n) - n // 2) * self.scale_m


#: How the pupil mask's pixel scale is set. "galsim": the farthest open pixel of the binned mask
#: lies on the 2.36 m disc, which is what GalSim 2.8.5's ``roman.getPSF`` ends up doing (its
#: ``Image.flip_ud`` drops the scale read from the FITS header, and ``Aperture`` then falls back
#: to this rule). "header": the header's entrance-pupil scale (``CDELT`` x ``PUPIL SCALE FACTOR``),
#: which puts the pupil edge of SCA 1 at 2.37 m but lets the short-wavelength mask of SCA 18 reach
#: 2.49 m. The two differ by 0.5-5.4 % in pupil size depending on the SCA and mask. "official":
#: the scale at which the pupil *as simulated* (the mask binned by ``pupil_bin``, a binned pixel
#: open if any of its sub-pixels is) has the official clear area of that mask and SCA
#: (:func:`official_clear_area_m2`); see ``nlpsf/data/SOURCES.md``.
PUPIL_SCALE_RULES = defaults.PUPIL_SCALE_RULES
#: Where each rule's scale comes from (quoted in docs and conditions).
PUPIL_SCALE_SOURCES: dict[str, str] = {
    "galsim": "GalSim 2.8.5 roman.getPSF: farthest open pixel of the binned mask on the 2.36 m disc",
    "header": "pupil FITS header: CDELT x PUPIL SCALE FACTOR (entrance pupil), times the binning",
    "official": (
        "roman-technical-information PupilMasks (RST-PYLD-ANYS-0511, 2022): the binned mask's open area "
        "equals the official clear area per mask and SCA"
    ),
}
#: The official clear-area files (``nlpsf/data/rti_pupil_masks``), by mask kind.
OFFICIAL_PUPIL_FILES: dict[str, str] = {
    "short": "pupilmask_obsc_skinny_mask.ecsv",
    "long": "pupilmask_obsc_F184_mask.ecsv",
}


def official_pupil_dir() -> Path:
    """The vendored official pupil-mask clear areas (see ``nlpsf/data/SOURCES.md``)."""
    return Path(str(resources.files("nlpsf") / "data" / "rti_pupil_masks"))


@cache
def _official_clear_areas(kind: str) -> dict[int, float]:
    """``exit_pupil_clear`` [m^2] per SCA of one mask: the clear (open) area of the projected pupil
    in entrance-pupil units. Read as plain CSV under the ECSV header (numpy only, so the simulator
    does not import astropy); the summary rows (Min, Max, avg, std) are skipped."""
    lines = [
        line
        for line in (official_pupil_dir() / OFFICIAL_PUPIL_FILES[kind]).read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    names = [name.strip() for name in lines[0].split(",")]
    sca_column, area_column = names.index("sca"), names.index("exit_pupil_clear")
    areas = {}
    for line in lines[1:]:
        values = [v.strip() for v in line.split(",")]
        if values[sca_column].isdigit():
            areas[int(values[sca_column])] = float(values[area_column])
    return areas


def official_clear_area_m2(sca: int, band: str) -> float:
    """The official clear area [m^2] of the pupil mask ``band`` uses on ``sca`` (entrance-pupil units)."""
    kind = "long" if check_band(band) in LONG_WAVELENGTH_BANDS else "short"
    return _official_clear_areas(kind)[check_sca(sca)]


#: The binning whose masks are also shipped packed (``pupils_bin4.npz``): the one every simulation
#: uses by default. Reading them needs numpy alone, where the FITS files need astropy.io.fits
#: (0.25 s of CPU to import, more than the optics of a one-band simulation).
PUPIL_COMPANION_BIN = 4


def _pupil_fits_name(sca: int, kind: str) -> str:
    return f"RST_WIM_Filter_{'F184' if kind == 'long' else 'skinny'}_SCA_{sca}.fits.gz"


def _pupil_from_fits(sca: int, kind: str, pupil_bin: int) -> tuple[np.ndarray, float]:
    """(open mask binned by ``pupil_bin``, rows flipped to GalSim's orientation; header scale [m])."""
    from astropy.io import fits

    with gzip.open(_data_dir() / _pupil_fits_name(sca, kind), "rb") as handle, fits.open(handle) as hdul:
        header = hdul[0].header
        data = np.asarray(hdul[0].data, dtype=np.float64)
        # The file's pixel scale is for the exit pupil in microns; the header gives the
        # factor to the entrance pupil (GalSim does the same).
        scale_m = float(header["CDELT"]) * float(header["HIERARCH PUPIL SCALE FACTOR"]) * 1e-6
    n = data.shape[0] // pupil_bin
    binned = data.reshape(n, pupil_bin, n, pupil_bin).sum(axis=(1, 3))
    # GalSim keeps a binned pixel if any sub-pixel is open; we keep that rule so the optical
    # model is the same one the reference pipeline uses.
    return (binned > 0)[::-1, :].copy(), scale_m


def _pupil_companion_path() -> Path:
    return Path(str(resources.files("nlpsf") / "data" / "pupils" / f"pupils_bin{PUPIL_COMPANION_BIN}.npz"))


@cache
def _pupil_companion() -> dict[str, np.ndarray]:
    with np.load(_pupil_companion_path(), allow_pickle=False) as archive:
        return {k: archive[k] for k in archive.files}


def _pupil_from_companion(sca: int, kind: str) -> tuple[np.ndarray, float]:
    packed = _pupil_companion()
    n = int(packed["side"])
    mask = np.unpackbits(packed[f"{kind}_{sca}"])[: n * n].reshape(n, n).astype(np.float64)
    return mask, float(packed[f"{kind}_{sca}_scale_m"])


def write_pupil_companion() -> Path:
    """Pack every SCA's binned masks from the FITS files (``python -c 'from nlpsf import roman;
    roman.write_pupil_companion()'`` after the masks change); ``tests/library/test_data.py`` checks it."""
    arrays: dict[str, np.ndarray] = {}
    for sca in range(1, N_SCA + 1):
        for kind in ("short", "long"):
            mask, scale_m = _pupil_from_fits(sca, kind, PUPIL_COMPANION_BIN)
            arrays[f"{kind}_{sca}"] = np.packbits(mask.ravel())
            arrays[f"{kind}_{sca}_scale_m"] = np.array(scale_m)
            arrays["side"] = np.array(mask.shape[0])
    path = _pupil_companion_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **arrays)
    _pupil_companion.cache_clear()
    return path


@cache
def pupil(sca: int, band: str, pupil_bin: int = 4, scale_rule: str = "galsim") -> Pupil:
    """Pupil mask of ``sca`` for ``band`` (short- or long-wavelength mask), binned by ``pupil_bin``."""
    sca = check_sca(sca)
    band = check_band(band)
    if check_integer(pupil_bin, "pupil_bin", 1, 16) and 2048 % int(pupil_bin):
        raise InputError("pupil_bin", f"must divide 2048, got {pupil_bin!r}")
    if scale_rule not in PUPIL_SCALE_RULES:
        raise InputError("pupil_scale", f"must be one of {', '.join(PUPIL_SCALE_RULES)}, got {scale_rule!r}")
    kind = "long" if band in LONG_WAVELENGTH_BANDS else "short"
    if pupil_bin == PUPIL_COMPANION_BIN and _pupil_companion_path().exists():
        transmission, scale_m = _pupil_from_companion(sca, kind)
    else:
        open_mask, scale_m = _pupil_from_fits(sca, kind, pupil_bin)
        transmission = open_mask.astype(np.float64)
    n = transmission.shape[0]
    transmission.setflags(write=False)
    if scale_rule == "galsim":
        offsets = np.arange(n) - n // 2
        radius = np.hypot(offsets[None, :], offsets[:, None])
        binned_scale_m = DIAMETER_M / (2.0 * radius[transmission > 0].max())
    elif scale_rule == "official":
        # Matched on the binned mask the optics actually use: binning keeps a pixel open if any
        # sub-pixel is, which adds 1.2-1.4 % of open area along every edge, so a scale matched on
        # the unbinned mask would leave the simulated pupil that much too large.
        binned_scale_m = math.sqrt(official_clear_area_m2(sca, band) / float(transmission.sum()))
    else:
        binned_scale_m = scale_m * pupil_bin
    return Pupil(sca, kind, transmission, binned_scale_m)


@cache
def _zernike_table(sca: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    data = np.loadtxt(_data_dir() / f"Roman_Cycle-9_WFI_zim_zernikes_082623_{sca:02d}.txt")
    aberrations = np.zeros((5, 23))
    aberrations[:, 1:] = data[:, 5:]
    x = data[:, 1] / PIXEL_PITCH_MM
    y = data[:, 2] / PIXEL_PITCH_MM
    if sca % 3 != 0:
        # These SCAs are mounted rotated by 180 degrees relative to the field coordinates.
        x, y = -x, -y
    return aberrations, x + SCA_PIXELS / 2, y + SCA_PIXELS / 2


def field_points(sca: int) -> list[tuple[float, float]]:
    """Where the SCA's aberrations are given: its centre and four corners (pixels, inside 1-4088)."""
    _table, x, y = _zernike_table(check_sca(sca))
    return [(_clip_pixel(px), _clip_pixel(py)) for px, py in zip(x, y, strict=True)]


def _clip_pixel(value: float) -> float:
    return float(min(max(value, 1.0), SCA_PIXELS))


def aberrations(sca: int, position_pixels: tuple[float, float] | None = None) -> np.ndarray:
    """Noll Zernike coefficients (index 0 unused, 1..22) in waves at 1293 nm.

    Bilinear interpolation between the four corner field points, as GalSim does; piston, tip and
    tilt are zeroed because they only move the PSF.
    """
    sca = check_sca(sca)
    table, x, y = _zernike_table(sca)
    if position_pixels is None:
        position_pixels = (SCA_PIXELS / 2, SCA_PIXELS / 2)
    px, py = (float(v) for v in position_pixels)
    if not (np.isfinite(px) and np.isfinite(py)) or not (0 <= px <= SCA_PIXELS and 0 <= py <= SCA_PIXELS):
        raise InputError("position", f"position on the SCA must lie in [0, {SCA_PIXELS}] pixels, got {position_pixels!r}")
    corners = {}
    for i in range(1, 5):
        key = ("l" if x[i] < x[0] else "r") + ("l" if y[i] < y[0] else "u")
        corners[key] = table[i]
    fx = (px - x.min()) / (x.max() - x.min())
    fy = (py - y.min()) / (y.max() - y.min())
    result = (
        (1 - fx) * (1 - fy) * corners["ll"]
        + (1 - fx) * fy * corners["lu"]
        + fx * (1 - fy) * corners["rl"]
        + fx * fy * corners["ru"]
    )
    result[:4] = 0.0
    return result
