"""The response kernel K(Q): how a PSF metric responds to a calibration residual r(Q) at each charge level.

Under the pipeline's correction (``ramps.correction``) a residual r enters the fitted image linearly,
sum_j w_pj r(Q*_pj), at each resultant's corrected level Q*_pj, and the moments respond to the image
linearly (``moments.pixel_response``, g). So, to first order in r,

    Delta metric = sum_p g_p / s sum_j w_pj r(Q*_pj) - (sum_p g_p / s) sum_j w_sky_j r(Q*_sky_j),

the last term the sky estimate moving with the residual (a star-free pixel's own corrected level).
That is a weighted sum of r over charge levels: a measure K on Q. On nodes Q_i (0, then geometric), each
sample (Q*, v) is shared between its two nodes by linear interpolation (hat functions), so
sum_i k_i r(Q_i) is the same sum with r interpolated linearly between nodes: exact for a piecewise-linear
r, within (Delta Q / Q)^2 / 8 of r's curvature otherwise. The density K_i = k_i / h_i (h_i the trapezoid
weight of node i) makes Delta metric = integral K(Q) r(Q) dQ by the trapezoid rule. Per realization
(centroid) the same sums give the statistical error (their standard error).

``Response.integrate`` evaluates a residual on the samples themselves (no nodes); the kernel is for the
page, the ECSV and a calibrator's own integrals.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from nlpsf import roman
from nlpsf.sim import ramps

from ..checks import InputError

#: Columns of a kernel (``charge_e`` and, per metric, K and its error): the requirement metrics whose
#: response is linear in r. |e| is not (the modulus of two linear responses); its column is the response
#: along the quadratic residual's (e1, e2) direction (exact for residuals of that shape; for others take
#: e1 and e2 and their modulus, as ``Response.integrate`` does).
KERNEL_METRICS: tuple[str, ...] = ("size", "e1", "e2", "e")
_MEASURED = {"size": 0, "e1": 1, "e2": 2}
#: Ratio of successive nodes above the first (geometric); the interpolation error of a smooth residual is
#: about (ratio - 1)^2 / 8 of its curvature term: 1e-5 of a quadratic's.
NODE_RATIO = 1.01
#: Where a star without a position sits: the SCA's centre, as the optics take it (``roman``) [pixels].
SCA_CENTRE = roman.SCA_PIXELS / 2
#: The first node above 0 [e-].
FIRST_NODE_E = 1.0
#: The fraction of the quadratic residual's effect a kernel's signal range holds.
SIGNAL_FRACTION = 0.9
#: Units of a residual's effect (``bias``, ``total``, ``scatter``: values and uncertainties alike).
EFFECT_UNITS = {
    "size": "dimensionless (Delta R / R)",
    "e1": "dimensionless (Delta e1)",
    "e2": "dimensionless (Delta e2)",
    "e": "dimensionless (|Delta e|)",
}
#: Bins per decade of charge of :meth:`Kernel.fractional_bins`.
BINS_PER_DECADE = 10
#: Units of a kernel's columns (the ECSV's and the JSON's).
KERNEL_UNITS = {
    "charge_e": "electron",
    **{name: "1 / electron" for name in KERNEL_METRICS},
    **{f"{name}_err": "1 / electron" for name in KERNEL_METRICS},
}


def nodes(top: float, ratio: float = NODE_RATIO, first: float = FIRST_NODE_E) -> np.ndarray:
    """0, then first, first x ratio, ... to the first node at or above ``top`` [e-]."""
    if top <= first:
        return np.array([0.0, first])
    count = math.ceil(math.log(top / first) / math.log(ratio)) + 1
    return np.concatenate([[0.0], first * ratio ** np.arange(count)])


def trapezoid_weights(grid: np.ndarray) -> np.ndarray:
    """h_i with sum_i h_i f_i the trapezoid rule on ``grid``."""
    h = np.zeros_like(grid)
    d = np.diff(grid)
    h[:-1] += d / 2
    h[1:] += d / 2
    return h


@dataclass(frozen=True, eq=False)
class Response:
    """A star's first-order response to a residual: the samples (charge level, weight per metric).

    ``levels`` (M,) [e-], ``weights`` (M, 3) and ``owner`` (M,): sample m adds weights[m] x r(levels[m]) to
    realization owner[m]'s (Delta R / R, Delta e1, Delta e2), of ``count`` realizations; the quadratic residual
    -Q^2 gives ``beta_slopes`` (count, 3), the slope the calibrator's Delta_beta acts through
    (``experiment.slopes``' bias slope)."""

    levels: np.ndarray
    weights: np.ndarray
    owner: np.ndarray
    count: int
    magnitude: float
    flux_electrons: float
    full_well_e: float
    saturation_e: float
    conditions: dict = field(default_factory=dict)
    flags: list = field(default_factory=list)
    #: (M,) the fine pixel (row, column of the stamps) each sample is read in; -1 for the sky estimate's.
    rows: np.ndarray | None = None
    cols: np.ndarray | None = None
    oversampling: int = 1
    stamp: int = 0
    raw_beta: float = 0.0
    #: (x, y) on the SCA [science pixels, 1-based] the star sits at; None: the SCA's centre.
    position: tuple[float, float] | None = None

    @property
    def star_position(self) -> tuple[float, float]:
        return self.position if self.position is not None else (SCA_CENTRE, SCA_CENTRE)

    @property
    def realizations(self) -> int:
        return self.count

    def per_realization(self, residual: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        """(R, 3): each realization's (Delta R / R, Delta e1, Delta e2) for ``residual`` [e-] of Q [e-]."""
        values = np.asarray(residual(self.levels), dtype=np.float64)
        if values.shape != self.levels.shape or not np.all(np.isfinite(values)):
            raise InputError("residual", "must give a finite value [e-] at every charge level the star's resultants reach")
        R = self.count
        out = np.zeros((R, 3))
        for k in range(3):
            out[:, k] = np.bincount(self.owner, weights=self.weights[:, k] * values, minlength=R)
        return out

    def integrate(self, residual: Callable[[np.ndarray], np.ndarray]) -> dict[str, tuple[float, float]]:
        """{metric: (mean, standard error over the realizations)} for size, e1, e2 and |e| (the modulus of
        the e1 and e2 means; its error propagated from theirs)."""
        values = self.per_realization(residual)
        return summarise(values)

    @property
    def beta_slopes(self) -> np.ndarray:
        return self.per_realization(ramps.correction.quadratic_residual(1.0))

    def kernel(self, grid: np.ndarray | None = None) -> Kernel:
        """The kernel on ``grid`` (default: :func:`nodes` up to the largest level)."""
        grid = nodes(float(self.levels.max(initial=1.0))) if grid is None else np.asarray(grid, dtype=np.float64)
        R = self.count
        N = grid.size
        index = np.clip(np.searchsorted(grid, self.levels, side="right") - 1, 0, N - 2)
        t = (self.levels - grid[index]) / (grid[index + 1] - grid[index])
        per = np.zeros((R, N, 3))
        flat = self.owner * N
        for k in range(3):
            w = self.weights[:, k]
            per[:, :, k] = (
                np.bincount(flat + index, weights=w * (1 - t), minlength=R * N)
                + np.bincount(flat + index + 1, weights=w * t, minlength=R * N)
            ).reshape(R, N)
        return Kernel(grid, per, self)


def summarise(values: np.ndarray) -> dict[str, tuple[float, float]]:
    """{size, e1, e2, e: (mean, standard error)} of per-realization (R, 3) responses."""
    R = values.shape[0]
    mean = values.mean(axis=0)
    error = values.std(axis=0, ddof=1) / math.sqrt(R) if R > 1 else np.zeros(3)
    out = {name: (float(mean[k]), float(error[k])) for name, k in _MEASURED.items()}
    modulus = math.hypot(mean[1], mean[2])
    e_error = math.hypot(mean[1] * error[1], mean[2] * error[2]) / modulus if modulus > 0 else float(math.hypot(*error[1:]))
    out["e"] = (modulus, e_error)
    return out


@dataclass(frozen=True, eq=False)
class Kernel:
    """K(Q) on nodes: ``per_node`` (R, N, 3) the node weights k_i per realization (Delta = sum_i k_i r(Q_i))."""

    charge_e: np.ndarray
    per_node: np.ndarray
    response: Response

    @property
    def node_weights(self) -> np.ndarray:
        """(N, 3) mean k_i over realizations."""
        return self.per_node.mean(axis=0)

    def density(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """{metric: (K_i, its standard error)} per e- of charge (trapezoid rule: Delta = int K r dQ)."""
        h = trapezoid_weights(self.charge_e)
        h = np.where(h > 0, h, 1.0)
        R = self.per_node.shape[0]
        mean = self.per_node.mean(axis=0) / h[:, None]
        error = (self.per_node.std(axis=0, ddof=1) / math.sqrt(R) if R > 1 else np.zeros_like(mean)) / h[:, None]
        out = {name: (mean[:, k], error[:, k]) for name, k in _MEASURED.items()}
        # |e| along the quadratic residual's direction (see KERNEL_METRICS).
        u = self._e_direction()
        out["e"] = (u[0] * mean[:, 1] + u[1] * mean[:, 2], np.hypot(u[0] * error[:, 1], u[1] * error[:, 2]))
        return out

    def integrate(self, residual: Callable[[np.ndarray], np.ndarray]) -> dict[str, tuple[float, float]]:
        """The kernel's own sums, sum_i k_i r(Q_i) (r linear between nodes), per realization summarised."""
        values = np.asarray(residual(self.charge_e), dtype=np.float64)
        return summarise(np.einsum("rnk,n->rk", self.per_node, values))

    def signal_range(self, metric: str = "size", fraction: float = SIGNAL_FRACTION) -> tuple[float, float]:
        """(low, high) [e-]: the charge levels that hold the central ``fraction`` of the quadratic residual's
        effect on ``metric`` (the weight |K(Q)| Q^2 on the nodes): the signal range a calibration must get
        right for this star. (0, 0) where the metric does not respond."""
        density = self.density()[metric][0]
        weight = np.abs(density) * trapezoid_weights(self.charge_e) * self.charge_e**2
        total = float(weight.sum())
        if not (total > 0 and math.isfinite(total)):
            return 0.0, 0.0
        cumulative = np.cumsum(weight) / total
        tail = (1.0 - fraction) / 2
        low = self.charge_e[min(int(np.searchsorted(cumulative, tail)), self.charge_e.size - 1)]
        high = self.charge_e[min(int(np.searchsorted(cumulative, 1.0 - tail)), self.charge_e.size - 1)]
        return float(low), float(high)

    def columns(self) -> dict[str, np.ndarray]:
        """``charge_e`` and, per metric, K and ``<metric>_err`` [1 / e-]: the ECSV's and the JSON's columns."""
        out = {"charge_e": self.charge_e}
        for name, (value, error) in self.density().items():
            out[name] = value
            out[f"{name}_err"] = error
        return out

    def fractional_bins(self, per_decade: int = BINS_PER_DECADE) -> dict[str, np.ndarray]:
        """The kernel in bins of 1 / ``per_decade`` of a decade of charge, as the effect of a fractional residual:
        per metric, sum_i k_i Q_i over the nodes in each bin (and its standard error over the realizations), the
        change of the metric were the residual the whole charge (r = Q) in that bin and zero elsewhere. A residual
        of a fraction eps of the charge there changes the metric by eps times it. ``edges_e`` (B + 1,) [e-]: the
        bins' edges, from the decade below the first node above zero to the one above the last. Unlike the density
        K(Q), whose samples at the few levels a uniform sky's resultants take are spikes one node wide, a bin's
        value is an integral: the sky estimate's part and the star's compare by their areas."""
        q = self.charge_e
        positive = q > 0
        low = math.floor(math.log10(float(q[positive].min())) * per_decade + 1e-9)
        high = math.ceil(math.log10(float(q.max())) * per_decade - 1e-9)
        edges = 10.0 ** (np.arange(low, max(high, low + 1) + 1) / per_decade)
        which = np.clip(np.searchsorted(edges, q, side="right") - 1, 0, edges.size - 2)
        weighted = self.per_node * q[None, :, None]  # (R, N, 3): k_i Q_i per realization
        R, B = weighted.shape[0], edges.size - 1
        sums = np.zeros((R, B, 3))
        for k in range(3):
            for r in range(R):
                sums[r, :, k] = np.bincount(which[positive], weights=weighted[r, positive, k], minlength=B)
        mean = sums.mean(axis=0)
        error = sums.std(axis=0, ddof=1) / math.sqrt(R) if R > 1 else np.zeros_like(mean)
        out: dict[str, np.ndarray] = {"edges_e": edges}
        for name, k in _MEASURED.items():
            out[name], out[f"{name}_err"] = mean[:, k], error[:, k]
        u = self._e_direction()
        out["e"] = u[0] * mean[:, 1] + u[1] * mean[:, 2]
        out["e_err"] = np.hypot(u[0] * error[:, 1], u[1] * error[:, 2])
        return out

    def _e_direction(self) -> tuple[float, float]:
        """The unit (e1, e2) direction of the quadratic residual's effect, along which the ``e`` column is taken."""
        slopes = self.response.beta_slopes.mean(axis=0)
        modulus = math.hypot(slopes[1], slopes[2])
        return (slopes[1] / modulus, slopes[2] / modulus) if modulus > 0 else (0.0, 0.0)

    def meta(self) -> dict:
        """What the kernel is for: the star, its limits, the identity it satisfies, the quadratic residual's
        slopes through it and the signal range each metric draws on, its flags and conditions."""
        from ..serialise import json_safe

        slopes = self.integrate(ramps.correction.quadratic_residual(1.0))
        return json_safe(
            {
                "magnitude": self.response.magnitude,
                "flux_electrons": self.response.flux_electrons,
                "full_well_e": self.response.full_well_e,
                "saturation_e": self.response.saturation_e,
                "realizations": self.response.realizations,
                "quadratic_identity": "sum of K(Q) (-Q^2) dQ over the nodes = d metric / d Delta_beta, the solver's slope",
                "quadratic_slopes": {k: {"value": v, "uncertainty": e} for k, (v, e) in slopes.items()},
                "signal_fraction": SIGNAL_FRACTION,
                "signal_range_e": {name: list(self.signal_range(name)) for name in KERNEL_METRICS},
                "units": dict(KERNEL_UNITS),
                "flags": [str(f) for f in self.response.flags],
                "flag_codes": [str(getattr(f, "code", "")) for f in self.response.flags],
                "conditions": self.response.conditions,
            }
        )

    def table(self):
        """An astropy Table: ``charge_e`` and per metric K and ``<metric>_err`` [1 / e-], with the meta."""
        return kernel_table(self.columns(), self.meta())

    def to_dict(self) -> dict:
        """JSON: the table's columns by the same names, the kernel in tenths of a decade as a fractional residual's
        effect (``fractional_bins``), and its meta."""
        from ..serialise import json_number

        def listed(columns: dict) -> dict:
            return {k: [json_number(v) for v in values] for k, values in columns.items()}

        return {"columns": listed(self.columns()), "fractional_bins": listed(self.fractional_bins()), "meta": self.meta()}


def kernel_table(columns: dict, meta: dict):
    """The ECSV table of a kernel from its columns and meta (``Kernel.columns``, ``Kernel.meta``, or a kernel's
    JSON as ``Kernel.to_dict`` gives it, None for a non-finite value): one owner of the file's column names,
    units and descriptions, for the CLI's ``--output`` and the service's download alike."""
    from astropy.table import Table

    names = ["charge_e", *(f"{n}{tail}" for n in KERNEL_METRICS for tail in ("", "_err"))]
    missing = [n for n in names if n not in columns]
    if missing:
        raise InputError("kernel", f"not a kernel: no column {missing[0]!r}")
    table = Table({n: np.array([np.nan if v is None else v for v in columns[n]], dtype=np.float64) for n in names})
    for name in names:
        table[name].unit = KERNEL_UNITS[name]
    for name in KERNEL_METRICS:
        table[name].description = f"d {name} / d r per e- of charge: Delta {name} = int K(Q) r(Q) dQ, r in e-"
        table[f"{name}_err"].description = f"standard error of {name} over the centroid realizations"
    table.meta.update(meta)
    return table
