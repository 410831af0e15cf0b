"""Slope tables over the field: the candidate Roman default scene, a grid of positions per SCA, and
interpolation across it.

The scene is the Roman default's (``nlpsf.request.presets``: its optics at the star's position,
the official pupil scale, a K0V star, jitter, charge diffusion, IPC, the background and the HLWAS
ramp), one table per grid node.

The grid. GalSim interpolates the Zernikes of an SCA *bilinearly* between its four corner field
points (``galsim.roman.roman_psfs._interp_aberrations_bilinear``, mirrored by
``roman.aberrations``), so the optics over an SCA are a smooth function of the fractional position
(fx, fy) on the square the corners span. A slope is a smooth but not bilinear function of the
Zernikes, so the tables sit on an n x n grid of pixel positions spanning the SCA (pixels 1 ... 4088
each axis, n odd so the centre is a node) and are interpolated across it by one of
:data:`SCHEMES`: ``bilinear`` (within the grid cell, GalSim's scheme for the Zernikes applied to the
slopes) or ``lagrange`` (the tensor-product polynomial through every node, biquadratic on 3 x 3).
``scripts/field_interpolation_error.py`` measures both against fresh simulations at random positions.

The runtime format is one ``.npz`` (numpy only): per (band, SCA) the node positions, each node's
magnitude grid, its slope columns in float32 and their error columns as 16-bit codes rounded up
(:func:`pack_errors`), and the metadata as JSON. Each (band, SCA) has its
own grid size n (``meta["tables"][key]["grid"]``), so a file can hold denser grids where the
field interpolation needs them (W146: 5 x 5, docs/field.md) and 3 x 3 elsewhere.

About 600 lines, kept as one module because the file format (its writer, reader and error codes)
and the reads across the grid share one layout of arrays; the nodes' splines are evaluated
together by ``nlpsf.slopes.tables.splines.evaluate_stacked_cubics``.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path

import numpy as np

from nlpsf import roman
from nlpsf.checks import InputError, check_integer

from .tables.splines import evaluate_stacked_cubics, stack_cubics

#: Interpolation schemes across the field grid.
SCHEMES: tuple[str, ...] = ("bilinear", "lagrange")
#: Grid sizes a build accepts (2: the corners only; odd sizes have the SCA centre as a node).
GRID_SIZES: tuple[int, ...] = (2, 3, 5, 7, 9)
#: The scene names a table build understands ("paper": the shipped tables' idealised scene).
TABLE_SCENES: tuple[str, ...] = ("paper", "roman")
#: Runtime format tag of a field-grid file (3: the error columns as 16-bit codes, :func:`pack_errors`;
#: read too: 2, every array float and byte-shuffled, ``tables.storage.shuffle_bytes``; 1, plain arrays).
FORMAT = "nlpsf-field-grid-3"
FORMATS_READ: tuple[str, ...] = ("nlpsf-field-grid-1", "nlpsf-field-grid-2", FORMAT)
#: Mantissa bits an error keeps in a -3 file (float16's 10): rounded up, an error grows by less than
#: 2**-10 = 9.8e-4 of itself and never shrinks.
ERROR_MANTISSA_BITS = 10
_DROPPED_BITS = 23 - ERROR_MANTISSA_BITS
#: The codes with a meaning of their own (every other code is a positive error): an exact zero,
#: an error too small for the array's 63 binades (kept exactly, float32, in the outliers), NaN.
_ZERO_CODE, _OUTLIER_CODE, _NAN_CODE = 0, 0xFFFE, 0xFFFF
_LARGEST_CODE = 0xFFFD


def _is_error_column(name: str) -> bool:
    return name.endswith(("_err", "_interp"))


def pack_errors(errors: np.ndarray) -> tuple[np.ndarray, int, np.ndarray]:
    """Non-negative float32 errors as uint16 codes rounded up: (codes, exponent offset, outliers).

    A code is a float32's bit pattern without its sign (an error is never negative) and with its
    mantissa rounded up to :data:`ERROR_MANTISSA_BITS` bits (the bit pattern of a positive float
    grows with its value, so rounding the integer up rounds the value up, carrying into the
    exponent), counted from an offset: 6 bits of exponent (63 binades) and 10 of mantissa, float16's
    mantissa with a wider exponent. float16 itself holds 30 normal binades; the errors of a grid span
    up to 67 (6e-18 to 1.2e3 in slope units in the 5-band rebuild: a leave-one-out estimate can be all but zero), so it
    would flush the smallest to zero or to a few bits. The 63 binades end at the array's largest
    error; an error below them (a negligible one, next to its standard error) is an outlier: code
    0xFFFE, its float32 kept exactly, in order. 0: an error of zero; 0xFFFF: NaN (padding)."""
    errors = np.asarray(errors, dtype=np.float32)
    finite = np.isfinite(errors)
    if np.any(np.isinf(errors)) or np.any(errors[finite] < 0):
        raise InputError("field grid", "errors must be finite and non-negative (or NaN padding) to be packed")
    bits = np.where(finite, errors, 0).view(np.uint32).astype(np.int64)
    rounded = (bits + (1 << _DROPPED_BITS) - 1) >> _DROPPED_BITS
    if np.any(rounded << _DROPPED_BITS >= 0x7F800000):
        raise InputError("field grid", "an error rounded up would overflow float32")
    positive = finite & (rounded > 0)
    offset = 0
    if positive.any():
        offset = max(int(rounded[positive].min()), int(rounded[positive].max()) - (_LARGEST_CODE - 1))
    outlier = positive & (rounded < offset)
    codes = np.where(positive, rounded - offset + 1, _ZERO_CODE)
    codes = np.where(outlier, _OUTLIER_CODE, codes)
    codes = np.where(finite, codes, _NAN_CODE)
    return codes.astype(np.uint16), offset, errors[outlier].astype(np.float32)


def unpack_errors(codes: np.ndarray, offset: int, outliers: np.ndarray | None = None) -> np.ndarray:
    """The float32 errors :func:`pack_errors` coded (each at or above the error packed)."""
    codes = np.asarray(codes, dtype=np.int64)
    coded = (codes >= 1) & (codes <= _LARGEST_CODE)
    bits = np.where(coded, (codes - 1 + int(offset)) << _DROPPED_BITS, 0)
    values = bits.astype(np.uint32).view(np.float32).copy()
    values[codes == _NAN_CODE] = np.nan
    outlier = codes == _OUTLIER_CODE
    if outlier.any():
        values[outlier] = outliers
    return values


def check_grid(n: int) -> int:
    check_integer(n, "grid", 2, max(GRID_SIZES))
    if n not in GRID_SIZES:
        raise InputError("grid", f"the field grid is n x n with n one of {', '.join(map(str, GRID_SIZES))}, got {n}")
    return int(n)


def grid_axis(n: int) -> np.ndarray:
    """Pixel coordinates of the n nodes along one axis (1 and 4088 included, centre for odd n)."""
    return np.linspace(1.0, float(roman.SCA_PIXELS), check_grid(n))


def grid_positions(n: int) -> list[tuple[int, int, tuple[float, float]]]:
    """Every node (i along x, j along y, (x, y) pixels) of the n x n grid, the same on every SCA."""
    axis = grid_axis(n)
    return [(i, j, (float(axis[i]), float(axis[j]))) for j in range(n) for i in range(n)]


# --- interpolation across the grid -----------------------------------------------------------


def _lagrange_weights(axis: np.ndarray, x: float) -> np.ndarray:
    weights = np.ones(axis.size)
    for k in range(axis.size):
        for m in range(axis.size):
            if m != k:
                weights[k] *= (x - axis[m]) / (axis[k] - axis[m])
    return weights


def _bilinear_weights(axis: np.ndarray, x: float) -> np.ndarray:
    weights = np.zeros(axis.size)
    k = int(np.clip(np.searchsorted(axis, x) - 1, 0, axis.size - 2))
    t = (x - axis[k]) / (axis[k + 1] - axis[k])
    weights[k], weights[k + 1] = 1.0 - t, t
    return weights


def weights(n: int, position: tuple[float, float], scheme: str = "lagrange") -> np.ndarray:
    """(n, n) weights [j (y), i (x)] of the grid nodes for a value at ``position`` (pixels)."""
    if scheme not in SCHEMES:
        raise InputError("scheme", f"must be one of {', '.join(SCHEMES)}, got {scheme!r}")
    axis = grid_axis(n)
    x, y = (float(v) for v in position)
    for v in (x, y):
        if not (1.0 <= v <= roman.SCA_PIXELS):
            raise InputError("position", f"position must lie in [1, {roman.SCA_PIXELS}] pixels, got {position!r}")
    rule = _lagrange_weights if scheme == "lagrange" else _bilinear_weights
    return np.outer(rule(axis, y), rule(axis, x))


def interpolate(values: np.ndarray, position: tuple[float, float], scheme: str = "lagrange") -> np.ndarray:
    """Interpolate node values ``values[j, i, ...]`` (j along y, i along x) to ``position``."""
    values = np.asarray(values, dtype=np.float64)
    n = values.shape[0]
    if values.shape[1] != n:
        raise InputError("values", f"need an n x n grid of values, got shape {values.shape}")
    w = weights(n, position, scheme)
    return np.tensordot(w, values, axes=([0, 1], [0, 1]))


# --- the runtime file ------------------------------------------------------------------------


#: Columns a field-grid file keeps per node (the slope columns of ``nlpsf.slopes.tables``, their standard
#: errors and their magnitude-interpolation error estimates).
def _slope_columns() -> list[str]:
    from .tables import COLUMN_METRICS, MODES

    return [f"{mode}_{metric}{suffix}" for metric in COLUMN_METRICS for mode in MODES for suffix in ("", "_err", "_interp")]


#: Field-interpolation error of an n x n Lagrange grid, as a fraction of the median |slope| over the
#: SCA's nodes (at that magnitude): the worst measured against fresh simulations where no resultant
#: saturates, rounded up (scripts/shipped_grid_error.py; docs/field.md). 3 x 3: 16 random positions
#: over the 8 bands (size 5.1e-4, e1 2.5e-2, e2 6.0e-3; the grid built before the K0V star and the
#: sky's local estimate). 5 x 5: 16 random positions per band with today's grid (2026-12-02, seed
#: 2026, ``--band B``): W146 4.4e-4, 5.4e-4, 3.3e-4; Z087 4.3e-4, 5.0e-4, 6.3e-4; Y106 4.2e-4, 3.3e-4,
#: 5.0e-4; K213 5.2e-4, 4.5e-4, 4.4e-4 (size, e1, e2); R062's own term below. FieldGrid.slope adds it
#: to the stated error.
FIELD_INTERPOLATION_BY_GRID: dict[int, dict[str, float]] = {
    3: {"size": 1e-3, "e1": 3e-2, "e2": 1e-2},
    5: {"size": 1e-3, "e1": 1e-3, "e2": 1e-3},
}
#: Where 16 random positions in one band (``--band B``) found a grid worse than the term above, that
#: band's worst, rounded up, replaces it (terms are only raised, never lowered here). 3 x 3 (before the
#: rebuild): R062 e1 5.7e-2, e2 5.9e-2; Z087 e1 7.1e-2, e2 6.0e-2; Y106 e2 2.6e-2; J129 e2 1.0e-2 (again
#: 1.0e-2 / 9.8e-3 with today's grid); W146 e2 1.1e-2. 5 x 5: R062 e1 1.2e-3, e2 1.4e-3. Elsewhere the
#: band's worst was within the term (today's H158 and F184 3 x 3: at most 4.4e-3 and 1.1e-3).
FIELD_INTERPOLATION_BY_BAND: dict[tuple[int, str], dict[str, float]] = {
    (3, "R062"): {"size": 1e-3, "e1": 6e-2, "e2": 6e-2},
    (3, "Z087"): {"size": 1e-3, "e1": 8e-2, "e2": 7e-2},
    (3, "Y106"): {"size": 1e-3, "e1": 3e-2, "e2": 3e-2},
    (3, "J129"): {"size": 1e-3, "e1": 3e-2, "e2": 2e-2},
    (3, "W146"): {"size": 1e-3, "e1": 3e-2, "e2": 2e-2},
    (5, "R062"): {"size": 1e-3, "e1": 2e-3, "e2": 2e-3},
}
#: The 3 x 3 term over all bands, under its earlier name.
FIELD_INTERPOLATION: dict[str, float] = FIELD_INTERPOLATION_BY_GRID[3]


def grid_residual_model(settings: dict) -> str | None:
    """The residual model a field grid's nodes were built with: their ``residual_nl`` setting; a grid built
    in the corrected state before the setting existed holds the earlier model, "per_read_beta"."""
    if settings.get("linearise_at", "beta0") != "corrected":
        return None
    return settings.get("residual_nl") or "per_read_beta"


def field_interpolation(n: int, band: str | None = None) -> dict[str, float]:
    """The measured field-interpolation term of an n x n grid in ``band``. A grid size not measured
    in that band takes the band's 3 x 3 term (a denser grid through the same nodes interpolates no
    worse), and a size never measured the 3 x 3 one."""
    n = int(n)
    if (n, band) in FIELD_INTERPOLATION_BY_BAND:
        return FIELD_INTERPOLATION_BY_BAND[(n, band)]
    if n == 3 or (n in FIELD_INTERPOLATION_BY_GRID and band in MEASURED_BANDS.get(n, ())):
        return FIELD_INTERPOLATION_BY_GRID[n]
    return FIELD_INTERPOLATION_BY_BAND.get((3, band), FIELD_INTERPOLATION_BY_GRID[3])


#: The bands each grid size's term was measured in (a 3 x 3 term holds for every band).
MEASURED_BANDS: dict[int, tuple[str, ...]] = {5: ("W146", "Z087", "Y106", "K213", "R062")}


#: The shipped field grid of the Roman default (``nlpsf tables build --scene roman --grid 3``, merged).
SHIPPED_NAME = "roman_field_grid.npz"


def shipped_grid_path() -> Path:
    from importlib import resources

    return Path(str(resources.files("nlpsf") / "data" / "tables" / SHIPPED_NAME))


@cache
def shipped_grid() -> FieldGrid | None:
    """The shipped Roman-default field grid, read once per process; None when the file is absent."""
    path = shipped_grid_path()
    return FieldGrid.load(path) if path.is_file() else None


def write_grid(
    tables: list, destination: Path | str, dtype=np.float32, provenance: dict | None = None, per_table: dict | None = None
) -> Path:
    """Pack per-node tables (``tablebuild.compute_table`` with a ``grid_node``) into one ``.npz``.

    ``provenance``: how the file was made (code commit, date, CPU time, ...), kept in its metadata;
    ``per_table``: more metadata per (band, SCA) key (``tablebuild.merge_field_grid``: the ramp's shift).

    Per (band, SCA): ``{key}/positions`` (n, n, 2), ``{key}/magnitude`` and ``{key}/flux`` (n, n, M)
    in float64 (M the longest node grid, NaN-padded; magnitudes are labels, flux the spline's
    abscissa) and ``{key}/values`` (n, n, M, C) in ``dtype`` for the slope columns.
    """
    columns = _slope_columns()
    groups: dict[tuple[str, int], list] = {}
    for t in tables:
        groups.setdefault((t.meta["band"], int(t.meta["sca"])), []).append(t)
    arrays: dict[str, np.ndarray] = {}
    meta: dict = {"format": FORMAT, "columns": columns, "tables": {}, "value_dtype": np.dtype(dtype).name}
    meta["provenance"] = dict(provenance or {})
    meta["provenance"]["cpu_s"] = float(sum(float(t.meta.get("cpu_s", 0.0)) for t in tables))
    for (band, sca), group in sorted(groups.items()):
        n = int(group[0].meta["grid_node"][0])
        if len(group) != n * n:
            raise InputError("tables", f"{band} SCA {sca}: {len(group)} node tables for a {n} x {n} grid")
        length = max(len(t) for t in group)
        magnitude = np.full((n, n, length), np.nan)
        flux = np.full((n, n, length), np.nan)
        values = np.full((n, n, length, len(columns)), np.nan)
        positions = np.zeros((n, n, 2))
        for t in group:
            _, i, j = t.meta["grid_node"]
            rows = len(t)
            magnitude[j, i, :rows] = t["magnitude"]
            flux[j, i, :rows] = t["flux_electrons"]
            values[j, i, :rows] = np.stack([np.asarray(t[c], dtype=np.float64) for c in columns], axis=-1)
            positions[j, i] = t.meta["position"]
        key = f"{band}_{sca:02d}"
        arrays[f"{key}/positions"] = positions
        arrays[f"{key}/magnitude"] = magnitude
        arrays[f"{key}/flux"] = flux
        arrays[f"{key}/values"] = values.astype(dtype)
        fingerprints = {t.meta["fingerprint"] for t in group}
        if len(fingerprints) != 1:
            raise InputError("tables", f"{band} SCA {sca}: node tables made with different settings {sorted(fingerprints)}")
        meta["tables"][key] = {
            "band": band,
            "sca": sca,
            "grid": n,
            "settings": group[0].meta["settings"],
            "fingerprint": group[0].meta["fingerprint"],
            "exptime_s": float(group[0].meta["exptime_s"]),
            "scene": group[0].meta.get("scene"),
            "code_version": group[0].meta.get("code_version"),
            "saturation_magnitude": [[None] * n for _ in range(n)],
            "cpu_s": [[None] * n for _ in range(n)],
        }
        meta["tables"][key].update((per_table or {}).get(key, {}))
        for t in group:
            _, i, j = t.meta["grid_node"]
            meta["tables"][key]["saturation_magnitude"][j][i] = float(t.meta["saturation_magnitude"])
            meta["tables"][key]["cpu_s"][j][i] = float(t.meta.get("cpu_s", float("nan")))
    return FieldGrid(meta, arrays).save(destination)


def merge_grids(base: FieldGrid, update: FieldGrid) -> FieldGrid:
    """``base`` with every (band, SCA) of ``update`` put in its place (a denser grid, a rebuild).

    Entries taken from ``update`` keep its provenance as their own (``conditions`` returns it), the
    file's provenance stays ``base``'s and lists the entries replaced. Both must hold float32 slopes
    with the same columns."""
    if base.meta["columns"] != update.meta["columns"] or base.meta["value_dtype"] != update.meta["value_dtype"]:
        raise InputError("field grid", "the two field grids hold different columns or value types")
    meta = json.loads(json.dumps(base.meta))
    arrays = dict(base.arrays)
    replaced = []
    for key, entry in update.meta["tables"].items():
        meta["tables"][key] = {**entry, "provenance": entry.get("provenance", update.meta.get("provenance", {}))}
        for part in ARRAY_PARTS:
            arrays[f"{key}/{part}"] = update.arrays[f"{key}/{part}"]
        replaced.append(key)
    provenance = meta.setdefault("provenance", {})
    provenance["replaced_entries"] = sorted({*provenance.get("replaced_entries", []), *replaced})
    provenance["cpu_s"] = float(sum(c for e in meta["tables"].values() for row in e["cpu_s"] for c in row if c is not None))
    return FieldGrid(meta, arrays)


#: Bytes of (entry, column, magnitudes) evaluations a grid keeps, least recently used dropped first
#: (a magnitude solve over a 5 x 5 SCA asks ~750 of them, 0.75 MB).
_NODE_VALUES_KEPT_BYTES = 32 * 2**20

#: The arrays a field-grid file holds per (band, SCA), ``{key}/{part}``.
ARRAY_PARTS: tuple[str, ...] = ("positions", "magnitude", "flux", "values")


@dataclass(frozen=True, eq=False)
class FieldGrid:
    """One field-grid file, read: slopes at any position and magnitude of its (band, SCA)s.

    The public questions a caller asks (the solver's): :meth:`covers` / :meth:`coverage` (which (band,
    SCA) it holds), :meth:`magnitude_range` (where every node has a value), :meth:`saturation_magnitude`
    (the ramp's limit at a position), :meth:`final_frame_saturation_magnitude` (fainter than which no
    resultant saturates), :meth:`slope` (value and standard error of a metric and mode at a
    position and magnitude) and :meth:`conditions` (the scene, exposure and beta0 the slopes are for:
    the grid answers at those only; the paper tables' beta-flux scaling does not hold for a scene with
    a background and a ramp's saturation, so no other exposure or beta0 is read from it)."""

    meta: dict
    arrays: dict
    _splines: dict = field(default_factory=dict, repr=False)
    _node_values: OrderedDict = field(default_factory=OrderedDict, repr=False)
    _node_values_bytes: list = field(default_factory=lambda: [0], repr=False)  # a frozen grid's one counter
    _node_values_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    @classmethod
    def load(cls, path: Path | str) -> FieldGrid:
        from .tables.storage import unshuffle_bytes

        with np.load(path) as data:
            arrays = {k: data[k] for k in data.files}
        meta = json.loads(arrays.pop("meta").tobytes().decode())
        if meta.get("format") not in FORMATS_READ:
            raise InputError("field grid", f"{path}: not a {FORMAT} file")
        for name, how in meta.pop("shuffled", {}).items():
            array = unshuffle_bytes(arrays[name], how["dtype"])
            arrays[name] = np.ascontiguousarray(np.moveaxis(array, 0, -1)) if how["columns_first"] else array
        for key, how in meta.pop("packed_errors", {}).items():
            # -3: the slope columns float32, the error columns coded; every caller sees (.., C) float32.
            slopes, codes = arrays.pop(f"{key}/values"), arrays.pop(f"{key}/error_codes")
            values = np.empty((*slopes.shape[:-1], len(meta["columns"])), dtype=np.float32)
            errors = [i for i, c in enumerate(meta["columns"]) if _is_error_column(c)]
            values[..., [i for i in range(values.shape[-1]) if i not in errors]] = slopes
            outliers = arrays.pop(f"{key}/error_outliers", None)  # written only where there are any
            values[..., errors] = unpack_errors(codes, how["offset"], outliers)
            arrays[f"{key}/values"] = values
        meta["format"] = FORMAT
        return cls(meta, arrays)

    def save(self, destination: Path | str) -> Path:
        """Write this grid as one ``.npz`` (:data:`FORMAT`), atomically: every array through
        ``tables.storage.shuffle_bytes`` (lossless; the values column by column), 20 % smaller
        deflated than the plain arrays, the slope columns as they are (float32, bit for bit) and the
        error columns as :func:`pack_errors`' codes (rounded up; 36 % smaller again)."""
        from .tables.storage import shuffle_bytes

        errors = [i for i, c in enumerate(self.meta["columns"]) if _is_error_column(c)]
        slopes = [i for i in range(len(self.meta["columns"])) if i not in errors]
        stored: dict[str, np.ndarray] = {}
        packed: dict[str, dict] = {}
        for name, array in self.arrays.items():
            if name.endswith("/values") and array.dtype == np.float32:
                key = name.removesuffix("/values")
                stored[name] = array[..., slopes]
                stored[f"{key}/error_codes"], offset, outliers = pack_errors(array[..., errors])
                if outliers.size:
                    stored[f"{key}/error_outliers"] = outliers
                packed[key] = {"offset": offset, "mantissa_bits": ERROR_MANTISSA_BITS}
            else:
                stored[name] = array
        columns_first = ("/values", "/error_codes")
        shuffled = {k: {"dtype": v.dtype.str, "columns_first": k.endswith(columns_first)} for k, v in stored.items()}
        arrays = {k: shuffle_bytes(np.moveaxis(v, -1, 0) if shuffled[k]["columns_first"] else v) for k, v in stored.items()}
        meta = {**self.meta, "format": FORMAT, "shuffled": shuffled, "packed_errors": packed}
        arrays["meta"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
        destination = Path(destination)
        destination.parent.mkdir(parents=True, exist_ok=True)
        temporary = destination.with_name(destination.name + ".tmp")
        with open(temporary, "wb") as handle:
            np.savez_compressed(handle, **arrays)
        temporary.replace(destination)
        return destination

    def keys(self) -> list[str]:
        return sorted(self.meta["tables"])

    @staticmethod
    def key(band: str, sca: int) -> str:
        return f"{roman.check_band(band)}_{int(roman.check_sca(sca)):02d}"

    def covers(self, band: str, sca: int) -> bool:
        """Whether this file holds the grid of (band, SCA)."""
        return self.key(band, sca) in self.meta["tables"]

    def coverage(self) -> list[tuple[str, int]]:
        """Every (band, SCA) held, in band order."""
        from nlpsf import defaults

        pairs = [(t["band"], int(t["sca"])) for t in self.meta["tables"].values()]
        return sorted(pairs, key=lambda p: (defaults.BANDS.index(p[0]), p[1]))

    def _entry(self, band: str, sca: int) -> tuple[str, dict]:
        key = self.key(band, sca)
        if key not in self.meta["tables"]:
            raise InputError("band", f"no field grid for {band} SCA {sca} in this file")
        return key, self.meta["tables"][key]

    def conditions(self, band: str, sca: int) -> dict:
        """What the slopes of (band, SCA) are for: settings (beta0, full well, centroids, state ...),
        exposure, scene, grid size, and the file's provenance."""
        _, entry = self._entry(band, sca)
        keep = ("band", "sca", "grid", "settings", "exptime_s", "scene", "code_version", "fingerprint")
        return {k: entry.get(k) for k in keep} | {"provenance": entry.get("provenance", self.meta.get("provenance", {}))}

    def magnitude_range(self, band: str, sca: int) -> tuple[float, float]:
        """(brightest, faintest) magnitude at which every node of (band, SCA) has a value [AB]."""
        key, _ = self._entry(band, sca)
        mags = self.arrays[f"{key}/magnitude"]
        return float(np.nanmax(np.nanmin(mags, axis=-1))), float(np.nanmin(np.nanmax(mags, axis=-1)))

    def saturation_magnitudes(self, band: str, sca: int) -> np.ndarray:
        """(n, n) [j (y), i (x)]: each node's saturation magnitude, the brightest star whose brightest
        pixel keeps the resultants a slope needs (the ramp's limit; the grid starts 1.5 mag brighter)."""
        _, entry = self._entry(band, sca)
        return np.array(entry["saturation_magnitude"], dtype=np.float64)

    def saturation_magnitude(self, band: str, sca: int, position: tuple[float, float], scheme: str = "lagrange") -> float:
        """The saturation magnitude at ``position`` (pixels), interpolated across the nodes."""
        return float(interpolate(self.saturation_magnitudes(band, sca), position, scheme))

    def final_frame_saturation_magnitude(
        self, band: str, sca: int, position: tuple[float, float], scheme: str = "lagrange"
    ) -> float | None:
        """Fainter than this no pixel loses a resultant: the brightest pixel's charge reaches the full
        well only at the exposure's end (the saturation magnitude plus the ramp's shift,
        ``Ramp.saturation_shift_mag``). Between :meth:`saturation_magnitude` and this, resultants
        saturate and the field interpolation is rougher (docs/field.md). None: not recorded."""
        _, entry = self._entry(band, sca)
        shift = entry.get("ramp_shift_mag")
        return None if shift is None else self.saturation_magnitude(band, sca, position, scheme) + float(shift)

    def _spline(self, key: str, column: str, j: int, i: int):
        """(flux range, cubic spline of column / flux in flux) of one node, as ``nlpsf.slopes.tables`` reads
        a table (not kept: :meth:`_stacked_splines` keeps every node's polynomial as arrays)."""
        from scipy.interpolate import CubicSpline

        index = self.meta["columns"].index(column)
        flux = self.arrays[f"{key}/flux"][j, i]
        values = self.arrays[f"{key}/values"][j, i, :, index].astype(np.float64)
        ok = np.isfinite(flux) & np.isfinite(values)
        f, q = flux[ok], values[ok] / flux[ok]
        order = np.argsort(f)
        return f[order][0], f[order][-1], CubicSpline(f[order], q[order])

    def node_values(self, band: str, sca: int, column: str, magnitude) -> np.ndarray:
        """(n, n, ...) values of ``column`` at ``magnitude`` (a number or an array) at every node: a
        cubic spline of column / flux in flux along each node's magnitude grid, as ``nlpsf.slopes.tables``
        reads a table; NaN outside a node's grid (no extrapolation across the field). Read-only and
        memoised: an answer over the SCA asks every node's value once per node it answers at."""
        key, _ = self._entry(band, sca)
        if column not in self.meta["columns"]:
            raise InputError("column", f"no column {column!r} in this field grid")
        m = np.asarray(magnitude, dtype=np.float64)
        memo_key = (key, column, m.shape, m.tobytes())
        with self._node_values_lock:  # the service answers from threads
            cached = self._node_values.get(memo_key)
            if cached is not None:
                self._node_values.move_to_end(memo_key)
                return cached
        out = self._evaluate_nodes(key, column, m)
        out.flags.writeable = False
        with self._node_values_lock:
            if memo_key not in self._node_values:
                self._node_values[memo_key] = out
                self._node_values_bytes[0] += out.nbytes
            while self._node_values_bytes[0] > _NODE_VALUES_KEPT_BYTES and len(self._node_values) > 1:
                self._node_values_bytes[0] -= self._node_values.popitem(last=False)[1].nbytes
        return out

    def _evaluate_nodes(self, key: str, column: str, m: np.ndarray) -> np.ndarray:
        first_flux, first_magnitude = self._references(key)
        n = first_flux.shape[0]
        # Each node's flux at m, from its own brightest row, one node at a time (numpy's scalar and
        # array powers may differ in the last bit; the grid's answers are kept bit for bit).
        target = np.empty((n, n, *m.shape))
        for j in range(n):
            for i in range(n):
                target[j, i] = first_flux[j, i] * 10 ** (-0.4 * (m - first_magnitude[j, i]))
        knots, coefficients, low, high = self._stacked_splines(key, column)
        extra = (slice(None), slice(None), *([None] * m.ndim))
        inside = (target >= low[extra] * (1 - 1e-12)) & (target <= high[extra] * (1 + 1e-12))
        clipped = np.clip(target, low[extra], high[extra])
        return np.where(inside, evaluate_stacked_cubics(knots, coefficients, clipped) * target, np.nan)

    def _stacked_splines(self, key: str, column: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every node's spline of ``column`` as padded arrays (``nlpsf.slopes.tables.splines.stack_cubics``) and each
        node's flux range (n, n)."""
        cached = self._splines.get((key, column, "stacked"))
        if cached is None:
            n = self.arrays[f"{key}/flux"].shape[0]
            splines = [[self._spline(key, column, j, i) for i in range(n)] for j in range(n)]
            knots, coefficients = stack_cubics([[spline for _, _, spline in row] for row in splines])
            low = np.array([[node_low for node_low, _, _ in row] for row in splines])
            high = np.array([[node_high for _, node_high, _ in row] for row in splines])
            cached = self._splines[(key, column, "stacked")] = (knots, coefficients, low, high)
        return cached

    def _references(self, key: str) -> tuple[np.ndarray, np.ndarray]:
        """(n, n) flux and magnitude of each node's brightest row: a magnitude becomes that node's
        flux from there (the node's own photometry)."""
        cached = self._splines.get((key, "references"))
        if cached is None:
            flux, mags = self.arrays[f"{key}/flux"], self.arrays[f"{key}/magnitude"]
            first = np.nanargmax(flux, axis=-1)[..., None]
            cached = np.take_along_axis(flux, first, -1)[..., 0], np.take_along_axis(mags, first, -1)[..., 0]
            self._splines[(key, "references")] = cached
        return cached

    def column_value(
        self,
        band: str,
        sca: int,
        position: tuple[float, float],
        magnitude: float,
        column: str = "bias_size",
        scheme: str = "lagrange",
    ) -> float:
        """One column at ``position`` (pixels) and ``magnitude``, interpolated across the field."""
        return float(interpolate(self.node_values(band, sca, column, magnitude), position, scheme))

    def slope(
        self,
        band: str,
        sca: int,
        position: tuple[float, float],
        metric: str,
        mode: str,
        magnitude,
        scheme: str = "lagrange",
    ) -> tuple[np.ndarray, np.ndarray]:
        """(slope, standard error) of ``metric`` ("size", "e1", "e2" or "e", the modulus) and ``mode``
        ("bias": d metric / d beta, "scatter": sigma metric / sigma beta) at ``position`` (pixels) and
        ``magnitude`` (a number or an array; NaN outside :meth:`magnitude_range`), per unit beta.

        The error combines, as ``nlpsf.slopes.tables`` does, each node's standard error over the centroid
        draws with its magnitude-interpolation estimate (in quadrature), carried across the field as
        sum |w_k| err_k (the nodes share their centroid draws, so their errors are correlated; the sum
        bounds the error for any correlation), and the field interpolation's measured error,
        :func:`field_interpolation` (of this grid size) x the median |slope| of the nodes, in quadrature."""
        if metric == "e":
            s1, e1 = self.slope(band, sca, position, "e1", mode, magnitude, scheme)
            s2, e2 = self.slope(band, sca, position, "e2", mode, magnitude, scheme)
            value = np.hypot(s1, s2)
            with np.errstate(invalid="ignore", divide="ignore"):
                error = np.where(value > 0, np.hypot(s1 * e1, s2 * e2) / value, np.hypot(e1, e2))
            return value, error
        from .tables import COLUMN_METRICS, MODES

        if metric not in COLUMN_METRICS:
            raise InputError("metric", f"must be one of {', '.join([*COLUMN_METRICS, 'e'])}, got {metric!r}")
        if mode not in MODES:
            raise InputError("mode", f"must be one of {', '.join(MODES)}, got {mode!r}")
        column = f"{mode}_{metric}"
        n = self._entry(band, sca)[1]["grid"]
        w = weights(n, position, scheme)
        values = self.node_values(band, sca, column, magnitude)
        statistical = self.node_values(band, sca, f"{column}_err", magnitude)
        errors = np.hypot(statistical, self.node_values(band, sca, f"{column}_interp", magnitude))
        value = np.tensordot(w, values, axes=([0, 1], [0, 1]))
        error = np.tensordot(np.abs(w), errors, axes=([0, 1], [0, 1]))
        field_term = field_interpolation(n, band)[metric] * np.median(np.abs(values), axis=(0, 1))
        return value, np.hypot(error, field_term)
