"""Enough centroids where pixels lose resultants (issue 28, item 1).

Between a ramp's saturation limits the slope jumps from centroid to centroid as each pixel loses a
resultant, so a fresh answer there needs many more centroids than the tables' 100 for its statistical
error to fit its target. Two answers simulate there: the Roman default at a position between the
limits (flag ``default_between_limits``; held to 5 % in size and 10 % in e, as the field grid is
judged there) and an ``--accuracy`` answer (flag ``accuracy_centroids``; held to its accuracy). Both
choose their count from a pilot's relative error r: n (r / t)^2 centroids for a target t. Where the
slope is small against its spread a pilot's mean is far off, so r is measured again over the count
chosen and the count chosen again from it, :data:`ROUNDS` times at most, with a margin; the flag then
states each error reached. An e component small against |c_e| is held to its share of |c_e|
(:func:`_scale`), as its model uncertainty is. The simulations run in batches (``slopes.source.BATCH_REALIZATIONS``), so
the memory stays a batch's.
"""

from __future__ import annotations

import dataclasses
import math

from nlpsf.flags import FlagCode, make

from .validity import COMPONENT_SMALL_FRACTION, between_limits_flag

#: What a Roman-default answer between the saturation limits is held to against a fresh full
#: simulation there (5 % in size, 10 % in e); its statistical error is kept within
#: :data:`STATISTICAL_SHARE` of it, as an accuracy answer's (``accuracy.STATISTICAL_SHARE``).
DEFAULT_TARGET = {"size": 0.05, "e": 0.10, "e1": 0.10, "e2": 0.10}
STATISTICAL_SHARE = 0.5
#: The most centroids a default answer there simulates: ~2.4 ms of CPU each on H158's HLWAS ramp,
#: about 15 s at the cap (an ``--accuracy`` answer's cap is ``accuracy.MAX_REALIZATIONS``).
DEFAULT_MAX_REALIZATIONS = 6400
#: Times the count is chosen again from the error the last count reached.
ROUNDS = 2
#: The margin over n (r / t)^2: r is itself measured, and falling short costs another round.
MARGIN = 1.2


@dataclasses.dataclass(frozen=True)
class Reached:
    """What the rounds reached: the count, the relative statistical error over each count tried,
    the last error, and the count the last error asks for."""

    used: int
    tried: tuple[tuple[int, float], ...]
    relative: float
    needed: float
    #: What the errors are relative to (:func:`_scale`).
    against: str = "the slope"

    def met(self, target: float) -> bool:
        return self.relative <= target * (1 + 1e-9)

    def errors(self) -> str:
        return "; ".join(f"{r:.2g} over {n}" for n, r in self.tried)


def _rounds(request, the_plan, slopes, slopes_for, target: float, cap: int):
    """(plan, slopes, Reached): the count grown until the slope's statistical error at the request's
    magnitude is within ``target`` or ``cap`` is reached."""
    used, tried = int(the_plan.realizations), []
    for round_ in range(ROUNDS + 1):
        value, error, _ = slopes.at(float(request.magnitude))
        scale = _scale(request, slopes, value)
        relative = abs(error / scale) if scale else math.inf
        against = "the slope" if scale == abs(value) else f"{COMPONENT_SMALL_FRACTION:g} |c_e|, the component being small"
        tried.append((used, relative))
        needed = used * (relative / target) ** 2 if math.isfinite(relative) else math.inf
        following = min(cap, math.ceil(MARGIN * needed)) if math.isfinite(needed) else cap
        if relative <= target or following <= used or round_ == ROUNDS:
            break
        used = int(following)
        the_plan = dataclasses.replace(the_plan, realizations=used)
        slopes, earlier = slopes_for(request, the_plan), slopes
        slopes.reuse_batches(earlier)
    return the_plan, slopes, Reached(used, tuple(tried), relative, needed, against)


def _scale(request, slopes, value: float) -> float:
    """What an answer's statistical error is relative to: its slope; for an e component small
    against |c_e| (``validity.COMPONENT_SMALL_FRACTION``), that fraction of |c_e|: the model's parts
    move a component by a fraction of |c_e| (its answer is flagged ``e_component_small``), and pinning
    a slope near zero to 10 % of itself would take centroids without end."""
    ratio = slopes.modulus_over_component(float(request.magnitude)) if request.metric in ("e1", "e2") else None
    if not ratio:
        return abs(value)
    return max(abs(value), COMPONENT_SMALL_FRACTION * ratio * abs(value))


def _note(the_plan, code: FlagCode):
    return next((i for i, n in enumerate(the_plan.notes) if getattr(n, "code", None) == code), None)


def _with_note(the_plan, index: int, flag, **changes):
    notes = (*the_plan.notes[:index], flag, *the_plan.notes[index + 1 :])
    return dataclasses.replace(the_plan, notes=notes, **changes)


def enough_centroids(request, the_plan, slopes, slopes_for):
    """(plan, slopes) of an answer with enough centroids where pixels lose resultants (the module
    docstring); elsewhere the two come back unchanged. ``slopes_for(request, plan)``: the solver's."""
    if request.magnitude is None or the_plan.realizations is None:
        return the_plan, slopes
    index = _note(the_plan, FlagCode.DEFAULT_BETWEEN_LIMITS)
    if index is not None:
        return _default_between_limits(request, the_plan, slopes, slopes_for, index)
    index = _note(the_plan, FlagCode.ACCURACY_CENTROIDS)
    if index is not None:
        return _accuracy(request, the_plan, slopes, slopes_for, index)
    return the_plan, slopes


def _default_between_limits(request, the_plan, slopes, slopes_for, index: int):
    held = DEFAULT_TARGET[request.metric]
    target = STATISTICAL_SHARE * held
    the_plan, slopes, reached = _rounds(request, the_plan, slopes, slopes_for, target, DEFAULT_MAX_REALIZATIONS)
    why = (
        f"the slope's statistical error, relative to {reached.against}, is {reached.errors()} centroids, "
        f"against {target:.2g} (half the "
        f"{held:.0%} a default answer in {request.metric} is held to here), "
        + (
            "within it"
            if reached.met(target)
            else f"above it: about {reached.needed:.3g} centroids would be needed, more than the {reached.used} "
            "an answer simulates"
        )
    )
    values = the_plan.notes[index].values
    limits = (values["m_sat"], values["m_sat_final"])
    flag = between_limits_flag((values["x"], values["y"]), values["magnitude"], limits, reached.used, why)
    return _with_note(the_plan, index, flag), slopes


def _accuracy(request, the_plan, slopes, slopes_for, index: int):
    from .accuracy import ACCURACY_CENTROIDS_QUOTES, MAX_REALIZATIONS

    values = dict(the_plan.notes[index].values)
    the_plan, slopes, reached = _rounds(request, the_plan, slopes, slopes_for, float(values["target"]), MAX_REALIZATIONS)
    met = reached.met(float(values["target"]))
    verdict = (
        "within it"
        if met
        else f"above it: {reached.needed:.3g} centroids would be needed, more than the {reached.used} an answer simulates"
    )
    centroids = {**the_plan.model.get("centroids", {}), **values}
    errors = reached.errors() + ("" if reached.against == "the slope" else f", relative to {reached.against}")
    centroids.update(used=reached.used, reached_error=reached.relative, met=met, verdict=verdict, errors=errors)
    flag = make(FlagCode.ACCURACY_CENTROIDS, **{k: centroids[k] for k in ACCURACY_CENTROIDS_QUOTES})
    return _with_note(the_plan, index, flag, model={**the_plan.model, "centroids": centroids}), slopes
