"""A solve's answer: :class:`Solution`, whose uncertainty is an :class:`Uncertainty` holding its
named parts and the one rule that combines them (``Uncertainty.total``)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from nlpsf.flags import codes as flag_codes
from nlpsf.serialise import json_number


@dataclass(frozen=True)
class Uncertainty:
    """The uncertainty of a solved quantity, in its own unit, by part (None: the part is unknown
    or the answer has no uncertainty).

    - ``statistical``: the slope's standard error (realizations of the tables or the simulation);
    - ``fidelity``: the fidelity level's measured systematic error (``nlpsf tradeoff``);
    - ``optical_model``: the optical model against the official post-CDR PSF statistics;
    - ``effects``: the scene effects the answer leaves out (``Solution.model``);
    - ``pupil_scale``: the pupil-mask scale rule (galsim against header).
    """

    statistical: float | None = None
    fidelity: float | None = None
    optical_model: float | None = None
    effects: float | None = None
    pupil_scale: float | None = None

    #: The combination rule, in words (``total`` and ``model`` compute it).
    RULE = (
        "total = hypot(statistical, fidelity, effects, max(optical_model, pupil_scale)): the official-PSF "
        "comparison and the pupil-scale rule both measure the optical model's distance from Roman's, so the "
        "larger counts, not both; model = hypot(effects, pupil_scale)"
    )

    @property
    def total(self) -> float | None:
        if self.statistical is None:
            return None
        optical = max(self.optical_model or 0.0, self.pupil_scale or 0.0)
        return math.hypot(self.statistical, self.fidelity or 0.0, self.effects or 0.0, optical)

    @property
    def model(self) -> float | None:
        """What the scene the answer leaves out adds: its effects and the pupil-scale rule."""
        return None if self.effects is None else math.hypot(self.effects, self.pupil_scale or 0.0)

    @classmethod
    def none(cls) -> Uncertainty:
        """An answer without uncertainty (e.g. a metric insensitive to beta)."""
        return cls()

    def to_dict(self) -> dict:
        return {
            "statistical": json_number(self.statistical),
            "fidelity": json_number(self.fidelity),
            "optical_model": json_number(self.optical_model),
            "effects": json_number(self.effects),
            "pupil_scale": json_number(self.pupil_scale),
            "total": json_number(self.total),
            "rule": self.RULE,
        }


@dataclass(frozen=True)
class Solution:
    """The answer, with the two given values, its uncertainty and the conditions it holds for."""

    band: str
    sca: int
    metric: str
    mode: str
    beta0: float
    exptime: float
    full_well: float
    precision: float | None
    tolerance: float | None
    magnitude: float | None
    solved_for: str
    #: The uncertainty of the solved quantity, by part, and the rule combining them.
    parts: Uncertainty
    slope: float | None
    slope_uncertainty: float | None
    saturation_magnitude: float
    brightest_usable_magnitude: float | None
    binding_limit: str | None
    nonlinearity_magnitude: float | None
    flags: list[str]
    fidelity: str
    conditions: dict
    elapsed_s: float = field(default=0.0, compare=False)
    #: Stars (and dithers) averaged by the PSF model the scatter-mode answer holds for.
    stars: int = 1
    applies_to: str = ""
    #: The shear budget given (or, with a size ratio alone, implied): ``Budget``-like dict.
    shear: dict | None = None
    #: Scene effects the answer leaves out (name, impact on the metric's slope, relative), the SCA
    #: spread and the pupil-scale rule, and the uncertainty they add in the solved quantity's units;
    #: measured at the point with ``accuracy``, else read from the shipped measurement
    #: (``scripts/model_uncertainty.py``); None only where the answer has no uncertainty.
    model: dict | None = None
    #: The single-final-frame rule's saturation magnitude (equal to ``saturation_magnitude`` without a ramp).
    final_frame_saturation_magnitude: float | None = None
    #: The answer that holds across the uncertainty (``model_part.answer_extras``): the solved
    #: quantity if the slope's modulus were |c| (1 + U), U the bound and its coverage named.
    conservative: dict | None = None
    #: What varies from star to star, as ranges the answer holds over (not uncertainties): each
    #: range's ends, the slope's relative change there and the solved quantity there.
    ranges: dict | None = None

    @property
    def uncertainty(self) -> float | None:
        return self.parts.total

    @property
    def uncertainty_statistical(self) -> float | None:
        return self.parts.statistical

    @property
    def uncertainty_fidelity(self) -> float | None:
        return self.parts.fidelity

    @property
    def uncertainty_optical_model(self) -> float | None:
        """The optical model's share (Cycle-9 Zernikes against the official post-CDR PSF statistics)."""
        return self.parts.optical_model

    @property
    def uncertainty_model(self) -> float | None:
        return self.parts.model

    def to_dict(self) -> dict:
        return {
            "band": self.band,
            "sca": self.sca,
            "metric": self.metric,
            "mode": self.mode,
            "beta0": self.beta0,
            "exptime": self.exptime,
            "full_well": self.full_well,
            "precision": json_number(self.precision),
            "tolerance": json_number(self.tolerance),
            "magnitude": json_number(self.magnitude),
            "solved_for": self.solved_for,
            "uncertainty": json_number(self.uncertainty),
            "uncertainty_statistical": json_number(self.uncertainty_statistical),
            "uncertainty_fidelity": json_number(self.uncertainty_fidelity),
            "uncertainty_optical_model": json_number(self.uncertainty_optical_model),
            "uncertainty_model": json_number(self.uncertainty_model),
            "model": self.model,
            "slope": json_number(self.slope),
            "slope_uncertainty": json_number(self.slope_uncertainty),
            "saturation_magnitude": json_number(self.saturation_magnitude),
            "final_frame_saturation_magnitude": json_number(self.final_frame_saturation_magnitude),
            "brightest_usable_magnitude": json_number(self.brightest_usable_magnitude),
            "binding_limit": self.binding_limit,
            "nonlinearity_magnitude": json_number(self.nonlinearity_magnitude),
            "flags": [str(f) for f in self.flags],
            "flag_codes": flag_codes(self.flags),
            "fidelity": self.fidelity,
            "stars": self.stars,
            "applies_to": self.applies_to,
            "shear": self.shear,
            "conservative": self.conservative,
            "ranges": self.ranges,
            "conditions": self.conditions,
            "elapsed_s": self.elapsed_s,
        }
