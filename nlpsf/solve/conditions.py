"""What an answer's conditions say: the tables' and the request's settings, the scene and state
its slope is for, the Roman default's values, the saturation rule, the readout and where its ramp
slopes came from, what a fresh simulation ran, and which stars the answer applies to.

The solver (``nlpsf.solve.solver.answer``) attaches them; this module only reads its plan and slopes.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

from nlpsf._version import __version__
from nlpsf.request import presets as roman_default
from nlpsf.slopes import fidelity as levels
from nlpsf.slopes import fieldgrid, tables

if TYPE_CHECKING:
    from nlpsf.request.resolve import SolveRequest
    from nlpsf.slopes.source import Slopes


class SolvePlan(Protocol):
    """What these read of ``nlpsf.solve.solver.SolvePlan`` (not imported: the solver imports this module)."""

    fidelity: str
    scene: object | None
    grid: object | None


def conditions(request: SolveRequest, the_plan: SolvePlan, slopes: Slopes) -> dict:
    """The answer's conditions: the tables' and the request's, the scene it is for, the state its
    slope is taken at, the Roman default's values, the saturation rule and the readout."""
    out = tables.conditions(slopes.table, request.exptime, request.beta0, request.full_well)
    relation = "T = |c(m)| * precision * beta0" + (" / sqrt(stars)" if request.mode == "scatter" else "")
    who = applies_to(request.mode, request.stars)
    out.update(fidelity=the_plan.fidelity, code_version=__version__, relation=relation, stars=request.stars, applies_to=who)
    # Which scene the answer is for, and the detector state its slope is taken at.
    out["scene_name"] = request.preset
    out["linearise_at"] = request.linearise_at
    # How a calibration error acts there: the field grid's own model where the answer reads it, else
    # what the fresh simulations ran.
    grid_conditions = None if the_plan.grid is None else the_plan.grid.conditions(request.band, request.sca)
    if grid_conditions is not None:
        out["residual_nl"] = fieldgrid.grid_residual_model(grid_conditions["settings"])
    else:
        out["residual_nl"] = request.residual_model
    if request.policy.quotes_default:
        out["roman_default"] = roman_default.conditions()
        own = roman_default.default_fill(request.band, request.sca, request.exptime)
        out["roman_default_changed"] = not roman_default.is_default_scene(request.scene, own.background_e) or (
            request.ramp != own.ramp
        )
    if the_plan.grid is not None:
        out["slopes_from"] = f"the Roman default's field grid ({fieldgrid.SHIPPED_NAME})"
        # The slopes are the grid's, not the paper tables': their settings are the grid's nodes'.
        out.update(grid_settings(the_plan.grid, request.band, request.sca, grid_conditions))
    ramp = request.ramp
    if ramp is None:
        out["saturation_rule"] = "final frame: the brightest pixel's charge at the end of the exposure hits the full well"
    else:
        out["saturation_rule"] = (
            "ramp: the brightest pixel saturates in the resultant a slope needs (the first, or the second where one "
            "resultant gives no slope; later saturated resultants are dropped): " + ramp.saturation_rule()
        )
        out["ramp"] = ramp.conditions(request.exptime)
        # Fainter than this the tables answer exactly at beta_eff (OLS); brighter, pixels drop resultants.
        out["ramp_table_exact_from_magnitude"] = slopes.exact_from() if slopes.ramp_factor is not None else None
        out["ramp_slopes_from"] = ramp_basis(slopes)
    return out


#: The table settings an answer's conditions quote (``tables.conditions``) that a field grid's nodes set.
_GRID_SETTINGS = ("oversampling", "stamp", "realizations", "seed", "weight_cut_rho2", "pupil_scale")


def grid_settings(grid, band: str, sca: int, grid_conditions: dict | None = None) -> dict:
    """The conditions of an answer read from a field grid: its nodes' settings in place of the
    paper tables' (the pupil-scale rule, centroids, stamp...) and the exposure and beta0 they hold.
    ``grid_conditions``: ``grid.conditions(band, sca)`` where the caller has read them already."""
    settings = (grid_conditions or grid.conditions(band, sca))["settings"]
    out = {key: settings[key] for key in _GRID_SETTINGS if key in settings}
    out["table_conditions"] = {"exptime_s": settings["exptime_s"], "beta0": settings["beta0"]}
    return out


def add_simulation_conditions(conditions: dict, the_plan: SolvePlan, slopes: Slopes) -> None:
    """What a fresh simulation ran (realizations, wavelengths the optics evaluated) and the scene."""
    if the_plan.fidelity != "table":
        conditions["realizations"] = slopes.realizations
        # What the optics evaluated (a scene's SED integrates the band even at linear fidelity).
        simulated = slopes.prepared  # the prepared simulation, None where none ran
        conditions["n_wavelengths"] = (
            int(simulated.psf.wavelengths_nm.size)
            if simulated is not None
            else levels.simulation_settings(the_plan.fidelity).n_wavelengths
        )
    if the_plan.scene is not None:
        conditions["scene"] = the_plan.scene.to_dict()
        conditions["scene_description"] = the_plan.scene.describe()


def applies_to(mode: str, stars: int) -> str:
    """Which stars an answer holds for (a bias: every star; a scatter: one star, or a PSF model's average)."""
    if mode == "bias":
        return "every star alike: a bias in the mean beta is common to all stars, averaging does not reduce it"
    if stars == 1:
        return "one star: the scatter of a single star's metric over per-pixel beta maps"
    return (
        f"a PSF model averaging {stars} stars or dithers on independent pixels (scatter / sqrt({stars})), "
        "each as bright as the answer's magnitude"
    )


def ramp_basis(slopes: Slopes) -> str:
    """Where a ramp answer's slopes came from: the field grid, the tables at beta_eff, fresh simulations."""
    parts = []
    if "grid" in slopes.ramp_bases:
        parts.append("the Roman default's field grid (its ramp simulated at every node)")
    if "table" in slopes.ramp_bases:
        parts.append(
            f"tables at beta_eff = {slopes.ramp_factor:.6g} beta0 "
            "(exact: quadratic NL, OLS fit, every pixel keeps every resultant)"
        )
    if "simulation" in slopes.ramp_bases:
        level = "linear-response" if slopes.fidelity in ("table", "linear") else slopes.fidelity.replace("_", " ")
        why = (
            "the optimally weighted fit has no exact table mapping"
            if slopes.ramp.fit == "optimal"
            else f"brighter than m={slopes.exact_from():.2f} pixels drop saturated resultants"
            if slopes.fidelity == "table"
            else ("the scene has no table" if slopes.scene_model is not None else f"fidelity {slopes.fidelity} asked for")
        )
        parts.append(f"fresh {level} simulations of the ramp ({why}; {slopes.realizations} realizations)")
    return "; ".join(parts) or "none needed"
