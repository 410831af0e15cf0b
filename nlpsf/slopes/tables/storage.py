"""The tables on disk: one runtime file per table set (``.npz``, numpy alone), derived from an ECSV.

The runtime file holds every table's rows (float64) and, per slope column, its cubic spline as
scipy's public ``PPoly`` holds it: breakpoints ``x`` (flux ascending) and coefficients ``c`` (4,
rows - 1; highest power first), as ``CubicSpline(x, slope / x)`` returns them when the file is
written. Reading it needs numpy alone, and the splines are evaluated with numpy on those
coefficients (``splines.evaluate_cubic``): nothing of scipy at run time, public or private.

The shipped files are ``slopes.npz`` and ``field_slopes.npz``. The ECSVs they were derived from
(units and metadata, human-readable) are their sources in the repository and are not installed: a
user gets the same tables readable from ``nlpsf tables export`` (:func:`export_ecsv`) or the API's
``tables.ecsv`` / ``tables.csv``. A table file a user builds (``nlpsf tables build --merge-to
FILE.ecsv``) is written as both, the ECSV and its runtime file beside it; ``load_tables`` reads the
runtime file when its fingerprint matches the ECSV's (found by a regular expression over the
ECSV's YAML header, so that astropy is not imported), and otherwise parses the ECSV with astropy
(its splines then built with scipy's ``CubicSpline`` when first read).
"""

from __future__ import annotations

import gzip
import json
import re
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from nlpsf.checks import InputError

from .model import SLOPE_COLUMNS, SlopeTable, TableSet, table_key
from .splines import not_a_knot_spline

#: Version of the runtime file's layout (3: each slope column's spline as PPoly breakpoints and
#: coefficients; 2, knot derivatives, and 1, unshuffled coefficients, are no longer read: a table file
#: with such a companion is read from its ECSV).
COMPANION_FORMAT = 3


def shuffle_bytes(array: np.ndarray) -> np.ndarray:
    """``array``'s bytes regrouped by significance, (itemsize, *shape) uint8: lossless, and it
    deflates 10-20 % smaller (the exponent bytes of neighbouring values are alike), as HDF5's shuffle."""
    array = np.ascontiguousarray(array)
    planes = array.view(np.uint8).reshape(*array.shape, array.dtype.itemsize)
    return np.ascontiguousarray(np.moveaxis(planes, -1, 0))


def unshuffle_bytes(packed: np.ndarray, dtype: str) -> np.ndarray:
    """The array ``shuffle_bytes`` packed, bit for bit."""
    return np.ascontiguousarray(np.moveaxis(packed, 0, -1)).view(np.dtype(dtype))[..., 0]


def _tables_folder() -> Path:
    return Path(str(resources.files("nlpsf") / "data" / "tables"))


def shipped_table_path() -> Path:
    """The shipped tables at each SCA's centre: the runtime file (its source ECSV is not installed)."""
    return _tables_folder() / "slopes.npz"


def field_table_path() -> Path:
    """The shipped tables at each SCA's four corner field points (``nlpsf solve --over-field``)."""
    return _tables_folder() / "field_slopes.npz"


def companion_path(path: Path) -> Path:
    """The runtime file of an ECSV table file (``.ecsv`` or gzipped ``.ecsv.gz``): the same
    numbers and their splines, read without astropy/scipy."""
    name = path.name.removesuffix(".gz").removesuffix(".ecsv")
    return path.with_name(name + ".npz")


#: The ECSV metadata a runtime file keeps (with ``per_table``), so that an export gives it back.
META_KEYS = ("settings", "fingerprint", "method", "data_version", "code_version")
_EXPORTED_META = ("description", *META_KEYS, "per_table", "units")


def write_companion(table, path: Path) -> Path:
    """Write the runtime file of a merged astropy table (written, or to be exported, as ECSV to ``path``).

    Layout: ``meta`` (JSON text: the ECSV's metadata, column names, the data's dtype), and per
    (band, SCA) ``{band}_{sca}`` (in a field-point file ``{band}_{sca}_p{point}``): the float64 rows
    x columns (magnitude ascending); ``{band}_{sca}_x``: the splines' breakpoints, the flux ascending
    (rows,); ``{band}_{sca}_c``: per slope column (``SLOPE_COLUMNS``, in ``meta["spline_columns"]``'s
    order) the coefficients of scipy's ``CubicSpline(x, column / x)``, (columns, 4, rows - 1) -- a
    ``PPoly(c[k], x)``. Every array is stored through ``shuffle_bytes``. The fingerprint ties it to
    the ECSV it came from.
    """
    names = [n for n in table.colnames if n not in KEY_COLUMNS]
    arrays: dict[str, np.ndarray] = {}
    keys = []
    for key, rows in groups(table):
        data = np.column_stack([np.asarray(table[n][rows], dtype=np.float64) for n in names])
        data = data[np.argsort(data[:, names.index("magnitude")])]
        flux = data[:, names.index("flux_electrons")]
        order = np.argsort(flux)
        splines = [not_a_knot_spline(flux[order], data[order, names.index(c)]) for c in SLOPE_COLUMNS]
        if not all(np.array_equal(x, flux[order]) for x, _ in splines):
            raise ArithmeticError(f"{key}: a spline's breakpoints are not the table's flux")
        arrays[array_name(key)] = shuffle_bytes(data.T)
        arrays[f"{array_name(key)}_x"] = shuffle_bytes(splines[0][0])
        arrays[f"{array_name(key)}_c"] = shuffle_bytes(np.stack([c for _, c in splines]))
        keys.append(list(key))
    meta = {k: table.meta[k] for k in _EXPORTED_META if k in table.meta}
    meta.update(
        columns=names,
        spline_columns=list(SLOPE_COLUMNS),
        keys=keys,
        companion_format=COMPANION_FORMAT,
        dtype=np.dtype(np.float64).str,
        source=Path(path).name,
        ecsv_columns=[[n, table[n].dtype.str] for n in table.colnames],
    )
    destination = companion_path(Path(path))
    temporary = destination.with_name(destination.name + ".tmp.npz")
    np.savez_compressed(temporary, meta=np.array(json.dumps(meta)), **arrays)
    temporary.replace(destination)
    return destination


#: Columns that say which table a row belongs to.
KEY_COLUMNS = ("band", "sca", "field_point")


def groups(table) -> list[tuple[tuple, np.ndarray]]:
    """(key, row mask) of every table in a merged file: (band, SCA) or (band, SCA, field point)."""
    columns = [np.asarray(table["band"]).astype(str), np.asarray(table["sca"], dtype=int)]
    if "field_point" in table.colnames:
        columns.append(np.asarray(table["field_point"], dtype=int))
    labels = np.rec.fromarrays(columns)
    keys, inverse = np.unique(labels, return_inverse=True)
    out = [((str(key[0]), *(int(v) for v in tuple(key)[1:])), inverse.ravel() == k) for k, key in enumerate(keys)]
    return sorted(out, key=lambda item: item[0])


def array_name(key: tuple) -> str:
    return "_".join(str(part) if k < 2 else f"p{part}" for k, part in enumerate(key))


def table_from_arrays(
    key: tuple, data: np.ndarray, meta: dict, breaks: np.ndarray | None = None, coefficients: np.ndarray | None = None
) -> SlopeTable:
    names = meta["columns"]
    column = {name: data[:, k].copy() for k, name in enumerate(names) if name not in KEY_COLUMNS}
    info = meta["per_table"][table_key(*key)]
    splines = {} if coefficients is None else {n: (breaks, c) for n, c in zip(meta["spline_columns"], coefficients, strict=True)}
    return SlopeTable(
        band=key[0],
        sca=key[1],
        magnitudes=column["magnitude"],
        flux_electrons=column["flux_electrons"],
        peak_electrons=column["peak_electrons"],
        columns={n: v for n, v in column.items() if n.startswith(("bias_", "scatter_"))},
        settings=dict(meta["settings"]),
        saturation_magnitude=float(info["saturation_magnitude"]),
        peak_fraction=float(info["peak_fraction"]),
        splines=splines,
        field_point=int(key[2]) if len(key) > 2 else None,
        position=tuple(float(v) for v in info["position"]) if "position" in info else None,
    )


def public_meta(meta: dict, source: Path) -> dict:
    out = {k: meta[k] for k in META_KEYS if k in meta}
    # The file's name only: a server must not disclose where it is installed.
    out["source"] = source.name
    return out


@lru_cache(maxsize=4)
def load_tables(path: str | None = None) -> TableSet:
    """Open a table file (the shipped one by default). Cached: the calculator never re-reads.

    ``path``: a runtime file (``.npz``, numpy alone, milliseconds), or an ECSV, read through its
    runtime file when that is beside it and matches the ECSV's fingerprint, and otherwise parsed
    with astropy (a table's splines are then built with scipy when a column is first read).
    """
    source = Path(path) if path is not None else shipped_table_path()
    if not source.exists():
        raise InputError("tables", f"no table file named {source.name}; build one with `nlpsf tables build`")
    if source.suffix == ".npz":
        tableset = read_runtime(source)
        if tableset is None:
            raise InputError("tables", f"{source.name} is not a slope-table file of format {COMPANION_FORMAT}")
        return tableset
    companion = companion_path(source)
    if companion.exists():
        tableset = read_runtime(companion, ecsv_fingerprint(source), source)
        if tableset is not None:
            return tableset
    return load_ecsv(source)


def read_runtime(path: Path, fingerprint: str | None = None, source: Path | None = None) -> TableSet | None:
    """The tables of a runtime file; None if it is of another format or (``fingerprint`` given)
    was not derived from that ECSV. ``source``: the file named in the tables' metadata."""
    archive = np.load(path, allow_pickle=False)
    meta = json.loads(str(archive["meta"]))
    if meta.get("companion_format") != COMPANION_FORMAT:
        return None
    if fingerprint is not None and fingerprint != meta.get("fingerprint"):
        return None
    keys = [(str(k[0]), *map(int, k[1:])) for k in meta["keys"]]

    def read(key: tuple) -> SlopeTable:
        name, dtype = array_name(key), meta["dtype"]
        data, breaks, coefficients = (unshuffle_bytes(archive[n], dtype) for n in (name, f"{name}_x", f"{name}_c"))
        return table_from_arrays(key, data.T, meta, breaks, coefficients)

    return TableSet(keys, public_meta(meta, source or path), read)


def ecsv_fingerprint(path: Path) -> str | None:
    """The ``fingerprint`` in an ECSV file's YAML header, read without parsing the file."""
    pattern = re.compile(r"^#\s*-?\s*\{?\s*fingerprint:\s*['\"]?([0-9a-f]+)")
    opener = gzip.open if path.name.endswith(".gz") else open
    with opener(path, "rt") as handle:
        for line in handle:
            if not line.startswith("#"):
                break
            match = pattern.match(line)
            if match:
                return match.group(1)
    return None


def load_ecsv(source: Path) -> TableSet:
    from astropy.table import Table

    table = Table.read(source, format="ascii.ecsv")
    per_table = table.meta["per_table"]
    names = [n for n in table.colnames if n not in KEY_COLUMNS]
    meta: dict[str, Any] = {k: table.meta[k] for k in META_KEYS if k in table.meta}
    meta.update(columns=names, per_table=per_table)
    out = {}
    for key, rows in groups(table):
        key = (str(key[0]), *map(int, key[1:]))
        data = np.column_stack([np.asarray(table[n][rows], dtype=np.float64) for n in names])
        data = data[np.argsort(data[:, names.index("magnitude")])]
        out[key] = table_from_arrays(key, data, meta)
    return TableSet(list(out), public_meta(meta, source), out.__getitem__)


def export_ecsv(destination: Path | str, path: Path | str | None = None) -> Path:
    """Write a runtime table file (the shipped centre tables by default) as the ECSV it was derived
    from: the same rows, columns, types and metadata (astropy; gzipped when ``destination`` ends in
    ``.gz``, with no time stamp). ``nlpsf tables export``."""
    from astropy.table import Table

    runtime = Path(path) if path is not None else shipped_table_path()
    archive = np.load(runtime, allow_pickle=False)
    meta = json.loads(str(archive["meta"]))
    if meta.get("companion_format") != COMPANION_FORMAT or "ecsv_columns" not in meta:
        raise InputError("tables", f"{runtime.name} is not a slope-table file of format {COMPANION_FORMAT}")
    blocks: dict[str, list[np.ndarray]] = {name: [] for name, _ in meta["ecsv_columns"]}
    for key in meta["keys"]:
        data = unshuffle_bytes(archive[array_name(key)], meta["dtype"]).T
        named = {"band": np.full(len(data), key[0]), "sca": np.full(len(data), key[1])}
        if len(key) > 2:
            named["field_point"] = np.full(len(data), key[2])
        named.update((name, data[:, k]) for k, name in enumerate(meta["columns"]))
        for name in blocks:
            blocks[name].append(named[name])
    types = dict(meta["ecsv_columns"])
    columns = [np.concatenate(blocks[name]).astype(types[name]) for name in blocks]
    table = Table(columns, names=list(blocks), meta={k: meta[k] for k in _EXPORTED_META if k in meta})
    return write_ecsv(table, destination)


def write_ecsv(table, destination: Path | str) -> Path:
    """``table`` (astropy) written as ECSV, gzipped where the name ends in ``.gz`` (astropy reads it
    as it is) with no time stamp, so that equal tables give equal bytes."""
    import io

    destination = Path(destination)
    destination.parent.mkdir(parents=True, exist_ok=True)
    if destination.name.endswith(".gz"):
        text = io.StringIO()
        table.write(text, format="ascii.ecsv")
        with open(destination, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb", mtime=0, filename="") as packed:
            packed.write(text.getvalue().encode())
    else:
        table.write(destination, format="ascii.ecsv", overwrite=True)
    return destination
