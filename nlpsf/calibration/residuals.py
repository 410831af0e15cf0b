"""Residuals a calibration leaves: curves, polynomials, shape families, and the difference of two linearity
reference files (docs/calibration.md).

A residual is r(Q) [e-] at charge Q [e-]: corrected signal minus true charge. A curve is linear between its
points (ECSV ``charge_e``, ``residual_e``); it must cover every charge level the star's resultants reach
(refused otherwise: no extrapolation). A shape family is a residual up to its scale: ``constant_fraction``
(r = s Q), ``power_law:ALPHA`` (r = s (Q / 1e5 e-)^ALPHA), ``quadratic`` (r = -s Q^2, the solver's
Delta_beta = s), ``polynomial:N`` (r = s Q^N).

Two linearity reference files (romancal's ``linearity``, ASDF, ``coeffs`` (n, rows, cols) in DN, a
polynomial F_c = sum_k c_k F^k per pixel) give a per-pixel residual: the file applied less the reference
file, r_p(R) = g [P_file(R / g) - P_ref(R / g)] at each resultant's measured signal R = S(Q*) [e-], g the
gain [e- / DN]. Only the native pixels under the star's stamp are read from disk (the array is memory
mapped; a full-frame file, 4096 x 4096, carries a 4-pixel reference border, so science pixel x (1-4088)
is column x + 3; a smaller array is a cut-out whose first column is science pixel 1). Reading needs the
``roman`` extra (roman_datamodels, asdf).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..checks import InputError, SimulationError
from .kernel import Response

#: The pivot of the power-law family [e-].
POWER_LAW_PIVOT_E = 1e5
#: romanisim 0.15.0's reference gain [e-/DN] (``parameters.reference_data``; the same source as the full
#: well's 55000 DN x 2): the default where no gain is given. No per-SCA gain is published in
#: roman-technical-information 1.5.0 (nlpsf/data/SOURCES.md); flight gains are per pixel, in CRDS.
DEFAULT_GAIN = 2.0
#: Science pixels per SCA side and the reference border of a full-frame reference file.
SCIENCE_PIXELS = 4088
REFERENCE_BORDER = 4
FULL_FRAME = SCIENCE_PIXELS + 2 * REFERENCE_BORDER
#: At most this many points in a residual curve (the API's body limits hold it too).
MAX_CURVE_POINTS = 10_000
#: At most this many coefficients in a polynomial residual or a linearity file's polynomial.
MAX_COEFFICIENTS = 24

Residual = Callable[[np.ndarray], np.ndarray]


def from_curve(charge_e, residual_e, name: str = "residual curve") -> Residual:
    """r linear between the points (``charge_e`` strictly increasing, finite); evaluating it outside their
    range is an InputError naming the range."""
    q = np.asarray(charge_e, dtype=np.float64).ravel()
    r = np.asarray(residual_e, dtype=np.float64).ravel()
    if q.size != r.size or q.size < 2:
        raise InputError("residual", f"{name}: give at least two (charge_e, residual_e) points of equal count")
    if q.size > MAX_CURVE_POINTS:
        raise InputError("residual", f"{name}: at most {MAX_CURVE_POINTS} points, got {q.size}")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(r))):
        raise InputError("residual", f"{name}: charge_e and residual_e must be finite numbers")
    if np.any(np.diff(q) <= 0):
        raise InputError("residual", f"{name}: charge_e must increase strictly")

    def residual(levels):
        levels = np.asarray(levels, dtype=np.float64)
        low, high = float(levels.min(initial=q[0])), float(levels.max(initial=q[-1]))
        if low < q[0] or high > q[-1]:
            raise InputError(
                "residual",
                f"{name} covers {q[0]:.6g}-{q[-1]:.6g} e-; the star's resultants reach {low:.6g}-{high:.6g} e- "
                "(extend the curve: a residual is never extrapolated)",
            )
        return np.interp(levels, q, r)

    return residual


def read_curve(path: str | Path) -> Residual:
    """An ECSV (or any astropy-readable table) with columns ``charge_e`` and ``residual_e`` [e-]."""
    from astropy.table import Table

    try:
        table = Table.read(str(path), format="ascii.ecsv")
    except FileNotFoundError:
        raise InputError("residual", f"{path}: no such file") from None
    except Exception as error:
        raise InputError("residual", f"{path}: not a readable ECSV table ({error})") from None
    for column in ("charge_e", "residual_e"):
        if column not in table.colnames:
            raise InputError("residual", f"{path}: no column {column!r} (columns: {', '.join(table.colnames)})")
    return from_curve(table["charge_e"], table["residual_e"], str(path))


def from_polynomial(coefficients) -> Residual:
    """r(Q) = sum_k a_k Q^k, ``coefficients`` (a_0, a_1, ...) [e-^(1-k)]."""
    a = np.asarray(coefficients, dtype=np.float64).ravel()
    if a.size == 0 or a.size > MAX_COEFFICIENTS or not np.all(np.isfinite(a)):
        raise InputError("residual", f"give 1 to {MAX_COEFFICIENTS} finite polynomial coefficients (a_0, a_1, ...)")
    return lambda q: np.polynomial.polynomial.polyval(np.asarray(q, dtype=np.float64), a)


#: Shape families: name -> (description, shape for a parameter).
FAMILIES = ("constant_fraction", "power_law", "quadratic", "polynomial")


def family(spec: str) -> tuple[str, Residual]:
    """(description, unit-scale shape) of ``constant_fraction``, ``power_law:ALPHA``, ``quadratic``,
    ``polynomial:N``."""
    name, _, parameter = str(spec).strip().partition(":")
    if name == "constant_fraction":
        return "r = s Q (a constant fraction s of the charge)", lambda q: np.asarray(q, dtype=np.float64)
    if name == "quadratic":
        return "r = -s Q^2 (the solver's Delta_beta = s)", lambda q: -(np.asarray(q, dtype=np.float64) ** 2)
    if name == "power_law":
        alpha = _number(parameter, spec, -4.0, 12.0)
        return (
            f"r = s (Q / {POWER_LAW_PIVOT_E:g} e-)^{alpha:g}",
            lambda q: np.power(np.maximum(np.asarray(q, dtype=np.float64), 0.0) / POWER_LAW_PIVOT_E, alpha),
        )
    if name == "polynomial":
        n = int(_number(parameter, spec, 0, MAX_COEFFICIENTS))
        return f"r = s Q^{n}", lambda q: np.asarray(q, dtype=np.float64) ** n
    raise InputError("shape", f"unknown shape {spec!r}; shapes: constant_fraction, power_law:ALPHA, quadratic, polynomial:N")


def _number(text: str, spec: str, low: float, high: float) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InputError("shape", f"{spec!r}: give the family's parameter as a number after ':'") from None
    if not (math.isfinite(value) and low <= value <= high):
        raise InputError("shape", f"{spec!r}: the parameter must lie in [{low:g}, {high:g}]")
    return value


# --- linearity reference files ---------------------------------------------------------------------


@dataclass(frozen=True)
class PixelPolynomials:
    """The correction polynomials (n, rows, cols) [DN] of the native pixels under a star, with where they
    sit: native pixel (row0 + i, col0 + j) in science-pixel numbering (1-based)."""

    coeffs: np.ndarray
    row0: int
    col0: int
    source: str

    def at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """(n, len) coefficients of the science pixels (rows, cols) (1-based; inside the block)."""
        return self.coeffs[:, rows - self.row0, cols - self.col0]

    @property
    def window(self) -> tuple[int, int, int, int]:
        """(first row, last row, first column, last column) of the block, science pixels (1-based)."""
        return self.row0, self.row0 + self.coeffs.shape[1] - 1, self.col0, self.col0 + self.coeffs.shape[2] - 1

    def covers(self, window: tuple[int, int, int, int]) -> bool:
        r0, r1, c0, c1 = self.window
        return r0 <= window[0] and window[1] <= r1 and c0 <= window[2] and window[3] <= c1

    def cut(self, window: tuple[int, int, int, int], field: str = "linearity") -> PixelPolynomials:
        """The block's pixels in ``window``; refused (naming the source and both windows) where it does not
        cover them."""
        if not self.covers(window):
            have = self.window
            raise InputError(
                field,
                f"{self.source}: its pixels (rows {have[0]}-{have[1]}, columns {have[2]}-{have[3]}) do not cover the "
                f"science pixels the star's measurement reads (rows {window[0]}-{window[1]}, columns {window[2]}-{window[3]})",
            )
        top, left = window[0] - self.row0, window[2] - self.col0
        block = self.coeffs[:, top : top + window[1] - window[0] + 1, left : left + window[3] - window[2] + 1]
        return PixelPolynomials(block, window[0], window[2], self.source)

    def padded(self, n: int) -> PixelPolynomials:
        """The same polynomials with n coefficients (zeros above its own order)."""
        if self.coeffs.shape[0] >= n:
            return self
        out = np.zeros((n, *self.coeffs.shape[1:]))
        out[: self.coeffs.shape[0]] = self.coeffs
        return PixelPolynomials(out, self.row0, self.col0, self.source)

    @classmethod
    def inline(cls, coeffs, first_row: int, first_column: int, source: str, field: str = "linearity") -> PixelPolynomials:
        """Per-pixel correction polynomials given as numbers (a request's, not a file's): ``coeffs`` (n, rows,
        cols) [DN], c_k of F_c = sum_k c_k F^k; its pixel [0, 0] is science pixel (``first_row``,
        ``first_column``) (1-based). Refused, naming ``field``: a shape other than (n, rows, cols) with 2 <= n <=
        MAX_COEFFICIENTS, pixels off the SCA, a coefficient that is not a finite number (its pixel named)."""
        try:
            block = np.asarray(coeffs, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError(field, f"{source}: give the coefficients as an array (n, rows, cols) of numbers") from None
        if block.ndim != 3 or not (2 <= block.shape[0] <= MAX_COEFFICIENTS) or 0 in block.shape:
            raise InputError(
                field,
                f"{source}: coefficients of shape {block.shape}; expected (n, rows, cols) with 2 <= n <= {MAX_COEFFICIENTS}",
            )
        first_row, first_column = int(first_row), int(first_column)
        last_row, last_column = first_row + block.shape[1] - 1, first_column + block.shape[2] - 1
        if first_row < 1 or first_column < 1 or last_row > SCIENCE_PIXELS or last_column > SCIENCE_PIXELS:
            raise InputError(
                field,
                f"{source}: rows {first_row}-{last_row}, columns {first_column}-{last_column} are not all science pixels "
                f"(1-{SCIENCE_PIXELS})",
            )
        _check_finite(block, first_row, first_column, source, field)
        return cls(block, first_row, first_column, source)


def science_pixels(response: Response) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) [science pixels, 1-based] each sample of ``response`` is read in; -1 for the sky
    estimate's samples. The stamp's fine pixel i sits (i - centre) / N native pixels from the star."""
    x, y = response.star_position
    n, centre = response.oversampling, (response.stamp - 1) / 2
    star = response.rows >= 0
    rows = np.full(response.levels.shape, -1)
    cols = np.full(response.levels.shape, -1)
    rows[star] = np.rint(y + (response.rows[star] - centre) / n).astype(int)
    cols[star] = np.rint(x + (response.cols[star] - centre) / n).astype(int)
    return rows, cols


def measured_window(response: Response) -> tuple[int, int, int, int]:
    """(first row, last row, first column, last column) [science pixels, 1-based]: the pixels the star's
    measurement reads, those whose samples carry a non-zero weight (the moments' weight function is cut at
    rho^2, so the others do not enter at all). A linearity calibration matters here and nowhere else."""
    rows, cols = science_pixels(response)
    used = (rows >= 0) & np.any(response.weights != 0, axis=1)
    if not np.any(used):
        raise SimulationError("the star's measurement reads no pixel (every weight is zero)")
    return int(rows[used].min()), int(rows[used].max()), int(cols[used].min()), int(cols[used].max())


def star_window(position: tuple[float, float], stamp: int, oversampling: int) -> tuple[int, int, int, int]:
    """(first row, last row, first column, last column) of the science pixels (1-based) a whole stamp covers."""
    half = math.ceil((stamp / 2) / oversampling) + 1
    x, y = (round(float(v)) for v in position)
    return y - half, y + half, x - half, x + half


def read_linearity(path: str | Path, window: tuple[int, int, int, int]) -> PixelPolynomials:
    """The ``coeffs`` of a romancal linearity reference file over ``window`` (science pixels, 1-based),
    read from disk alone (memory-mapped ASDF). Refused, naming the file: no such file, not ASDF, no
    ``roman.coeffs``, a shape other than (n, rows, cols), the window outside the array, NaN or infinite
    coefficients under the star."""
    path = Path(path)
    try:
        import asdf
    except ImportError:
        raise InputError(
            "linearity", "reading linearity reference files needs the roman extra: pip install 'nlpsf[roman]'"
        ) from None
    try:
        import roman_datamodels  # noqa: F401 - registers the Roman tags, so the tree reads as written
    except ImportError:
        raise InputError(
            "linearity", "reading linearity reference files needs the roman extra: pip install 'nlpsf[roman]'"
        ) from None
    if not path.is_file():
        raise InputError("linearity", f"{path}: no such file")
    try:
        handle = asdf.open(str(path), memmap=True, lazy_load=True)
    except Exception as error:
        raise InputError("linearity", f"{path}: not an ASDF file ({type(error).__name__}: {error})") from None
    with handle as af:
        roman = af.tree.get("roman")
        if roman is None or "coeffs" not in roman:
            raise InputError("linearity", f"{path}: no roman.coeffs (a romancal linearity reference file holds one)")
        meta = roman.get("meta") if hasattr(roman, "get") else None
        reftype = None if meta is None else _get(meta, "reftype")
        if reftype is not None and str(reftype).upper() != "LINEARITY":
            raise InputError("linearity", f"{path}: its reftype is {reftype}, not LINEARITY")
        coeffs = roman["coeffs"]
        shape = tuple(int(s) for s in coeffs.shape)
        if len(shape) != 3 or shape[0] < 2 or shape[0] > MAX_COEFFICIENTS:
            raise InputError(
                "linearity", f"{path}: coeffs has shape {shape}; expected (n, rows, cols) with 2 <= n <= {MAX_COEFFICIENTS}"
            )
        border = REFERENCE_BORDER if shape[1:] == (FULL_FRAME, FULL_FRAME) else 0
        r0, r1, c0, c1 = window
        top, bottom, left, right = r0 - 1 + border, r1 - 1 + border, c0 - 1 + border, c1 - 1 + border
        if top < 0 or left < 0 or bottom >= shape[1] or right >= shape[2]:
            raise InputError(
                "linearity",
                f"{path}: coeffs of shape {shape} do not cover science pixels rows {r0}-{r1}, columns {c0}-{c1} around the star",
            )
        block = np.array(coeffs[:, top : bottom + 1, left : right + 1], dtype=np.float64)
    _check_finite(block, r0, c0, str(path), "linearity")
    return PixelPolynomials(block, r0, c0, str(path))


def _check_finite(block: np.ndarray, row0: int, col0: int, source: str, field: str) -> None:
    if not np.all(np.isfinite(block)):
        bad = np.argwhere(~np.isfinite(block))[0]
        raise InputError(
            field,
            f"{source}: coefficient {bad[0]} of science pixel (row {row0 + bad[1]}, column {col0 + bad[2]}) "
            "is not a finite number",
        )


def _get(node, key):
    try:
        return node[key]
    except (KeyError, TypeError):
        return getattr(node, key, None)


def file_residual(
    response: Response, applied: PixelPolynomials, reference: PixelPolynomials, gain: float, field: str = "linearity"
) -> tuple[np.ndarray, np.ndarray]:
    """(r at every sample of ``response`` [e-], the common residual there): the per-pixel residual
    g [P_applied(R/g) - P_reference(R/g)] at each sample's measured signal R = S(Q*), and the part every pixel
    shares, the two polynomials averaged over the pixels the measurement reads (:func:`measured_window`): the
    bias. The sky estimate's samples take the polynomials averaged over the blocks' pixels outside that window
    (the star-free pixels around the star, what a local sky estimate reads), or over the window where the
    blocks hold no other pixel (:func:`sky_pixels` says which). Both blocks must cover the measured window.
    Refused where a polynomial is not monotonic (a correction that decreases with the signal) over the signal
    range the star reaches in a pixel."""
    if not (math.isfinite(gain) and GAIN_RANGE[0] <= gain <= GAIN_RANGE[1]):
        raise InputError("gain", f"must be a gain in e-/DN between {GAIN_RANGE[0]:g} and {GAIN_RANGE[1]:g}, got {gain!r}")
    window = measured_window(response)
    n = max(applied.coeffs.shape[0], reference.coeffs.shape[0])
    sky_a, sky_r = (_sky_mean(p.padded(n), window, field) for p in (applied, reference))
    applied = applied.cut(window, field).padded(n)
    reference = reference.cut(window, field).padded(n)
    levels = response.levels
    signal = levels - response.raw_beta * levels * levels  # the measured resultant R = S(Q*) [e-]
    dn = signal / gain
    rows, cols = science_pixels(response)
    star = rows >= 0
    inside = star & (rows >= window[0]) & (rows <= window[1]) & (cols >= window[2]) & (cols <= window[3])
    top = float(dn.max(initial=0.0))
    for polys in (applied, reference):
        _check_monotonic(polys, top, field)
    a_mean, r_mean = applied.coeffs.mean(axis=(1, 2)), reference.coeffs.mean(axis=(1, 2))
    common = gain * (_horner(a_mean, dn) - _horner(r_mean, dn))
    common[~star] = gain * (_horner(sky_a, dn[~star]) - _horner(sky_r, dn[~star]))
    out = common.copy()  # the sky's samples, and a stamp pixel outside the window (zero weight there)
    if np.any(inside):
        a = applied.at(rows[inside], cols[inside])
        r = reference.at(rows[inside], cols[inside])
        out[inside] = gain * (_horner_each(a, dn[inside]) - _horner_each(r, dn[inside]))
    return out, common


def sky_pixels(block: PixelPolynomials, window: tuple[int, int, int, int]) -> int:
    """How many of ``block``'s pixels lie outside the measured ``window``: those the sky estimate reads."""
    r0, r1, c0, c1 = block.window
    return (r1 - r0 + 1) * (c1 - c0 + 1) - (window[1] - window[0] + 1) * (window[3] - window[2] + 1)


def _sky_mean(block: PixelPolynomials, window: tuple[int, int, int, int], field: str) -> np.ndarray:
    """The polynomial a star-free pixel around the star has on average: the block's pixels outside ``window``
    (the window's own where there are none)."""
    if sky_pixels(block, window) <= 0:
        return block.cut(window, field).coeffs.mean(axis=(1, 2))
    rows = np.arange(block.row0, block.row0 + block.coeffs.shape[1])[:, None]
    cols = np.arange(block.col0, block.col0 + block.coeffs.shape[2])[None, :]
    outside = ~((rows >= window[0]) & (rows <= window[1]) & (cols >= window[2]) & (cols <= window[3]))
    return block.coeffs[:, outside].mean(axis=1)


#: The gains accepted [e- / DN].
GAIN_RANGE = (0.1, 100.0)
#: Where the default gain comes from (an answer's conditions name it).
DEFAULT_GAIN_SOURCE = "romanisim 0.15.0 reference gain, 2 e-/DN (no per-SCA gain is published: docs/calibration.md)"


def pixel_effect(
    response: Response,
    applied: PixelPolynomials,
    reference: PixelPolynomials,
    gain: float | None = None,
    field: str = "linearity",
) -> dict:
    """What two calibrations' per-pixel polynomials do to the star (``applied`` less ``reference``): the bias
    (their polynomials averaged over the measured pixels, on every pixel), the total (each pixel its own), each
    with its standard error over the centroid realizations, and the scatter part (the rms over centroids of the
    total less the bias), with the conditions. ``gain`` None: :data:`DEFAULT_GAIN`."""
    from ..serialise import json_safe
    from .kernel import EFFECT_UNITS, summarise

    given = gain is not None
    gain = DEFAULT_GAIN if gain is None else float(gain)
    per_pixel, common = file_residual(response, applied, reference, gain, field)
    total = _per_realization(response, per_pixel)
    bias = _per_realization(response, common)
    window = measured_window(response)
    scatter = np.std(total - bias, axis=0, ddof=1) if response.count > 1 else np.zeros(3)
    return json_safe(
        {
            "magnitude": response.magnitude,
            "bias": {k: {"value": v, "uncertainty": e} for k, (v, e) in summarise(bias).items()},
            "total": {k: {"value": v, "uncertainty": e} for k, (v, e) in summarise(total).items()},
            "scatter": {name: {"value": float(scatter[k])} for k, name in enumerate(("size", "e1", "e2"))},
            "units": dict(EFFECT_UNITS),
            "conditions": {
                **response.conditions,
                "residual": f"linearity {applied.source} less reference {reference.source}, gain {gain:g} e-/DN",
                "gain_e_per_dn": gain,
                "gain_source": "given" if given else DEFAULT_GAIN_SOURCE,
                "measured_pixels": {"rows": [window[0], window[1]], "columns": [window[2], window[3]]},
                "sky_pixels": sky_pixels(applied, window),
                "bias_definition": "the two calibrations' polynomials averaged over the measured pixels, applied to every "
                "pixel; total: each pixel its own; scatter: the rms over centroids of total less bias; the sky estimate "
                "reads the given pixels outside the measured ones (sky_pixels of them; none: the measured pixels' mean)",
            },
            "flags": [str(f) for f in response.flags],
            "flag_codes": [str(getattr(f, "code", "")) for f in response.flags],
        }
    )


def _per_realization(response: Response, values: np.ndarray) -> np.ndarray:
    out = np.zeros((response.count, 3))
    for k in range(3):
        out[:, k] = np.bincount(response.owner, weights=response.weights[:, k] * values, minlength=response.count)
    return out


def _horner(c: np.ndarray, x: np.ndarray) -> np.ndarray:
    out = np.full_like(x, c[-1])
    for k in range(c.size - 2, -1, -1):
        out = out * x + c[k]
    return out


def _horner_each(c: np.ndarray, x: np.ndarray) -> np.ndarray:
    """sum_k c[k, m] x[m]^k per sample m."""
    out = c[-1].copy()
    for k in range(c.shape[0] - 2, -1, -1):
        out = out * x + c[k]
    return out


def _check_monotonic(polys: PixelPolynomials, top_dn: float, field: str = "linearity") -> None:
    """Every pixel's correction rises over [0, top_dn] (its derivative > 0 on a fine grid)."""
    x = np.linspace(0.0, max(top_dn, 1.0), 257)
    c = polys.coeffs
    derivative = np.zeros((x.size, *c.shape[1:]))
    for k in range(c.shape[0] - 1, 0, -1):
        derivative = derivative * x[:, None, None] + k * c[k][None]
    bad = np.argwhere(derivative <= 0)
    if bad.size:
        i, r, col = bad[0]
        raise InputError(
            field,
            f"{polys.source}: the correction of science pixel (row {polys.row0 + r}, column {polys.col0 + col}) is not "
            f"monotonic over the star's signal range (its slope is {derivative[i, r, col]:.3g} at {x[i]:.6g} DN, "
            f"the star reaches {top_dn:.6g} DN)",
        )
