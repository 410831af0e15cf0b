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

The file (``nlpsf.slopes.gridfile``: one ``.npz``, numpy only) holds per (band, SCA) the node
positions, each node's magnitude grid and its slope columns. Each (band, SCA) has its own grid size
n (``meta["tables"][key]["grid"]``), so a file can hold denser grids where the field interpolation
needs them (W146: 5 x 5, docs/field.md) and 3 x 3 elsewhere. :class:`FieldGrid` reads the slopes
out of it: each node's not-a-knot cubics built with numpy when a (band, SCA) is first read, and
evaluated for every node at once (``nlpsf.slopes.tables.splines``).
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from functools import cache, lru_cache
from pathlib import Path

import numpy as np

from nlpsf import roman
from nlpsf.checks import InputError, check_integer

from . import gridcubics, gridfile

#: Interpolation schemes across the field grid.
SCHEMES: tuple[str, ...] = ("bilinear", "lagrange")
#: Grid sizes a build accepts (2: the corners only; odd sizes have the SCA centre as a node).
GRID_SIZES: tuple[int, ...] = (2, 3, 5, 7, 9)
#: The scene names a table build understands ("paper": the shipped tables' idealised scene).
TABLE_SCENES: tuple[str, ...] = ("paper", "roman")


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
    """(n, n) weights [j (y), i (x)] of the grid nodes for a value at ``position`` (pixels); read-only."""
    return _weights(int(n), tuple(float(v) for v in position), scheme)


@lru_cache(maxsize=4096)
def _weights(n: int, position: tuple[float, ...], scheme: str) -> np.ndarray:
    if scheme not in SCHEMES:
        raise InputError("scheme", f"must be one of {', '.join(SCHEMES)}, got {scheme!r}")
    axis = grid_axis(n)
    x, y = (float(v) for v in position)
    for v in (x, y):
        if not (1.0 <= v <= roman.SCA_PIXELS):
            raise InputError("position", f"position must lie in [1, {roman.SCA_PIXELS}] pixels, got {position!r}")
    rule = _lagrange_weights if scheme == "lagrange" else _bilinear_weights
    out = np.outer(rule(axis, y), rule(axis, x))
    out.flags.writeable = False
    return out


def interpolate(values: np.ndarray, position: tuple[float, float], scheme: str = "lagrange") -> np.ndarray:
    """Interpolate node values ``values[j, i, ...]`` (j along y, i along x) to ``position``."""
    values = np.asarray(values, dtype=np.float64)
    n = values.shape[0]
    if values.shape[1] != n:
        raise InputError("values", f"need an n x n grid of values, got shape {values.shape}")
    w = weights(n, position, scheme)
    return contract(w, values)


def contract(w: np.ndarray, values: np.ndarray) -> np.ndarray:
    """sum over the nodes of ``w[j, i] values[j, i, ...]``: ``np.tensordot(w, values, axes=([0, 1],
    [0, 1]))``'s own product (one BLAS call on the same reshaped arrays), without its overhead."""
    return np.dot(w.reshape(1, -1), values.reshape(w.size, -1)).reshape(values.shape[2:])


def node_median(values: np.ndarray) -> np.ndarray:
    """``np.median(values, axis=(0, 1))`` to the last bit (the middle one of the sorted nodes, or the
    mean of the middle two; NaN where a node is NaN), without its overhead."""
    flat = np.sort(values.reshape(values.shape[0] * values.shape[1], *values.shape[2:]), axis=0)
    half = flat.shape[0] // 2
    middle = flat[half] if flat.shape[0] % 2 else (flat[half - 1] + flat[half]) / 2
    return np.where(np.isnan(flat[-1]), np.nan, middle)[()]


# --- the field interpolation's error -----------------------------------------------------------


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


#: Bytes of (entry, column, magnitudes) evaluations a grid keeps, least recently used dropped first
#: (a magnitude solve over a 5 x 5 SCA asks ~750 of them, 0.75 MB).
_NODE_VALUES_KEPT_BYTES = 32 * 2**20


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
    _saturation: dict = field(default_factory=dict, repr=False)  # saturation magnitude by position

    @classmethod
    def load(cls, path: Path | str) -> FieldGrid:
        """A field-grid file read (``gridfile.read``: every format in ``gridfile.FORMATS_READ``)."""
        return cls(*gridfile.read(path))

    def save(self, destination: Path | str) -> Path:
        """This grid written as one ``.npz`` in ``gridfile.FORMAT``, atomically (``gridfile.write``)."""
        return gridfile.write(self.meta, self.arrays, destination)

    def keys(self) -> list[str]:
        return sorted(self.meta["tables"])

    @staticmethod
    def key(band: str, sca: int) -> str:
        # A key, not a check: the request was validated where it came in; an unknown band is no entry.
        return f"{str(band).upper()}_{int(sca):02d}"

    def covers(self, band: str, sca: int) -> bool:
        """Whether this file holds the grid of (band, SCA)."""
        return self.key(band, sca) in self.meta["tables"]

    def coverage(self) -> list[tuple[str, int]]:
        """Every (band, SCA) held, in band order."""
        from nlpsf import defaults

        pairs = [(t["band"], int(t["sca"])) for t in self.meta["tables"].values()]
        return sorted(pairs, key=lambda p: (defaults.BANDS.index(p[0]), p[1]))

    def _entry(self, band: str, sca: int) -> tuple[str, dict]:
        # A request's band and SCA were checked where it was read: look up first, check only on a miss.
        found = self._splines.get(("entry", band, sca))
        if found is not None:
            return found
        key = f"{band}_{sca:02d}" if isinstance(band, str) and isinstance(sca, int) else None
        entry = self.meta["tables"].get(key)
        if entry is not None:
            self._splines[("entry", band, sca)] = key, entry
            return key, entry
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
        cached = self._splines.get((key, "magnitude_range"))
        if cached is None:
            mags = self.arrays[f"{key}/magnitude"]
            cached = float(np.nanmax(np.nanmin(mags, axis=-1))), float(np.nanmin(np.nanmax(mags, axis=-1)))
            self._splines[(key, "magnitude_range")] = cached
        return cached

    def node_positions(self, band: str, sca: int) -> tuple[tuple[float, float], ...] | None:
        """Every node's (x, y) pixels of (band, SCA), row by row (None: not held), read once."""
        key = f"{band}_{sca:02d}"
        cached = self._splines.get((key, "positions"))
        if cached is None and f"{key}/positions" in self.arrays:
            cached = tuple((float(x), float(y)) for x, y in self.arrays[f"{key}/positions"].reshape(-1, 2))
            self._splines[(key, "positions")] = cached
        return cached

    def saturation_magnitudes(self, band: str, sca: int) -> np.ndarray:
        """(n, n) [j (y), i (x)]: each node's saturation magnitude, the brightest star whose brightest
        pixel keeps the resultants a slope needs (the ramp's limit; the grid starts 1.5 mag brighter)."""
        key, entry = self._entry(band, sca)
        cached = self._splines.get((key, "saturation_magnitude"))
        if cached is None:
            cached = np.array(entry["saturation_magnitude"], dtype=np.float64)
            cached.flags.writeable = False
            self._splines[(key, "saturation_magnitude")] = cached
        return cached

    def saturation_magnitude(self, band: str, sca: int, position: tuple[float, float], scheme: str = "lagrange") -> float:
        """The saturation magnitude at ``position`` (pixels), interpolated across the nodes (kept: an
        answer asks at its position for its limits, and for whether it lies between them, again)."""
        memo_key = (band, sca, *position, scheme)
        cached = self._saturation.get(memo_key)
        if cached is None:
            cached = float(interpolate(self.saturation_magnitudes(band, sca), position, scheme))
            if len(self._saturation) >= 4096:
                self._saturation.clear()
            self._saturation[memo_key] = cached
        return cached

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
        """(flux range, scipy's cubic spline of column / flux in flux) of one node, as
        ``nlpsf.slopes.tables`` reads a table: the reference :meth:`_stacked_splines` equals (the
        tests compare them; the grid itself builds its nodes' cubics with numpy)."""
        from scipy.interpolate import CubicSpline

        f, q = gridcubics.node_series(self, key, self.meta["columns"].index(column), j, i)
        return f[0], f[-1], CubicSpline(f, q)

    def node_values(self, band: str, sca: int, column: str, magnitude) -> np.ndarray:
        """(n, n, ...) values of ``column`` at ``magnitude`` (a number or an array) at every node: a
        cubic spline of column / flux in flux along each node's magnitude grid, as ``nlpsf.slopes.tables``
        reads a table; NaN outside a node's grid (no extrapolation across the field). Read-only and
        memoised: an answer over the SCA asks every node's value once per node it answers at."""
        return self.columns_node_values(band, sca, (column,), magnitude)[0]

    def columns_node_values(self, band: str, sca: int, columns, magnitude) -> list[np.ndarray]:
        """:meth:`node_values` of several columns (a slope and its errors: each node's flux at the
        magnitude found once, the columns that share their knots read together; the same numbers)."""
        key, _ = self._entry(band, sca)
        m = np.asarray(magnitude, dtype=np.float64)
        shape, at = m.shape, m.tobytes()
        memo_keys = [(key, column, shape, at) for column in columns]
        with self._node_values_lock:  # the service answers from threads
            found = [self._node_values.get(memo_key) for memo_key in memo_keys]
            for memo_key, cached in zip(memo_keys, found, strict=True):
                if cached is not None:
                    self._node_values.move_to_end(memo_key)
        missing = [k for k, cached in enumerate(found) if cached is None]
        if not missing:
            return found  # a column is kept only once read: each is one of the grid's
        for k in missing:
            if columns[k] not in self.meta["columns"]:
                raise InputError("column", f"no column {columns[k]!r} in this field grid")
        computed = self._evaluate_nodes(key, [columns[k] for k in missing], m)
        with self._node_values_lock:
            for k, out in zip(missing, computed, strict=True):
                out.flags.writeable = False
                found[k] = out
                if memo_keys[k] not in self._node_values:
                    self._node_values[memo_keys[k]] = out
                    self._node_values_bytes[0] += out.nbytes
            while self._node_values_bytes[0] > _NODE_VALUES_KEPT_BYTES and len(self._node_values) > 1:
                self._node_values_bytes[0] -= self._node_values.popitem(last=False)[1].nbytes
        return found

    def values_at_nodes(self, band: str, sca: int, column: str, magnitudes) -> np.ndarray:
        """(n, n) each node's ``column`` at its own magnitude ``magnitudes[j, i]`` (any shape of n x n
        numbers): bit for bit what :meth:`node_values` gives at that node for that one magnitude
        (NaN outside the node's grid)."""
        return self.columns_at_nodes(band, sca, (column,), magnitudes)[0]

    def columns_at_nodes(self, band: str, sca: int, columns, magnitudes) -> list[np.ndarray]:
        """:meth:`values_at_nodes` of several columns at once (each node's flux at its magnitude found
        once). ``magnitudes`` of n x n x k numbers (node by node, k each): every node at its own k
        magnitudes, (n, n, k) each, in one read (the numbers of k reads)."""
        key, _ = self._entry(band, sca)
        m = np.asarray(magnitudes, dtype=np.float64)
        n = self._reference_floats(key)[2]
        return self._read_at(key, columns, m.reshape(-1).tolist(), m.size // (n * n))

    def _read_at(self, key: str, columns, magnitudes: list[float], per_node: int = 1) -> list[np.ndarray]:
        """Node k's columns at its own ``magnitudes[k]`` (``per_node`` > 1: at its own ``per_node``
        magnitudes from ``magnitudes[k * per_node]`` on): its flux there from its own brightest row
        by a scalar power (Python's float power is C's ``pow``, as numpy's scalar one: the same numbers)."""
        flux, reference, n = self._reference_floats(key)
        if per_node == 1:
            target = np.array([f * 10 ** (-0.4 * (m - r)) for f, m, r in zip(flux, magnitudes, reference, strict=True)])
            return self._read(key, columns, target.reshape(n, n), (slice(None), slice(None)))
        if len(magnitudes) != per_node * len(flux):
            raise ValueError(f"{len(magnitudes)} magnitudes for {len(flux)} nodes")
        nodes = enumerate(zip(flux, reference, strict=True))
        target = np.array([f * 10 ** (-0.4 * (magnitudes[k * per_node + j] - r)) for k, (f, r) in nodes for j in range(per_node)])
        return self._read(key, columns, target.reshape(n, n, per_node), (slice(None), slice(None), None))

    def slopes_at_nodes(self, band: str, sca: int, metric: str, mode: str, magnitudes) -> tuple[np.ndarray, np.ndarray]:
        """(slope, standard error), each (n, n): node k's at its own magnitude ``magnitudes[k]`` as
        :meth:`slope` gives them at that node's position for that one magnitude (the nodes'
        interpolation weights are 0 and 1 there), every node at once (a number: every node at that
        one magnitude; n x n x k numbers: each node at its own k magnitudes, (n, n, k) each, as k
        reads give them, read together). The field-interpolation term
        (the median over the nodes) is read from one evaluation of every node at every magnitude
        asked, which can differ from reading each magnitude alone in the last bit. NaN where a node
        is outside its grid."""
        components = ("e1", "e2") if metric == "e" else (metric,)
        n = self._entry(band, sca)[1]["grid"]
        names = [f"{mode}_{c}{part}" for c in components for part in ("", "_err", "_interp")]
        m = np.asarray(magnitudes, dtype=np.float64)
        if m.ndim == 0:  # one magnitude for every node (as the same n x n magnitudes are read)
            read = self.columns_node_values(band, sca, names, m)
            everywhere, where = read[::3], None
        else:
            m = m.reshape(n, n, -1) if m.size > n * n else m.reshape(n, n)  # (n, n, k): k magnitudes at each node
            distinct, where = np.unique(m, return_inverse=True)
            if distinct.size == 1 and m.ndim == 2:  # one magnitude: every node's values there, memoised (the same numbers)
                read = self.columns_node_values(band, sca, names, distinct[0])
                everywhere, where = read[::3], None
            else:
                read = self.columns_at_nodes(band, sca, names, m)
                everywhere, where = self.columns_node_values(band, sca, names[::3], distinct), where.reshape(m.shape)
        out = []
        for c, component in enumerate(components):  # each component's slope and error (the columns read together)
            values, statistical, interpolation = read[3 * c : 3 * c + 3]
            median = node_median(np.abs(everywhere[c]))
            field_term = field_interpolation(n, band)[component] * (median if where is None else median[where])
            out.append((values, np.hypot(np.hypot(statistical, interpolation), field_term)))
        if metric != "e":
            return out[0]
        (s1, e1), (s2, e2) = out
        value = np.hypot(s1, s2)
        with np.errstate(invalid="ignore", divide="ignore"):
            error = np.where(value > 0, np.hypot(s1 * e1, s2 * e2) / value, np.hypot(e1, e2))
        return value, error

    def _evaluate_nodes(self, key: str, columns: list[str], m: np.ndarray) -> list[np.ndarray]:
        if m.ndim == 0:  # one magnitude: each node's scalar power, as a node at its own magnitude is read
            return self._read_at(key, columns, [float(m)] * len(self._reference_floats(key)[0]))
        first_flux, first_magnitude = self._references(key)
        extra = (slice(None), slice(None), *([None] * m.ndim))
        # Each node's flux at every m, from its own brightest row: array powers, element for element
        # those of the node-by-node loop they replace (numpy's scalar and array powers may differ in
        # the last bit, one array's elements and another's do not: test_shipped_field_grid.py reads each node alone).
        target = first_flux[extra] * 10 ** (-0.4 * (m[None, None] - first_magnitude[extra]))
        return self._read(key, columns, target, extra)

    def _read(self, key: str, columns, target: np.ndarray, extra: tuple) -> list[np.ndarray]:
        """Every column's values at the nodes' fluxes ``target`` (n, n, ...; ``extra`` spreads a node's
        flux range over the rest), NaN outside a node's range; the columns sharing knots read together."""
        groups = self._splines.get((key, tuple(columns), "groups"))
        if groups is None:
            groups = gridcubics.prepare([self._stacked_splines(key, column) for column in columns])
            self._splines[(key, tuple(columns), "groups")] = groups
        return gridcubics.read(groups, len(columns), target, extra)

    def _stacked_splines(self, key: str, column: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Every node's cubic of ``column`` as padded arrays (knots (n, n, L), +inf past a node's last;
        coefficients (4, n, n, L - 1), zero past its last interval: ``splines.evaluate_stacked_cubics``' layout)
        and each node's flux range (n, n). Built with numpy for every column of the (band, SCA) at
        once, as its first answer asks for one (``splines.not_a_knot_coefficients``: scipy's not-a-knot
        CubicSpline, bit for bit; each row's arithmetic is its own, so the columns built together are
        built alike, and one pass costs about what a column's own did)."""
        cached = self._splines.get((key, column, "stacked"))
        if cached is None:
            family = list(self.meta["columns"]) if column in self.meta["columns"] else [column]
            for name, stacked in zip(family, gridcubics.build_stacked(self, key, family), strict=True):
                self._splines[(key, name, "stacked")] = stacked
            cached = self._splines[(key, column, "stacked")]
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

    def _reference_floats(self, key: str) -> tuple[list[float], list[float], int]:
        """:meth:`_references` flattened to Python floats, and n."""
        cached = self._splines.get((key, "reference floats"))
        if cached is None:
            flux, magnitude = self._references(key)
            cached = flux.reshape(-1).tolist(), magnitude.reshape(-1).tolist(), int(flux.shape[0])
            self._splines[(key, "reference floats")] = cached
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
        column = self._column(metric, mode)
        n = self._entry(band, sca)[1]["grid"]
        w = weights(n, position, scheme)
        values, statistical, interpolation = self.columns_node_values(
            band, sca, (column, f"{column}_err", f"{column}_interp"), magnitude
        )
        errors = np.hypot(statistical, interpolation)
        value = contract(w, values)
        error = contract(np.abs(w), errors)
        field_term = field_interpolation(n, band)[metric] * node_median(np.abs(values))
        return value, np.hypot(error, field_term)

    def value(self, band: str, sca: int, position, metric: str, mode: str, magnitude, scheme: str = "lagrange") -> np.ndarray:
        """:meth:`slope`'s slope alone (the same number), without its error."""
        if metric == "e":
            s1 = self.value(band, sca, position, "e1", mode, magnitude, scheme)
            return np.hypot(s1, self.value(band, sca, position, "e2", mode, magnitude, scheme))
        return self.values(band, sca, position, (metric,), mode, magnitude, scheme)[0]

    def values(self, band: str, sca: int, position, metrics, mode: str, magnitude, scheme: str = "lagrange") -> list:
        """:meth:`value` of several column metrics ("size", "e1", "e2") read together (the same numbers)."""
        columns = [self._column(metric, mode) for metric in metrics]
        w = weights(self._entry(band, sca)[1]["grid"], position, scheme)
        return [contract(w, v) for v in self.columns_node_values(band, sca, columns, magnitude)]

    @staticmethod
    def _column(metric: str, mode: str) -> str:
        from .tables import COLUMN_METRICS, MODES

        if metric not in COLUMN_METRICS:
            raise InputError("metric", f"must be one of {', '.join([*COLUMN_METRICS, 'e'])}, got {metric!r}")
        if mode not in MODES:
            raise InputError("mode", f"must be one of {', '.join(MODES)}, got {mode!r}")
        return f"{mode}_{metric}"


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
        for part in gridfile.ARRAY_PARTS:
            arrays[f"{key}/{part}"] = update.arrays[f"{key}/{part}"]
        replaced.append(key)
    provenance = meta.setdefault("provenance", {})
    provenance["replaced_entries"] = sorted({*provenance.get("replaced_entries", []), *replaced})
    provenance["cpu_s"] = float(sum(c for e in meta["tables"].values() for row in e["cpu_s"] for c in row if c is not None))
    return FieldGrid(meta, arrays)
