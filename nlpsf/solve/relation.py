"""The relation T = |c(m)| p beta0 read sideways, and where its quadratic detector model stops.

Two answers the page (and anyone) needs that are not a solve: the magnitude brighter than which the
quadratic S = Q - beta0 Q^2 no longer rises at the star's brightest pixel, and what a change of the
slope by a fraction ``impact`` (an effect's slope over the slope without it, minus one) does to the
precision an answer requires at fixed tolerance.
"""

from __future__ import annotations

import math

from nlpsf import defaults, roman
from nlpsf.checks import InputError, check_beta0, check_exptime, check_number
from nlpsf.slopes import tables


def nl_invalid_magnitude(
    band: str,
    sca: int = defaults.SCA,
    beta0: float = defaults.BETA0,
    exptime: float = defaults.EXPTIME_S,
    background_e: float = 0.0,
    tables_set: tables.TableSet | None = None,
) -> float:
    """Magnitude [AB] brighter than which 2 beta0 Q >= 1 in the star's brightest pixel, Q its
    charge (the star's peak, the maximum over sub-pixel centroids, plus ``background_e``): there
    dS/dQ = 1 - 2 beta0 Q reaches zero and the quadratic no longer describes a detector.

    The star's peak scales with its flux, so this is the tables' saturation magnitude at a "full
    well" of 1 / (2 beta0) - background; it does not depend on the full well. None where beta0 <= 0
    (in the paper's convention): S then rises at every charge."""
    band, sca = roman.check_band(band), roman.check_sca(sca)
    beta0, exptime = check_beta0(beta0), check_exptime(exptime)
    background_e = check_number(background_e, "background", 0.0, math.inf)
    charge = 1.0 / (2.0 * beta0) - background_e
    if charge <= 0:
        raise InputError("background", f"a background of {background_e:g} e- alone makes 2 beta0 Q >= 1")
    return (tables_set or tables.load_tables()).get(band, sca).saturation(exptime, charge)


def precision_with_impact(precision: float, impact: float) -> float:
    """The precision an answer requires once an effect changes its slope c to (1 + impact) c, at the
    same tolerance and beta0: T = |c| p beta0 gives p / |1 + impact| (inf where the slope vanishes).
    ``impact`` is signed: below -1 the effect flips the slope's sign, and only |c| enters T."""
    precision = check_number(precision, "precision", 0.0, math.inf, open_low=True)
    impact = check_number(impact, "impact", -math.inf, math.inf)
    ratio = abs(1.0 + impact)
    return math.inf if ratio == 0 else precision / ratio
