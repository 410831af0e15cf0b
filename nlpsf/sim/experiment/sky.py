"""The sky's own NL, as a local sky estimate removes it (docs/ramps.md, "Background").

A star sits on a sky of B e- per pixel. The NL bends the sky too: a star-free pixel's fitted level is
B - b2 B^2 c2(B) - ... (c_n the ramp factors of a pixel at the sky's rate; 1 on a final frame), coupled
by IPC like any other signal. A measurement estimates the local sky from star-free pixels of the same
exposure, so it subtracts that whole level, its NL included: only the star's own NL and its cross
terms with the sky stay in the image. Left in, the sky's NL would be a constant pedestal whose weight
in the moments grows as 1 / flux and dominates faint stars.

The pedestal is computed with the same chain as the star's image (``scene.detector_chain`` on a
final frame, ``ramps.scene_factors`` / ``scene_perturbation`` up the ramp) on a uniform, star-free
stamp, so the subtraction is exact whatever the detector effects (IPC before or after, higher orders).
A uniform calibration error moves the sky estimate with it; per-pixel scatter does not (the estimate
averages many other pixels), so the pedestal is always taken at one uniform b2.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .. import ramps
from .. import scene as scenes
from .prepared import Scene


def star_free_level(scene: Scene, charge_scale: float, beta: float, up_the_ramp: bool) -> tuple[float, float]:
    """(the sky's own NL in a star-free pixel, its d / d b2), per unit flux like ``nl_images``' images.

    ``up_the_ramp``: the sky pixel read by the scene's ramp (its own factors, at the sky's rate);
    otherwise the final frame. Both 0 without a sky. The level does not depend on the star's flux,
    so it is computed once per (configuration, b2) and divided by ``charge_scale``."""
    level, derivative = _star_free_level_e(scene.config, float(beta), up_the_ramp)
    return level / charge_scale, derivative / charge_scale


@lru_cache(maxsize=256)
def _star_free_level_e(config, beta: float, up_the_ramp: bool) -> tuple[float, float]:
    """:func:`star_free_level` in e- (a table's rows share it: one computation per b2, not per row)."""
    model = config.scene
    if model.background_e <= 0:
        return 0.0, 0.0
    n = config.oversampling
    size = 3 * n  # IPC reaches n fine pixels: the centre of a 3 x 3 native stamp sees the whole kernel
    centre = (0, size // 2, size // 2)
    if not up_the_ramp:
        _, level, derivative = scenes.detector_chain(np.zeros((1, size, size)), 1.0, beta, model, n)
        return float(level[centre]), float(derivative[centre])
    orders = tuple(range(2, 3 + len(model.nl_coefficients)))
    sky = np.full((1, size, size), model.background_e)
    state = (beta, *model.nl_coefficients)
    sr = ramps.scene_factors(sky, config.ramp, config.exptime_s, config.full_well_e, state, orders, model.ipc, model.ipc_order, n)
    level, derivative = ramps.scene_perturbation(sr, beta, model.nl_coefficients, model.ipc, model.ipc_order, n)
    return float(level[centre]), float(derivative[centre])
