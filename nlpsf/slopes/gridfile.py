"""The Roman default's field-grid file: its runtime format (one ``.npz``, numpy only), writing
it from per-node tables and merging two, reading it back. ``nlpsf.slopes.fieldgrid`` reads the
slopes out of what :func:`read` returns.

Per (band, SCA): the node positions, each node's magnitude grid, its slope columns in float32 and
their error columns as 16-bit codes rounded up (:func:`pack_errors`), and the metadata as JSON.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from nlpsf.checks import InputError

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


#: Columns a field-grid file keeps per node (the slope columns of ``nlpsf.slopes.tables``, their standard
#: errors and their magnitude-interpolation error estimates).
def _slope_columns() -> list[str]:
    from .tables import COLUMN_METRICS, MODES

    return [f"{mode}_{metric}{suffix}" for metric in COLUMN_METRICS for mode in MODES for suffix in ("", "_err", "_interp")]


#: The arrays a field-grid file holds per (band, SCA), ``{key}/{part}``.
ARRAY_PARTS: tuple[str, ...] = ("positions", "magnitude", "flux", "values")


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
    return write(meta, arrays, destination)


def read(path: Path | str) -> tuple[dict, dict]:
    """(metadata, arrays) of a field-grid file, its errors unpacked and its arrays unshuffled."""
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
    return meta, arrays


def write(meta: dict, arrays_in: dict, destination: Path | str) -> Path:
    """Write a grid as one ``.npz`` (:data:`FORMAT`), atomically: every array through
    ``tables.storage.shuffle_bytes`` (lossless; the values column by column), 20 % smaller
    deflated than the plain arrays, the slope columns as they are (float32, bit for bit) and the
    error columns as :func:`pack_errors`' codes (rounded up; 36 % smaller again)."""
    from .tables.storage import shuffle_bytes

    errors = [i for i, c in enumerate(meta["columns"]) if _is_error_column(c)]
    slopes = [i for i in range(len(meta["columns"])) if i not in errors]
    stored: dict[str, np.ndarray] = {}
    packed: dict[str, dict] = {}
    for name, array in arrays_in.items():
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
    meta = {**meta, "format": FORMAT, "shuffled": shuffled, "packed_errors": packed}
    arrays["meta"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), dtype=np.uint8)
    destination = Path(destination)
    destination.parent.mkdir(parents=True, exist_ok=True)
    temporary = destination.with_name(destination.name + ".tmp")
    with open(temporary, "wb") as handle:
        np.savez_compressed(handle, **arrays)
    temporary.replace(destination)
    return destination
