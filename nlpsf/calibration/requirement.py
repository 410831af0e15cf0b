"""The requirement in the calibrator's terms: a residual's effect on a star, the two-of-three calculator for a
residual shape's scale, and the envelope eps(Q) a calibration's residuals must stay within.

For a residual s x shape(Q) the metric is linear in the scale: Delta = s I(m), I(m) = integral K_m(Q) shape(Q) dQ
(``kernel.Response.integrate``). So, as for beta: tolerance T = |s I(m)|; given two of (scale, tolerance,
magnitude) the third follows, the magnitude being the brightest star (within the simulated range) whose
|s I(m)| stays within T. The envelope over a magnitude range is the largest scale the tolerance allows at
the worst magnitude, times the shape: eps(Q) = T / max_m |I(m)| x |shape(Q)|.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from nlpsf.sim import experiment

from ..checks import InputError, check_magnitude
from .kernel import EFFECT_UNITS, Response, nodes
from .response import star_response

#: A progress report: (steps done, steps in all, what is being done).
Progress = Callable[[int, int, str], None]
#: Magnitude step of a scan (the magnitude solve refines between its points by bisection).
SCAN_STEP_MAG = 0.25
BISECTION_STEPS = 24


def scene_for(request) -> experiment.Scene:
    """The prepared simulation a solve request's fresh slopes run (its scene, readout, exposure, pupil rule),
    at the linear level."""
    from dataclasses import replace

    from nlpsf.slopes.source import Slopes
    from nlpsf.solve.solver import plan

    linear = replace(request, fidelity="linear", accuracy=None)
    return Slopes.for_request(linear, plan(linear)).prepare()


#: Below this fraction of the sum of its terms' sizes, a residual's effect is a cancellation to rounding: none.
CANCELLED = 1e-9
NO_RESPONSE = (
    " (its effect cancels: a residual that is the same fraction of the charge everywhere, a gain error, scales the "
    "image and the sky alike and leaves size and ellipticity unchanged)"
)


def response_to(response, shape: Callable, metric: str) -> tuple[float, float]:
    """(effect, standard error) of ``shape`` on ``metric``; (0, error) where the effect is a cancellation to
    rounding (below CANCELLED of the sum of its terms' sizes), as a gain error's is."""
    value, error = response.integrate(shape)[metric]
    terms = np.abs(response.weights * np.asarray(shape(response.levels), dtype=np.float64)[:, None]).sum(axis=0)
    if abs(value) <= CANCELLED * float(terms.max()) / max(response.count, 1):
        return 0.0, error
    return value, error


@dataclass(frozen=True)
class Effect:
    """A residual's effect on one star: {metric: (value, standard error)} and what it is for."""

    magnitude: float
    values: dict
    conditions: dict
    flags: list

    def to_dict(self) -> dict:
        return {
            "magnitude": self.magnitude,
            "bias": {k: {"value": v, "uncertainty": e} for k, (v, e) in self.values.items()},
            "units": dict(EFFECT_UNITS),
            "conditions": self.conditions,
            "flags": [str(f) for f in self.flags],
            "flag_codes": [str(getattr(f, "code", "")) for f in self.flags],
        }


def effect(response: Response, residual: Callable, description: str) -> Effect:
    values = response.integrate(residual)
    conditions = dict(response.conditions)
    conditions["residual"] = description
    conditions["method"] = (
        "first order in the residual: the pipeline's correction on every resultant, the moments' linear response at a "
        "perfect calibration (docs/calibration.md)"
    )
    return Effect(response.magnitude, values, conditions, response.flags)


@dataclass(frozen=True)
class ScaleAnswer:
    """The two-of-three answer for a residual shape: scale, tolerance, magnitude, with the response I(m)."""

    metric: str
    shape: str
    scale: float
    tolerance: float
    magnitude: float
    response: float
    response_error: float
    solved_for: str
    notes: list

    def to_dict(self) -> dict:
        return {
            "metric": self.metric,
            "shape": self.shape,
            "scale": self.scale,
            "tolerance": self.tolerance,
            "magnitude": self.magnitude,
            "response_per_unit_scale": self.response,
            "response_uncertainty": self.response_error,
            "solved_for": self.solved_for,
            "relation": "tolerance = |scale x integral K(Q) shape(Q) dQ|",
            "notes": self.notes,
        }


def solve_scale(
    scene: experiment.Scene,
    metric: str,
    shape: Callable,
    shape_name: str,
    raw_beta: float,
    scale: float | None = None,
    tolerance: float | None = None,
    magnitude: float | None = None,
    faint: float = 26.0,
    progress: Progress | None = None,
) -> ScaleAnswer:
    """Given two of ``scale``, ``tolerance``, ``magnitude``, the third (see the module). ``progress(done, total,
    message)`` after each star simulated (a magnitude solve's total is its scan and its bisection)."""
    given = [name for name, v in (("scale", scale), ("tolerance", tolerance), ("magnitude", magnitude)) if v is not None]
    if len(given) != 2:
        raise InputError("scale", f"give exactly two of scale, tolerance, magnitude (got {', '.join(given) or 'none'})")
    if tolerance is not None and not (math.isfinite(tolerance) and tolerance > 0):
        raise InputError("tolerance", "must be a positive number")
    if scale is not None and not (math.isfinite(scale) and scale != 0):
        raise InputError("scale", "must be a finite, non-zero number")

    done = [0]

    def at(m: float, total: int = 1) -> tuple[float, float]:
        value = response_to(star_response(scene, m, raw_beta), shape, metric)
        done[0] += 1
        if progress is not None:
            progress(done[0], total, f"star m = {m:.3f} simulated")
        return value

    if magnitude is not None:
        magnitude = check_magnitude(magnitude)
        value, error = at(magnitude)
        if scale is None:
            if value == 0:
                raise InputError("shape", f"{metric} does not respond to this shape at m = {magnitude:g}{NO_RESPONSE}")
            scale = tolerance / abs(value)
            return ScaleAnswer(metric, shape_name, scale, tolerance, magnitude, value, error, "scale", [])
        return ScaleAnswer(metric, shape_name, scale, abs(scale * value), magnitude, value, error, "tolerance", [])
    # The magnitude: the brightest star whose error stays within the tolerance (scanned, then bisected).
    low = _brightest_usable(scene)
    grid = np.arange(low, faint + 1e-9, SCAN_STEP_MAG)
    total = grid.size + BISECTION_STEPS + 1
    errors = np.array([abs(scale * at(float(m), total)[0]) for m in grid])
    within = errors <= tolerance
    notes = []
    if within[0]:
        m, notes = float(grid[0]), [f"every simulated star from the ramp's limit (m = {grid[0]:.2f}) meets the tolerance"]
    elif not within[-1]:
        raise InputError("tolerance", f"no star brighter than m = {faint:g} meets it (|error| {errors[-1]:.3g} at m = {faint:g})")
    else:
        last_bad = int(np.flatnonzero(~within)[-1])
        a, b = float(grid[last_bad]), float(grid[last_bad + 1])
        for _ in range(BISECTION_STEPS):
            middle = 0.5 * (a + b)
            if abs(scale * at(middle, total)[0]) <= tolerance:
                b = middle
            else:
                a = middle
        m = b
    value, error = at(m, total)
    return ScaleAnswer(metric, shape_name, scale, tolerance, m, value, error, "magnitude", notes)


def _brightest_usable(scene: experiment.Scene) -> float:
    """The brightest star whose brightest pixel keeps the resultants a slope needs (the ramp's limit), or the
    final frame's saturation, rounded up to 0.01 mag."""
    from nlpsf.slopes.tablebuild import saturation_magnitude

    config = scene.config
    final = saturation_magnitude(scene.star_peak_fraction, config)
    if config.ramp is None:
        return math.ceil(final * 100) / 100
    shift = config.ramp.saturation_shift_mag(config.exptime_s, config.full_well_e, 5e-7, config.scene.background_e)
    return math.ceil((final - shift) * 100) / 100 + 0.01


def envelope(
    scene: experiment.Scene,
    metric: str,
    shape: Callable,
    shape_name: str,
    raw_beta: float,
    tolerance: float,
    magnitudes: tuple[float, float],
    step: float = SCAN_STEP_MAG,
    progress: Progress | None = None,
) -> dict:
    """eps(Q): the largest residual of ``shape``'s family allowed at each charge level for every star in
    ``magnitudes`` (brightest, faintest): T / max_m |I(m)| x |shape(Q)|, on the kernel's nodes up to the largest
    level any of them reaches."""
    bright, faint = sorted(check_magnitude(v) for v in magnitudes)
    grid = np.arange(bright, faint + 1e-9, step)
    worst, worst_m, top = 0.0, None, 1.0
    for index, m in enumerate(grid):
        if progress is not None:
            progress(index, grid.size, f"star m = {m:.2f} of {bright:.2f}-{faint:.2f}")
        response = star_response(scene, float(m), raw_beta)
        value = abs(response_to(response, shape, metric)[0])
        top = max(top, float(response.levels.max(initial=1.0)))
        if value > worst:
            worst, worst_m = value, float(m)
    if worst == 0:
        raise InputError("shape", f"{metric} does not respond to this shape over the magnitude range{NO_RESPONSE}")
    scale = tolerance / worst
    charge = nodes(top, ratio=1.05)
    epsilon = scale * np.abs(np.asarray(shape(charge), dtype=np.float64))
    return {
        "charge_e": charge.tolist(),
        "epsilon_e": epsilon.tolist(),
        "scale": scale,
        "shape": shape_name,
        "metric": metric,
        "tolerance": tolerance,
        "worst_magnitude": worst_m,
        "magnitudes": [bright, faint],
        "relation": "eps(Q) = tolerance / max over the magnitudes of |integral K_m(Q) shape(Q) dQ| x |shape(Q)|",
    }
