"""Simulation and slope results, their statistics and serialisation."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from nlpsf.flags import codes as flag_codes

from .. import detector, moments
from .prepared import Scene


@dataclass(frozen=True)
class Statistic:
    """Mean, standard deviation and standard error of the mean over realizations (None if no data)."""

    mean: float | None
    std: float | None
    stderr: float | None
    count: int

    @classmethod
    def of(cls, values: np.ndarray) -> Statistic:
        values = np.asarray(values, dtype=np.float64)
        values = values[np.isfinite(values)]
        if values.size == 0:
            return cls(None, None, None, 0)
        std = float(values.std(ddof=1)) if values.size > 1 else 0.0
        return cls(float(values.mean()), std, std / math.sqrt(values.size), int(values.size))

    @property
    def std_error(self) -> float | None:
        """The standard error of ``std`` itself, std / sqrt(2 (n - 1)): the large-n value for
        normally distributed draws (None with fewer than two). A scatter point's error bar."""
        if self.std is None or self.count < 2:
            return None
        return self.std / math.sqrt(2 * (self.count - 1))

    def to_dict(self) -> dict:
        return {"mean": self.mean, "std": self.std, "stderr": self.stderr}


@dataclass(frozen=True)
class SimulationResult:
    """NL-induced change of PSF size and ellipticity for one (magnitude, beta, sigma_beta)."""

    conditions: dict
    magnitude: float
    beta: float
    beta_convention: str
    beta_paper: float
    sigma_beta: float
    realizations: int
    flux_electrons: float
    #: The star's brightest pixel before the NL [e-], over every sub-pixel centroid (``star_peak_electrons``).
    peak_electrons: float
    reference: dict
    dR_over_R: Statistic
    de1: Statistic
    de2: Statistic
    failed_realizations: int
    flags: list[str]
    elapsed_s: float
    centroid_offset: list[float] | None = None
    extras: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        c = self.conditions
        return {
            "band": c["band"],
            "sca": c["sca"],
            "magnitude": self.magnitude,
            "beta": self.beta,
            "beta_convention": self.beta_convention,
            "beta_paper": self.beta_paper,
            "nl_model": detector.describe(self.beta_convention),
            "sigma_beta": self.sigma_beta,
            "realizations": self.realizations,
            "exptime_s": c["exptime_s"],
            "flux_electrons": self.flux_electrons,
            "peak_electrons": self.peak_electrons,
            "full_well_electrons": c["full_well_e"],
            "reference": self.reference,
            "dR_over_R": self.dR_over_R.to_dict(),
            "de1": self.de1.to_dict(),
            "de2": self.de2.to_dict(),
            "failed_realizations": self.failed_realizations,
            "flags": [str(f) for f in self.flags],
            "flag_codes": flag_codes(self.flags),
            "elapsed_s": self.elapsed_s,
            "fidelity": c["fidelity"],
            "centroid_offset_fine_pixels": self.centroid_offset,
            "conditions": c,
            **self.extras,
        }


def _reference_summary(scene: Scene, index: slice | int | None = None) -> dict:
    ref = scene.reference
    pick = slice(None) if index is None else index
    ok = ref.ok[pick]
    e1, e2, sigma = (np.atleast_1d(getattr(ref, k)[pick])[np.atleast_1d(ok)] for k in ("e1", "e2", "sigma"))
    grid = scene.config.grid
    if e1.size == 0:
        return {"e1": None, "e2": None, "sigma": None, "sigma_arcsec": None}
    return {
        "e1": float(e1.mean()),
        "e2": float(e2.mean()),
        "sigma": float(sigma.mean()),
        "sigma_arcsec": float(sigma.mean() * grid.scale_arcsec),
    }


def _metrics(fit: moments.Moments, reference: moments.Moments, ref_index=None):
    """Delta R / R, Delta e1, Delta e2 per realization (NaN where a fit failed) and the status."""
    if ref_index is not None:
        reference = moments.select(reference, np.full(len(fit), ref_index))
    ok = fit.ok & reference.ok
    d_r, d_e1, d_e2 = (np.where(ok, v, np.nan) for v in moments.differences(fit, reference))
    status = np.where(reference.ok, fit.status, reference.status)
    return d_r, d_e1, d_e2, status


@dataclass(frozen=True)
class SlopeResult:
    """Slopes at one magnitude: the paper's Fig. 3 (bias) and Fig. 5 (scatter) ordinates.

    ``bias[metric]``: d(metric)/d(beta) at beta0, a statistic over centroid realizations.
    ``scatter[metric]``: sigma(metric) / sigma_beta for independent per-pixel beta, with its
    uncertainty; ``scatter_basis`` says how it was obtained.
    """

    conditions: dict
    magnitude: float
    beta0: float
    beta_convention: str
    flux_electrons: float
    #: The star's brightest pixel before the NL [e-], over every sub-pixel centroid (``star_peak_electrons``).
    peak_electrons: float
    bias: dict[str, Statistic]
    scatter: dict[str, dict[str, float | None]]
    scatter_basis: str
    failed_realizations: int
    flags: list[str]
    elapsed_s: float
    extras: dict = field(default_factory=dict)

    def slope(self, mode: str, parts: Sequence[str]) -> tuple[float | None, float | None]:
        """(slope, its standard error) of one metric (``parts`` one of METRICS) or of |e| (parts
        ``("de1", "de2")``, combined in quadrature); (None, None) where the simulation failed."""
        values, errors = [], []
        for part in parts:
            if mode == "bias":
                values.append(self.bias[part].mean)
                errors.append(self.bias[part].stderr or 0.0)
            else:
                values.append(self.scatter[part]["value"])
                errors.append(self.scatter[part]["uncertainty"] or 0.0)
        if any(v is None for v in values):
            return None, None
        if len(values) == 1:
            return float(values[0]), float(errors[0])
        value = math.hypot(*values)
        error = math.hypot(values[0] * errors[0], values[1] * errors[1]) / value if value > 0 else math.hypot(*errors)
        return value, error

    def to_dict(self) -> dict:
        c = self.conditions
        return {
            "band": c["band"],
            "sca": c["sca"],
            "magnitude": self.magnitude,
            "beta0": self.beta0,
            "beta_convention": self.beta_convention,
            "exptime_s": c["exptime_s"],
            "flux_electrons": self.flux_electrons,
            "peak_electrons": self.peak_electrons,
            "bias_slope": {k: v.to_dict() for k, v in self.bias.items()},
            "scatter_slope": self.scatter,
            "scatter_basis": self.scatter_basis,
            "failed_realizations": self.failed_realizations,
            "flags": [str(f) for f in self.flags],
            "flag_codes": flag_codes(self.flags),
            "elapsed_s": self.elapsed_s,
            "fidelity": c["fidelity"],
            "conditions": c,
            **self.extras,
        }


def pooled_statistic(parts: Sequence[Statistic]) -> Statistic:
    """One statistic over the realizations of independent ``parts`` (each a mean over its own
    centroids): the pooled mean, and the standard deviation from the within- and between-part sums
    of squares, as if every realization had been in one sample."""
    filled = [p for p in parts if p.mean is not None and p.count > 0]
    count = sum(p.count for p in filled)
    if count == 0:
        return Statistic(None, None, None, 0)
    mean = sum(p.count * p.mean for p in filled) / count
    if count < 2:
        return Statistic(float(mean), 0.0, 0.0, count)
    squares = sum((p.count - 1) * (p.std or 0.0) ** 2 + p.count * (p.mean - mean) ** 2 for p in filled)
    std = math.sqrt(squares / (count - 1))
    return Statistic(float(mean), std, std / math.sqrt(count), count)


def pooled(results: Sequence[SlopeResult]) -> SlopeResult:
    """The slopes of several independent batches of centroids at one magnitude, as one result: a
    linear-response answer (bias and scatter both means over centroids, ``_linear_slopes``) needs
    more centroids than one prepared scene should hold in memory where pixels lose resultants."""
    if len(results) == 1:
        return results[0]
    first = results[0]
    if any(r.scatter_basis != first.scatter_basis or r.magnitude != first.magnitude for r in results):
        raise ValueError("only batches of one linear-response simulation at one magnitude are pooled")
    bias = {name: pooled_statistic([r.bias[name] for r in results]) for name in first.bias}
    scatter = {}
    for name in first.scatter:
        weights = [r.bias[name].count for r in results]
        values = [r.scatter[name]["value"] for r in results]
        errors = [r.scatter[name]["uncertainty"] or 0.0 for r in results]
        total = sum(w for w, v in zip(weights, values, strict=True) if v is not None)
        if total == 0:
            scatter[name] = {"value": None, "uncertainty": None}
            continue
        value = sum(w * v for w, v in zip(weights, values, strict=True) if v is not None) / total
        error = math.sqrt(sum((w * u) ** 2 for w, v, u in zip(weights, values, errors, strict=True) if v is not None)) / total
        scatter[name] = {"value": value, "uncertainty": error}
    flags, seen = [], set()
    for flag in (f for r in results for f in r.flags):
        if str(flag) not in seen:
            seen.add(str(flag))
            flags.append(flag)
    counts = [max(s.count for s in r.bias.values()) for r in results]
    extras = {**first.extras, "batches": {"count": len(results), "realizations": counts}}
    return replace(
        first,
        peak_electrons=max(r.peak_electrons for r in results),
        bias=bias,
        scatter=scatter,
        failed_realizations=sum(r.failed_realizations for r in results),
        flags=flags,
        elapsed_s=sum(r.elapsed_s for r in results),
        extras=extras,
    )
