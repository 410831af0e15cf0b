"""Between the saturation limits, nlpsf's ramp path against the GalSim peer's, on the SAME charge stamps.

docs/validation.md (the GalSim section): at two points between the limits nlpsf's polychromatic slope
is ~1 % from the peer's. On identical charge stamps the two ramp paths agree pixel for pixel (romancal's
flags) and centroid for centroid (fit, IPC, moments); the 1 % is which pixels cross a flag edge under
the two PSF models. This test holds the first half: nlpsf's "signal" saturation rule (coupled powers,
``ramps.scene_factors_coupled``) against ``reference.romancal_usable`` on GalSim's ``applyIPC`` of every
read, and nlpsf's linear-response slope against the peer's read-by-read ramp, likelihood fit and HSM
moments (a symmetric difference in beta), both on nlpsf's own unit stamps of the point where the
difference was found (H158 SCA 12, m = 16.93, 11 pixels per centroid lose resultants).
"""

from dataclasses import replace

import numpy as np
import pytest

from nlpsf import solve
from nlpsf.request import presets as roman_default
from nlpsf.sim import experiment, moments, ramps, reference
from nlpsf.sim.experiment import kernels

from ..conftest import requires_galsim

pytestmark = [requires_galsim, pytest.mark.reference]

BAND, SCA, POSITION, MAGNITUDE = "H158", 12, (2001.4, 3440.2), 16.926
CENTROIDS = 12


@pytest.mark.slow
def test_between_the_limits_nlpsf_ramp_is_the_peers_on_the_same_charge(monkeypatch):
    kept: dict = {}
    simulate = experiment.slopes

    def keep_scene(config, magnitudes, **options):  # passes through: only remembers what was simulated
        kept.update(config=config, scene=options["scene"], beta0=options["beta0"])
        return simulate(config, magnitudes, **options)

    monkeypatch.setattr(experiment, "slopes", keep_scene)
    scene_model = replace(roman_default.base_scene(), position=POSITION)
    solve(BAND, SCA, "e2", magnitude=MAGNITUDE, tolerance=1e-4, fidelity="linear", scene=scene_model)
    config, scene, beta0 = kept["config"], kept["scene"], kept["beta0"]
    model, ramp = config.scene, config.ramp
    flux = float(config.electrons(MAGNITUDE))
    scale = flux * config.oversampling**2
    state = (beta0, *model.nl_coefficients)
    # nlpsf: the flags the slope is read with (raw beta0's signal) and its per-centroid linear response.
    _, usable = ramps.scene_factors_coupled(
        scene.coupled_powers, scale, model.background_e, ramp, config.exptime_s, config.full_well_e, state, (2,)
    )
    effect = kernels.ramp_effect(scene, scale, beta=beta0)
    settings = config.moment_settings
    beta = experiment.CORRECTED_RESIDUAL * beta0
    fit, reference_fit, stamps, perturbation, derivative = kernels._perturbed_fit(scene, scale, beta, settings, effect)
    ours = moments.response_to(stamps + perturbation, fit, derivative, settings)[0].T.copy()
    ours[0] *= fit.sigma / reference_fit.sigma

    # The peer, on nlpsf's charge (its own bandpass's electrons rescaled to nlpsf's, so the charge is equal).
    peer_ramp = reference.PeerRamp(
        tuple(tuple(r) for r in ramp.table.resultants), ramp.table.frame_time_s, ramp.read_noise_e, ramp.fit, config.full_well_e
    )
    peer = reference.GalSimRomanDefault(BAND, SCA, POSITION, oversampling=config.oversampling, stamp=scene.stamps.shape[-1])
    peer_flux = peer.electrons(MAGNITUDE, peer_ramp.exptime_s)
    unit = np.asarray(scene.charge[:CENTROIDS]) * config.oversampling**2 * (flux / peer_flux)
    K = len(peer_ramp.resultants)
    fewer = 0
    for r in range(CENTROIDS):
        charge = peer_flux * unit[r] + model.background_e
        theirs_usable = reference.romancal_usable(peer._resultants(charge, peer_ramp, beta0), peer_ramp)
        np.testing.assert_array_equal(np.asarray(usable[r]).ravel(), theirs_usable)
        fewer += int(np.sum(theirs_usable < K))
    assert fewer >= 5 * CENTROIDS  # between the limits: resultants are lost in every centroid
    theirs = peer.corrected_slopes(unit, MAGNITUDE, peer_ramp, beta0, model.background_e)
    for k, values in enumerate((theirs.dR_over_R, theirs.de1, theirs.de2)):
        mine = ours[k][:CENTROIDS]
        scale_k = abs(np.mean(values))
        # HSM's float32 moments and the second-order difference: ~2e-3 of the slope per centroid measured.
        assert np.max(np.abs(mine - values)) <= 5e-3 * scale_k
        assert abs(np.mean(mine) - np.mean(values)) <= 1e-3 * scale_k
