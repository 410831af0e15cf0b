"""What a solve's answer is valid for: the flags and refusals of its magnitude against the tables'
range, saturation (final frame and ramp), the linear regime of T = c p beta0, and an ellipticity
component too small against the modulus to carry a requirement.

``slopes`` arguments are the solver's c(m) at the request (``nlpsf.solve.solver``).
"""

from __future__ import annotations

import math

from nlpsf.checks import InputError
from nlpsf.flags import Flag, FlagCode, make
from nlpsf.slopes import tables

#: Past this Δβ Q_peak the error is no longer linear in Δβ and T = c p β0 stops describing it.
LINEAR_REGIME_LIMIT = 0.05
#: An e1 / e2 slope below this fraction of |c_e| = hypot(c_e1, c_e2) is flagged as small
#: (``FlagCode.E_COMPONENT_SMALL``): the model's parts move both components by a fraction of |c_e|,
#: so a component this small has a relative uncertainty of order part / fraction. The same cut as
#: docs/validation.md's "near zero" points.
COMPONENT_SMALL_FRACTION = 0.3
#: A slope within this many standard errors of zero is "consistent with zero" for that flag.
COMPONENT_ZERO_SIGMAS = 2.0


def _peak_electrons(slopes, magnitude: float) -> float:
    own = slopes.own_peak_electrons(magnitude) if hasattr(slopes, "own_peak_electrons") else None
    if own is not None:
        return own  # the simulated star's own peak, as its saturation limits are
    table = slopes.table
    flux = float(table.flux_at(magnitude - 2.5 * math.log10(slopes.exptime / table.exptime_s)))
    return flux * table.peak_fraction * int(table.settings["oversampling"]) ** 2


def _magnitude_flags(slopes, magnitude: float, region: int, m_sat: float, beta0: float) -> list[str]:
    lo, hi = slopes.range()
    if region < 0:
        peak = _peak_electrons(slopes, magnitude)
        if 2 * beta0 * peak >= 1:
            raise InputError(
                "magnitude",
                f"an m={magnitude:g} star is too bright for beta0={beta0:g}: the quadratic nonlinearity is not monotonic "
                f"there (2 beta0 Q_peak = {2 * beta0 * peak:.2f} >= 1), so S = Q - beta Q^2 does not describe the detector",
            )
        # The tables hold the slopes in beta0 x flux (the beta Q rule), so where they stop depends on
        # beta0; saturation does not. Say both, with this star's own numbers.
        full_well = float(getattr(slopes, "full_well", slopes.table.settings["full_well_e"]))
        reach = beta0 * _peak_electrons(slopes, lo)
        raise InputError(
            "magnitude",
            f"m={magnitude:g} is past the tables at beta0={beta0:g}: they hold the NL strength beta0 x Q_peak up to "
            f"{reach:.3g} (built to {tables.BRIGHT_MARGIN_MAG} mag past saturation at their own beta0 = "
            f"{slopes.table.beta0:g}), reached at m={lo:.2f} at this beta0, and this star's is {beta0 * peak:.3g}; its "
            f"brightest pixel would hold {peak / full_well:.2g} x the full well {full_well:g} e- in a single final frame "
            f"(stars brighter than m={m_sat:.2f} saturate, whatever beta0). A smaller beta0, a fainter star or an up-the-ramp "
            "readout (which reads the star before it saturates) is answered",
        )
    flags = []
    if region > 0:
        flags.append(make(FlagCode.EXTRAPOLATED_FAINT, magnitude=magnitude, faintest=hi))
    if magnitude < m_sat:
        flags.append(make(FlagCode.STAR_SATURATED, magnitude=magnitude, m_sat=m_sat))
    return flags


def refuse_saturation_past_tables(slopes, m_sat: float, beta0: float) -> None:
    """Refuse a brightest-usable-star answer the tables cannot give: the NL error stays below the
    tolerance at every star they hold, but at this beta0 they stop (in beta0 x flux) fainter than the
    saturation magnitude, so whether the stars between meet it -- and the slope at saturation -- is
    unknown. Answered as the saturation magnitude, it carried no slope and flags that contradicted it;
    a given magnitude there is refused by :func:`_magnitude_flags` alike."""
    lo = slopes.range()[0]
    at_end, at_sat = _peak_electrons(slopes, lo), _peak_electrons(slopes, m_sat)
    monotonic = (
        f"; there the quadratic is not even monotonic (2 beta0 Q_peak = {2 * beta0 * at_sat:.3g} >= 1)"
        if 2 * beta0 * at_sat >= 1
        else ""
    )
    raise InputError(
        "beta0",
        f"at beta0={beta0:g} the tables hold the NL strength beta0 x Q_peak only down to m={lo:.2f}, and the NL error "
        f"stays below the tolerance for every star they hold; stars saturate only at m={m_sat:.2f}, past them, so the "
        f"brightest usable star and the slope there are not known{monotonic}. Give beta0 at most "
        f"{beta0 * at_end / at_sat:.3g} /e- (the tables then reach saturation), a tighter tolerance, or ask for the "
        f"precision or the tolerance at a magnitude fainter than m={lo:.2f}",
    )


def _validity_flags(slopes, magnitude: float | None, precision: float | None, beta0: float, full_well: float) -> list[str]:
    if magnitude is None or not math.isfinite(magnitude):
        return []
    peak = _peak_electrons(slopes, magnitude)
    if slopes.ramp is not None:
        # The fit only sees reads up to the last unsaturated resultant (or the first one).
        peak = min(peak, max(full_well, peak * slopes.ramp.first_usable_fraction(slopes.exptime)))
    flags = []
    if 2 * beta0 * peak >= 1:
        flags.append(make(FlagCode.QUADRATIC_NOT_MONOTONIC, value=2 * beta0 * peak, magnitude=magnitude))
    if precision is not None and math.isfinite(precision) and precision * beta0 * peak > LINEAR_REGIME_LIMIT:
        flags.append(make(FlagCode.OUTSIDE_LINEAR_REGIME, value=precision * beta0 * peak, limit=LINEAR_REGIME_LIMIT))
    return flags


def _between_limits_flag(magnitude: float, m_sat: float, m_sat_final_frame: float) -> Flag:
    return make(FlagCode.BETWEEN_SATURATION_LIMITS, magnitude=magnitude, m_sat_final=m_sat_final_frame, m_sat=m_sat)


def _ramp_magnitude_flags(magnitude: float, m_sat: float, m_sat_final_frame: float) -> list[str]:
    if magnitude < m_sat - tables.BRIGHT_MARGIN_MAG:
        raise InputError(
            "magnitude",
            f"m={magnitude:g} saturates the brightest pixel in the resultant a ramp slope needs by more than "
            f"{tables.BRIGHT_MARGIN_MAG} mag (usable down to m={m_sat:.2f}); such a star has no meaningful NL answer",
        )
    if magnitude < m_sat:
        return [make(FlagCode.RAMP_SATURATED, magnitude=magnitude, m_sat=m_sat)]
    if magnitude < m_sat_final_frame:
        return [_between_limits_flag(magnitude, m_sat, m_sat_final_frame)]
    return []


def _binding(m_nl: float | None, m_sat: float, flags: list[str]) -> tuple[float, str]:
    """The brightest usable star: the fainter of the NL limit and saturation, and which binds."""
    if m_nl is None or m_nl < m_sat:
        where = "" if m_nl is None else f" (the NL error would reach the tolerance only at m={m_nl:.2f})"
        flags.append(make(FlagCode.SATURATION_BINDS, m_sat=m_sat, where=where, nonlinearity_magnitude=m_nl))
        return m_sat, "saturation"
    return m_nl, "nonlinearity"


def component_flags(slopes, metric: str, magnitude: float | None, slope: float | None, error: float | None) -> list:
    """The flag of an e1 / e2 answer whose slope is small against the modulus |c_e| (below
    :data:`COMPONENT_SMALL_FRACTION` of it) or within :data:`COMPONENT_ZERO_SIGMAS` standard errors
    of zero, whatever was solved for; for size and e, ``slope_consistent_with_zero`` where the
    slope is within those standard errors of zero; none for a slope not known. |c_e| is read from the
    answer's own slopes (the field grid's or the simulation's at that magnitude), else the tables'."""
    if magnitude is None or slope is None or not math.isfinite(magnitude):
        return []
    c, sigma = abs(float(slope)), abs(float(error or 0.0))
    zero = c <= COMPONENT_ZERO_SIGMAS * sigma
    if metric not in ("e1", "e2"):
        # size or |e|: a slope its own error cannot tell from zero (between the saturation limits the
        # size slope changes sign) is said, whatever is solved for.
        if not zero:
            return []
        return [make(FlagCode.SLOPE_CONSISTENT_WITH_ZERO, metric=metric, magnitude=magnitude, slope=float(slope), error=sigma)]
    ratio = slopes.modulus_over_component(magnitude) if hasattr(slopes, "modulus_over_component") else None
    if ratio is None and c > 0:
        from .model_part import component_scale  # the tables' |c_e| / |c_ei|

        ratio = component_scale(slopes, magnitude)
        ratio = None if ratio == 1.0 else ratio  # 1.0: no e slopes read (not an e answer's tables)
    fraction = None if ratio is None or not math.isfinite(ratio) or ratio <= 0 else 1.0 / ratio
    small = fraction is not None and fraction < COMPONENT_SMALL_FRACTION
    if not (small or zero):
        return []
    reasons = []
    if small:
        reasons.append(f"small against the modulus (|c_{metric}| = {fraction:.2f} |c_e| < {COMPONENT_SMALL_FRACTION:g} |c_e|)")
    if zero:
        reasons.append(f"consistent with zero (within {COMPONENT_ZERO_SIGMAS:g} standard errors)")
    modulus = math.nan if fraction is None else c / fraction
    return [
        make(
            FlagCode.E_COMPONENT_SMALL,
            metric=metric,
            magnitude=float(magnitude),
            why=" and ".join(reasons),
            slope=float(slope),
            error=sigma,
            modulus=modulus,
            fraction=fraction,
            limit=COMPONENT_SMALL_FRACTION,
        )
    ]


def between_limits(grid, band: str, sca: int, position, magnitude: float | None) -> tuple[float, float] | None:
    """(the ramp's saturation limit, the final frame's) at ``position`` where ``magnitude`` lies
    between them -- pixels lose resultants there and the field grid's interpolation misses a fresh
    simulation (docs/field.md, "Between the saturation limits") -- else None. None at a node of the
    grid too (only the magnitude is interpolated there) and where the grid states no final-frame limit."""
    if grid is None or position is None or magnitude is None or not math.isfinite(magnitude):
        return None
    final = grid.final_frame_saturation_magnitude(band, sca, position)
    if final is None:
        return None
    ramp = grid.saturation_magnitude(band, sca, position)
    if not ramp <= magnitude < final:
        return None
    from nlpsf.slopes import fieldgrid

    n = int(grid.conditions(band, sca)["grid"])
    if any(abs(x - position[0]) < 1e-6 and abs(y - position[1]) < 1e-6 for _, _, (x, y) in fieldgrid.grid_positions(n)):
        return None
    return float(ramp), float(final)


def between_limits_flag(
    position, magnitude: float, limits: tuple[float, float], realizations: int, centroids: str = "the grid's own"
) -> Flag:
    """The flag of a Roman-default answer simulated afresh between the saturation limits
    (``centroids``: why that many)."""
    return make(
        FlagCode.DEFAULT_BETWEEN_LIMITS,
        x=position[0],
        y=position[1],
        magnitude=magnitude,
        m_sat=limits[0],
        m_sat_final=limits[1],
        realizations=realizations,
        centroids=centroids,
    )


def between_limits_note(request, grid, magnitude: float | None) -> tuple[Flag, int] | None:
    """Where the Roman default's grid would answer at a position between the saturation limits
    (:func:`between_limits`) at ``magnitude``: the flag and the grid's centroid count, for a fresh
    simulation there (``solver.plan``); None elsewhere."""
    if grid is None:
        return None
    position = request.scene.position
    limits = between_limits(grid, request.band, request.sca, position, magnitude)
    if limits is None:
        return None
    realizations = int(grid.conditions(request.band, request.sca)["settings"]["realizations"])
    return between_limits_flag(position, float(magnitude), limits, realizations), realizations


def fresh_between_limits(answer, request, simulate: bool, flag: Flag, magnitude: float):
    """A magnitude answer the grid puts between the saturation limits at a position, solved again
    on fresh simulations with the grid's centroids; at table cost refused. ``answer`` is the
    solver's (``answer(request)``, passed in: this module sits below it)."""
    from dataclasses import replace

    from nlpsf.slopes import providers

    if not simulate:
        why = f"the answer lies between the saturation limits ({flag}): {providers.REFUSAL}"
        raise providers.NeedsSimulation(providers.Refusal(providers.RefusalCode.FIDELITY, "magnitude", why))
    fresh = answer(request.with_changes(fidelity="linear"))
    limits = [flag.values["m_sat"], flag.values["m_sat_final"]]
    conditions = {**fresh.conditions, "between_limits": {"grid_magnitude": magnitude, "limits": limits}}
    return replace(fresh, flags=[flag, *fresh.flags], conditions=conditions)
