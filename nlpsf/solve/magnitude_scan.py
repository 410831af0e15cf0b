"""The magnitude at which the NL error reaches the tolerance: one scan for the final frame and the ramp.

|c(m)| delta_beta = tolerance is solved scanning from faint to bright, so that every fainter star
also meets the tolerance (|c| need not be monotonic when e1 or e2 changes sign). Only the grid the
scan starts from differs between the paper's single final frame and an up-the-ramp exposure
(:func:`_final_frame_grid`, :func:`_ramp_grid`, and for the Roman default's field grid
:func:`_field_grid_scan`, its own c(m)); the bracket is then refined on the slopes the answer uses.
``slopes`` is the solver's c(m) at the request (``nlpsf.solve.solver``).

Fainter than the scan reaches. Where even its faintest star misses the tolerance, a fainter one
meets it only if |c| falls toward fainter stars: in the linear regime |c| is proportional to the
flux and the answer is extrapolated so (:data:`FlagCode.EXTRAPOLATED_ANSWER`). Where |c| does not
fall toward fainter stars, no star meets a tolerance its faintest scanned star misses -- an
``InputError`` naming the tolerance with the smallest one reachable (:class:`ToleranceUnreachable`),
not an answer. (The sky's own NL is removed with the local sky estimate, docs/ramps.md, so the Roman
default's faint end falls with the flux like the paper's.)
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from nlpsf.checks import InputError, SimulationError
from nlpsf.flags import Flag, FlagCode, make
from nlpsf.slopes import tables

#: Step of the derivative d ln|c| / dm [mag].
_H = 0.01
#: How far brighter than the scan's faint end its trend is read (:func:`_falls_fainter`) [mag].
_TREND_MAG = 0.5
#: Step of a simulated scene's own scan fainter than resultants saturate, where it has a sky [mag].
_SKY_STEP = 0.5


class ToleranceUnreachable(InputError):
    """No star meets the tolerance at this precision: even the faintest star the slopes reach
    misses it and |c| does not fall toward fainter stars (see the module docstring)."""

    def __init__(self, field: str, tolerance: float, faintest: float, error_there: float, smallest: float, reason: str):
        self.tolerance, self.faintest, self.error_there, self.smallest = tolerance, faintest, error_there, smallest
        super().__init__(
            field,
            f"no star meets a tolerance of {tolerance:.3g} at this precision: the NL error is {error_there:.3g} at "
            f"m={faintest:.2f}, the faintest magnitude the slopes reach, and {reason}; the smallest tolerance "
            f"reachable at this precision is {smallest:.3g} (or give a precision {tolerance / smallest:.3g} times "
            "the one given, or finer)",
        )


class NodeScan(NamedTuple):
    """What an SCA's nodes answered at once (``sca_nodes``) already found of one node's scan: its
    crossing (None: not crossed inside the scan), d ln|c| / dm there (None: not found), and its c(m)
    on the scan's magnitudes (the field grid's values at the node; None: not read)."""

    root: float | None
    log_derivative: float | None
    values: np.ndarray | None = None


@dataclass(frozen=True)
class MagnitudeScan:
    """Where the NL error reaches the tolerance (None: nowhere down to the scan's bright end), the
    slope and its uncertainty there, d ln|c| / dm, and the flags of the scan."""

    magnitude: float | None
    slope: float | None
    slope_error: float | None
    log_derivative: float | None
    flags: list[Flag]


@dataclass(frozen=True)
class _Grid:
    """The magnitudes scanned (faint to bright), |c| on them, and how the scan words its ends."""

    magnitudes: np.ndarray
    values: np.ndarray
    faintest: float
    everywhere: str  # "the NL error stays below the tolerance ..." where the scan found no crossing
    down_to: float
    sign_where: str
    shift: float = 0.0  # final frame: the tables' magnitude relabelling and beta0 factor
    factor: float = 1.0


def scan_magnitude(
    slopes, delta_beta: float, tolerance: float, m_sat: float, field: str = "tolerance", crossing: NodeScan | None = None
) -> MagnitudeScan:
    """Magnitude where |c(m)| delta_beta = tolerance; see the module docstring. ``field``: the
    request field that sets the tolerance, named where no star meets it (:class:`ToleranceUnreachable`).
    ``crossing``: what was found of this scan already (:class:`NodeScan`; ``sca_nodes``: the same
    scan and secant on every node of an SCA at once, bit for bit): not read or sought again."""
    flags: list[Flag] = []
    required = tolerance / delta_beta
    if getattr(slopes, "grid", None) is not None:
        grid = _field_grid_scan(slopes, m_sat, None if crossing is None else crossing.values)
    elif slopes.ramp is None:
        grid = _final_frame_grid(slopes)
    else:
        grid = _ramp_grid(slopes, required, m_sat)
    above = np.abs(grid.values) > required
    if above[0]:
        # Even the faintest scanned star exceeds the tolerance: a fainter one meets it only where
        # |c| falls toward fainter stars (the linear regime: in proportion to the flux).
        at_faint_end, brighter = _faint_end(slopes, grid)
        if not _falls_fainter(at_faint_end, brighter):
            reason = (
                f"it does not fall toward fainter stars (it is {abs(brighter) * delta_beta:.3g} at "
                f"m={grid.faintest - _TREND_MAG:.2f}), so no fainter star can be promised to meet it"
            )
            smallest = abs(at_faint_end) * delta_beta
            raise ToleranceUnreachable(field, tolerance, grid.faintest, smallest, smallest, reason)
        m_nl = float(grid.faintest + 2.5 * math.log10(abs(at_faint_end) / required))
        flags.append(make(FlagCode.EXTRAPOLATED_ANSWER, faintest=grid.faintest, magnitude=m_nl))
        if m_nl > 40:
            flags.append(make(FlagCode.FAINTER_THAN_40))
        slope, slope_err = slopes.at(m_nl)[:2]
        return MagnitudeScan(m_nl, slope, slope_err, -0.4 * math.log(10), flags)
    if not above.any():
        flags.append(make(FlagCode.BELOW_TOLERANCE_EVERYWHERE, where=grid.everywhere, down_to=grid.down_to))
        return MagnitudeScan(None, None, None, None, flags)
    k = int(np.argmax(above))  # first magnitude (from the faint side) where the tolerance is exceeded
    bright, faint = float(grid.magnitudes[k]), float(grid.magnitudes[k - 1])
    known = crossing is not None and crossing.root is not None
    m_nl = crossing.root if known else _crossing(slopes, grid, required, bright, faint, m_sat)
    if m_nl is None:
        # The fresh simulation stays below the tolerance from the tables' bracket down to saturation.
        where = (
            f"for the simulated star down to saturation m={m_sat:.2f} (the tables' c(m) at beta0 crosses it at "
            f"m={bright:.2f}-{faint:.2f}; this scene's own slopes stay below it there and at saturation)"
        )
        flags.append(make(FlagCode.BELOW_TOLERANCE_EVERYWHERE, where=where, down_to=m_sat))
        return MagnitudeScan(None, None, None, None, flags)
    slope, slope_err, _ = slopes.at(m_nl)
    log_derivative = crossing.log_derivative if known and crossing.log_derivative is not None else None
    log_derivative = _log_derivative(slopes, grid, m_nl) if log_derivative is None else log_derivative
    if any(np.diff(np.sign(grid.values[np.isfinite(grid.values)])) != 0):
        flags.append(make(FlagCode.SLOPE_CHANGES_SIGN, metric=slopes.metric, where=grid.sign_where))
    return MagnitudeScan(m_nl, slope, slope_err, log_derivative, flags)


def _faint_end(slopes, grid: _Grid) -> tuple[float, float]:
    """c at the scan's faintest magnitude and :data:`_TREND_MAG` brighter, from the slopes the
    answer uses (the scan's own values where they are those slopes)."""
    if slopes.ramp is None or getattr(slopes, "grid", None) is not None:
        step = float(grid.magnitudes[0] - grid.magnitudes[1])
        k = min(round(_TREND_MAG / step), grid.values.size - 1)
        return float(grid.values[0]), float(grid.values[k])
    return slopes.at(grid.faintest)[0], slopes.at(grid.faintest - _TREND_MAG)[0]


def _falls_fainter(at_faint_end: float, brighter: float) -> bool:
    """Whether |c| is smaller at the faint end than :data:`_TREND_MAG` brighter: in the linear regime
    it falls in proportion to the flux (by 10^(-0.4 x 0.5) = 0.63), so a fainter star meets what the
    faintest scanned one misses."""
    return abs(at_faint_end) < abs(brighter)


def _field_grid_scan(slopes, m_sat: float, values: np.ndarray | None = None) -> _Grid:
    """The Roman default's field grid at the position: its own c(m) on a 0.05 mag grid from the
    grid's faint end to the saturation magnitude, in one vectorised look-up (the slopes the answer
    reads, so the bracket is the answer's: the paper tables' c(m) has neither the default's values
    nor the shape its ramp, IPC and sky give it)."""
    brightest, faintest = slopes.grid.magnitude_range(slopes.band, slopes.sca)
    magnitudes = np.arange(faintest, max(m_sat, brightest) - 1e-9, -0.05)
    grid, position = slopes.grid, slopes.scene_model.position
    if values is None or values.shape != magnitudes.shape:  # ``values``: the node's own, read with the others
        values = grid.value(slopes.band, slopes.sca, position, slopes.metric, slopes.mode, magnitudes)
    slopes.ramp_bases.add("grid")
    everywhere = f"for every star from the field grid's faint end m={faintest:.2f} down to saturation m={m_sat:.2f}"
    return _Grid(magnitudes, np.asarray(values, dtype=np.float64), faintest, everywhere, m_sat, "over the scan")


def _final_frame_grid(slopes) -> _Grid:
    """The tables' own range on a 0.05 mag grid, in one vectorised look-up."""
    lo, hi = slopes.range()
    magnitudes = np.arange(hi, lo - 1e-9, -0.05)  # faint to bright
    shift = slopes.table.magnitude_shift(slopes.exptime, slopes.beta0)
    factor = slopes.table.beta0 / slopes.beta0
    values = slopes.table.values(slopes.metric, slopes.mode, magnitudes - shift) * factor
    margin = tables.BRIGHT_MARGIN_MAG
    everywhere = f"over the whole table, down to m={lo:.2f} ({margin} mag brighter than saturation, in beta0 x flux)"
    return _Grid(magnitudes, values, hi, everywhere, lo, "within the table", shift, factor)


def _ramp_grid(slopes, required: float, m_sat: float) -> _Grid:
    """Fainter than where the brightest pixel starts dropping resultants, |c(m)| at once from the
    tables at the OLS beta_eff on a 0.05 mag grid (exact for an OLS fit, a bracket for the optimal
    one; a simulated scene with a sky: its own slopes on a 0.5 mag grid); brighter, down to the
    ramp's saturation magnitude, from the slopes themselves on a 0.25 mag grid (fresh simulations),
    only when the crossing is not already in the table part."""
    hi = slopes.range()[1]
    exact = min(slopes.exact_from(), hi)
    c_ols = slopes.ramp.ols_quadratic_factor(slopes.exptime)
    table = slopes.table
    scene = slopes.scene_model
    if scene is not None and scene.background_e > 0 and not (slopes.fidelity == "table" and slopes.ramp_factor is not None):
        # A sky changes the ramp's factors (the optimal weights see its rate) and the NL's cross terms,
        # so the scene's c(m) has another shape than the paper tables' and they bracket nothing:
        # the scene's own slopes on a :data:`_SKY_STEP` grid (about 20 fresh magnitudes, ~0.5 CPU-s once
        # prepared). Away from saturation c(m) is a star term and a sky term, each a power of the flux, so
        # |c| is largest at a step's ends and the grid's nodes hold the promise between them.
        faint_grid = np.arange(hi, exact - 1e-9, -_SKY_STEP)
        faint_values = np.array([slopes.at(float(m))[0] for m in faint_grid])
    else:
        faint_grid = np.arange(hi, exact - 1e-9, -0.05)
        shift = table.magnitude_shift(slopes.exptime, c_ols * slopes.beta0)
        faint_values = table.values(slopes.metric, slopes.mode, faint_grid - shift) * (table.beta0 / slopes.beta0)
    bright_grid = np.arange(exact - 0.25, m_sat - 1e-9, -0.25)
    if bright_grid.size == 0 or bright_grid[-1] > m_sat + 1e-9:
        bright_grid = np.append(bright_grid, m_sat)
    if slopes.fidelity == "table" and slopes.ramp_factor is not None:
        slopes.ramp_bases.add("table")
    if np.any(np.abs(faint_values) > required):
        bright_grid = bright_grid[:0]  # the crossing is in the table part: no simulation needed to find it
    magnitudes = np.concatenate([faint_grid, bright_grid])
    values = np.concatenate([faint_values, [slopes.at(float(m))[0] for m in bright_grid]])
    everywhere = f"for every star down to the ramp's saturation limit m={m_sat:.2f}"
    return _Grid(magnitudes, values, hi, everywhere, m_sat, "over the scan")


def _crossing(slopes, grid: _Grid, required: float, bright: float, faint: float, m_sat: float) -> float | None:
    """The crossing inside the bracket [bright, faint], refined on the slopes the answer uses; None
    where fresh simulations stay below the tolerance down to saturation ``m_sat``."""

    def excess(m: float) -> float:
        return math.log(abs(slopes.at(m)[0]) / required)

    if slopes.ramp is None and slopes.fidelity == "table":
        # One vectorised look-up on a 1e-4 mag sub-grid of the bracket, then linear interpolation
        # of log|c| between the two sub-grid points around the crossing: ~1e-9 mag, in one call.
        sub = np.linspace(faint, bright, 501)
        log_c = np.log(np.abs(slopes.table.values(slopes.metric, slopes.mode, sub - grid.shift) * grid.factor) / required)
        j = max(int(np.argmax(log_c > 0)), 1)
        return float(sub[j - 1] + (sub[j] - sub[j - 1]) * (0.0 - log_c[j - 1]) / (log_c[j] - log_c[j - 1]))
    if slopes.ramp is None:
        # Fresh simulations: few evaluations, starting from the table's bracket widened a little.
        return _secant_root(excess, bright - 0.1, faint + 0.1, saturation=m_sat)
    if slopes.fidelity == "table" and slopes.ramp_factor is not None and bright >= slopes.exact_from():
        from scipy.optimize import brentq  # table look-ups are cheap: bracket to 1e-6 mag

        return brentq(excess, bright, faint, xtol=1e-6)
    return _secant_root(excess, bright, faint)


def _log_derivative(slopes, grid: _Grid, m_nl: float) -> float:
    """d ln|c| / dm at the crossing: from the tables for the final frame, from the slopes in use up the ramp."""
    if slopes.ramp is None:
        at = np.array([m_nl + _H, m_nl - _H, m_nl])
        ends = np.abs(slopes.table.values(slopes.metric, slopes.mode, at - grid.shift))
        if not math.isfinite(ends[1]):  # within _H of the tables' bright end: one-sided, from the crossing
            return float(np.log(ends[0] / ends[2]) / _H)
        return float(np.log(ends[0] / ends[1]) / (2 * _H))
    return (math.log(abs(slopes.at(m_nl + _H)[0])) - math.log(abs(slopes.at(m_nl - _H)[0]))) / (2 * _H)


def _secant_root(
    function, a: float, b: float, tolerance: float = 1e-4, iterations: int = 12, saturation: float | None = None
) -> float | None:
    """The root of ``function`` (log of |c| over the required slope) in [a, b], widened once by a
    magnitude each side where it does not change sign there. With ``saturation`` (the final frame),
    a widened end past where the star has a slope is taken back to the saturation magnitude, and None
    is returned where the function stays below zero (the error below the tolerance) down to it."""
    fa, fb = function(a), function(b)
    if not (math.isfinite(fa) and math.isfinite(fb)):
        raise SimulationError(
            f"the simulated star has no slope to search at the tables' bracket of the crossing (m={a:.2f}: {fa:.3g}, "
            f"m={b:.2f}: {fb:.3g}; it saturates there): this scene's crossing is not where the tables put it"
        )
    if fa * fb > 0:
        from scipy.optimize import brentq

        # The scan's bracket came from the tables' c(m) and the fresh simulations cross elsewhere:
        # widen it by a magnitude each side, once.
        lo, hi = a - 1.0, b + 1.0
        f_lo, f_hi = function(lo), function(hi)
        if not math.isfinite(f_lo) and saturation is not None and lo < saturation:
            # A magnitude brighter the star has no slope (2 beta0 Q_peak >= 1): the brightest usable
            # star is at most the saturation magnitude, so the search ends there.
            lo, f_lo = saturation, function(saturation)
            if f_lo < 0 and (f_hi < 0 or hi < saturation):
                return None  # below the tolerance down to saturation (fainter: the tables' scan): saturation binds
            if hi < saturation:  # the whole bracket is of saturated stars and saturation misses: search fainter
                hi, f_hi = saturation + 1.0, function(saturation + 1.0)
        if not (math.isfinite(f_lo) and math.isfinite(f_hi)):
            # Widened past where the simulated star has a slope (it saturates): no bracket to search.
            raise SimulationError(
                f"the simulated NL error does not cross the tolerance between m={a:.2f} and m={b:.2f}, where the tables' "
                f"scan put the crossing (log of |c| over the required slope: {fa:.3g} and {fb:.3g}), and a magnitude "
                f"further has no slope to search (m={lo:.2f}: {f_lo:.3g}, m={hi:.2f}: {f_hi:.3g}; the star saturates); "
                "this scene's crossing is not where the tables put it"
            )
        if f_lo * f_hi > 0:
            raise SimulationError(
                f"the simulated NL error does not cross the tolerance between m={lo:.2f} and m={hi:.2f}, around where "
                f"the tables' scan put it (log of |c| over the required slope: {f_lo:.3g} and {f_hi:.3g}); the scan "
                "of this scene's slopes needs a wider bracket than it takes"
            )
        return brentq(function, lo, hi, xtol=tolerance)
    c = b
    for _ in range(iterations):
        c = b - fb * (b - a) / (fb - fa)
        fc = function(c)
        if abs(fc) < 1e-6 or abs(c - b) < tolerance:
            return c
        if fa * fc < 0:
            b, fb = c, fc
        else:
            a, fa = c, fc
    return c
