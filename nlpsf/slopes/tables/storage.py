"""The tables on disk: the ECSV (astropy, with units and metadata) and its binary companion (numpy).

``load_tables`` reads the companion (``slopes.npz``: the same numbers, read in milliseconds with
numpy alone) when its fingerprint matches the ECSV's, found by a regular expression over the ECSV's
YAML header so that astropy is not imported; otherwise it parses the ECSV with astropy. The
companion holds each spline's knot derivatives, not its coefficients (which doubled the file):
``SlopeTable`` builds the coefficients from them with numpy, bit for bit scipy's (``splines``).
``write_companion`` writes the companion of a merged table (``tablebuild`` writes the ECSV beside it).

Why both files ship: the ECSV is the published, human-readable copy (units, metadata), the one the
API serves (``tables.ecsv``) and the one the tests read as independent truth (``tests/shipped.py``),
and the companion is trusted only while its fingerprint matches it; the runtime reads one format,
the companion.
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
from .splines import knot_derivatives

#: Version of the binary companion's layout (2: knot derivatives instead of spline coefficients,
#: byte-shuffled columns).
COMPANION_FORMAT = 2


def shuffle_bytes(array: np.ndarray) -> np.ndarray:
    """``array``'s bytes regrouped by significance, (itemsize, *shape) uint8: lossless, and it
    deflates 10-20 % smaller (the exponent bytes of neighbouring values are alike), as HDF5's shuffle."""
    array = np.ascontiguousarray(array)
    planes = array.view(np.uint8).reshape(*array.shape, array.dtype.itemsize)
    return np.ascontiguousarray(np.moveaxis(planes, -1, 0))


def unshuffle_bytes(packed: np.ndarray, dtype: str) -> np.ndarray:
    """The array ``shuffle_bytes`` packed, bit for bit."""
    return np.ascontiguousarray(np.moveaxis(packed, 0, -1)).view(np.dtype(dtype))[..., 0]


def shipped_table_path() -> Path:
    return Path(str(resources.files("nlpsf") / "data" / "tables" / "slopes.ecsv"))


def field_table_path() -> Path:
    """The shipped tables at each SCA's four corner field points (``nlpsf solve --over-field``)."""
    return Path(str(resources.files("nlpsf") / "data" / "tables" / "field_slopes.ecsv.gz"))


def companion_path(path: Path) -> Path:
    """The binary companion of an ECSV table file (``.ecsv`` or gzipped ``.ecsv.gz``): the same
    numbers, read without astropy/scipy."""
    name = path.name.removesuffix(".gz").removesuffix(".ecsv")
    return path.with_name(name + ".npz")


META_KEYS = ("settings", "fingerprint", "method", "data_version", "code_version")


def write_companion(table, path: Path) -> Path:
    """Write the binary companion of a merged astropy table (written as ECSV to ``path``).

    Layout: ``meta`` (JSON text: the ECSV's metadata, column names, the data's dtype), and per
    (band, SCA) ``{band}_{sca}``: the float64 rows x columns (magnitude ascending), and
    ``{band}_{sca}_knots``: per slope column (``SLOPE_COLUMNS``) the spline's knot derivatives (flux
    ascending, ``splines.knot_derivatives``), each stored column by column through
    ``shuffle_bytes``; in a field-point file ``{band}_{sca}_p{point}``. The fingerprint ties it to
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
        knots = np.stack([knot_derivatives(flux[order], data[order, names.index(c)]) for c in SLOPE_COLUMNS])
        arrays[array_name(key)] = shuffle_bytes(data.T)
        arrays[f"{array_name(key)}_knots"] = shuffle_bytes(knots)
        keys.append(list(key))
    meta = {k: table.meta[k] for k in (*META_KEYS, "per_table") if k in table.meta}
    meta.update(
        columns=names,
        spline_columns=list(SLOPE_COLUMNS),
        keys=keys,
        companion_format=COMPANION_FORMAT,
        dtype=np.dtype(np.float64).str,
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


def table_from_arrays(key: tuple, data: np.ndarray, meta: dict, knots: np.ndarray | None = None) -> SlopeTable:
    names = meta["columns"]
    column = {name: data[:, k].copy() for k, name in enumerate(names) if name not in KEY_COLUMNS}
    info = meta["per_table"][table_key(*key)]
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
        knot_derivatives={} if knots is None else dict(zip(meta["spline_columns"], knots, strict=True)),
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

    Reads the binary companion (numpy alone, milliseconds) when it is there and matches the ECSV's
    fingerprint; otherwise parses the ECSV with astropy (and a table's splines are then solved with
    scipy when a column is first read).
    """
    source = Path(path) if path is not None else shipped_table_path()
    if not source.exists():
        raise InputError("tables", f"no table file named {source.name}; build one with `nlpsf tables build`")
    companion = companion_path(source)
    if companion.exists():
        archive = np.load(companion, allow_pickle=False)
        meta = json.loads(str(archive["meta"]))
        if meta.get("companion_format") == COMPANION_FORMAT and ecsv_fingerprint(source) == meta.get("fingerprint"):
            keys = [(str(k[0]), *map(int, k[1:])) for k in meta["keys"]]

            def read(key: tuple) -> SlopeTable:
                name, dtype = array_name(key), meta["dtype"]
                data, knots = (unshuffle_bytes(archive[n], dtype) for n in (name, f"{name}_knots"))
                return table_from_arrays(key, data.T, meta, knots)

            return TableSet(keys, public_meta(meta, source), read)
    return load_ecsv(source)


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
