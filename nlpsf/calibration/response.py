"""A star's first-order response to a calibration residual, from a prepared simulation or a solve request.

The samples of ``kernel.Response`` come from the same simulation the solver's slopes do: the scene
prepared once (``experiment.prepare``), the readout at the star's flux with the per-resultant correction
(``experiment.correction``), the moments fitted at a perfect calibration and their gradient there
(``moments.pixel_response``; the size gradient relative to the unperturbed size, as ``experiment.slopes``
takes it). The quadratic residual -Q^2 through these samples is therefore the solver's Delta_beta slope
of the same simulation, to rounding.
"""

from __future__ import annotations

import numpy as np

from nlpsf.sim import experiment, moments, ramps
from nlpsf.sim.experiment import correction as corrections
from nlpsf.sim.experiment.kernels import _perturbed_fit
from nlpsf.sim.experiment.measure import _readout_at

from .. import defaults
from ..checks import InputError, SimulationError
from .kernel import Response


def star_response(scene: experiment.Scene, magnitude: float, raw_beta: float = defaults.BETA0) -> Response:
    """The samples (charge level, weight) of a star of ``magnitude`` in ``scene`` (all its realizations)."""
    config = scene.config
    flux = float(config.electrons(magnitude))
    scale = flux * config.oversampling**2
    effect, flags, _ = _readout_at(scene, scale, raw_beta, corrected=True)
    settings = config.moment_settings
    fit, reference, stamps, perturbation, _ = _perturbed_fit(scene, scale, 0.0, settings, effect)
    ok = fit.ok & reference.ok
    if not np.any(ok):
        if flags:  # saturated, unusable pixels: a star too bright for its readout is the request's, not a fault
            raise InputError(
                "magnitude",
                f"m = {magnitude:g}: the moments fail in every realization, the star is too bright for this readout "
                f"({'; '.join(str(f) for f in flags)})",
            )
        raise SimulationError(f"the moments failed at m={magnitude:g} in every realization")
    gradient = moments.pixel_response(stamps + perturbation, fit, settings)
    gradient[:, 0] *= (fit.sigma / reference.sigma)[:, None, None]
    gradient /= scale  # the images are per unit flux; the residual is in e-
    margin = (scene.stamps.shape[-1] - stamps.shape[-1]) // 2
    corr, trim = effect.correction.at_margin(margin)
    cr = corr.ramp
    full = np.zeros((cr.shape[0], 3, *cr.shape[1:]))
    full[:, :, trim[1], trim[2]] = gradient
    flat = np.arange(int(np.prod(cr.shape))) if cr.index is None else cr.index
    owner, row, col = np.unravel_index(flat, cr.shape)
    pixel = full[owner, :, row, col]  # (P, 3)
    used = cr.weights != 0
    pick_p, pick_j = np.nonzero(used)
    levels = [cr.level[pick_p, pick_j]]
    weights = [pixel[pick_p] * cr.weights[pick_p, pick_j][:, None]]
    owners = [owner[pick_p]]
    edge = (scene.stamps.shape[-1] - cr.shape[-1]) // 2
    rows, cols = [row[pick_p] + edge], [col[pick_p] + edge]
    sky_levels, sky_weights = star_free_samples(config, raw_beta)
    if sky_levels.size:
        # The sky estimate moves with the residual: a uniform offset under every pixel's gradient.
        total = -full.sum(axis=(2, 3))  # (R, 3)
        R = total.shape[0]
        levels.append(np.tile(sky_levels, R))
        weights.append((total[:, None, :] * sky_weights[None, :, None]).reshape(-1, 3))
        owners.append(np.repeat(np.arange(R), sky_levels.size))
        rows.append(np.full(R * sky_levels.size, -1))
        cols.append(np.full(R * sky_levels.size, -1))
    owner_all = np.concatenate(owners)
    keep = ok[owner_all]  # realizations whose fits failed are left out (their count is in the conditions)
    renumber = np.cumsum(ok) - 1
    conditions = config.conditions()
    conditions["residual_nl"] = "per_resultant_correction"
    conditions["raw_beta"] = raw_beta
    conditions["failed_realizations"] = int(np.sum(~ok))
    full_well = config.full_well_e
    saturation = float(full_well + ramps.correction.inverse_excess(np.array([full_well]), (raw_beta,))[0])
    return Response(
        np.concatenate(levels)[keep],
        np.concatenate(weights)[keep],
        renumber[owner_all[keep]],
        int(ok.sum()),
        float(magnitude),
        flux,
        float(full_well),
        saturation,
        conditions,
        list(flags),
        np.concatenate(rows)[keep],
        np.concatenate(cols)[keep],
        config.oversampling,
        scene.stamps.shape[-1],
        float(raw_beta),
        None if config.scene.position is None else tuple(float(v) for v in config.scene.position),
    )


def star_free_samples(config, raw_beta: float) -> tuple[np.ndarray, np.ndarray]:
    """(levels, weights) of a star-free pixel's usable resultants under the per-resultant correction
    (empty without a sky): what the sky estimate reads."""
    ramp = corrections.star_free_ramp(config, float(raw_beta))
    if ramp is None:
        return np.zeros(0), np.zeros(0)
    levels, weights = ramp
    used = weights != 0
    return levels[used], weights[used]
