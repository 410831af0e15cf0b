"""The Roman default's polychromatic slope against GalSim's own computation of the same scene.

The peer (``nlpsf.sim.reference.GalSimRomanDefault``) is GalSim only: ``OpticalPSF`` at the star's position
with the official pupil scale (from the official clear area), the default star's SED (its tabulated
spectrum or blackbody, as the answer's conditions name it) through the SCA's official bandpass
(``galsim.SED`` / ``Bandpass``), jitter and diffusion Gaussians, ``applyIPC`` after the NL, the
background (removed after the fit as a local sky estimate removes it, its own NL included), the
C2A_IMG_HLWAS ramp read by read with romancal's saturation flags and the likelihood fit (written
from the physics, checked here against the read-by-read brute force of ``test_ramps_readout``), HSM
moments, and the slope at the corrected state by a symmetric difference
in beta. The peer's calibration residual is a beta on every read (the earlier model, ``residual_nl=
"per_read_beta"``), so the answer here is asked for in that model; the default's own model (the
correction applied per resultant as romancal applies it) is checked against stcal's linearity routine
and a read-by-read brute force in ``test_residual_correction``. It is drawn at the answer's own
centroids (the answer's seed), so the two differ only by their physics and numerics.
``scripts/galsim_default_points.py`` runs the same comparison at random points (docs/validation.md, last section).
"""

from dataclasses import replace

import numpy as np
import pytest

from nlpsf import solve
from nlpsf.request import presets as roman_default
from nlpsf.sim import ramps, reference

from ..conftest import requires_galsim
from .test_ramps_readout import brute_force

pytestmark = [requires_galsim, pytest.mark.reference]


def _peer_ramp(conditions: dict, fit: str | None = None) -> reference.PeerRamp:
    ramp = conditions["ramp"]
    return reference.PeerRamp(
        tuple(tuple(r) for r in ramp["read_pattern"]),
        float(ramp["frame_time_s"]),
        float(ramp["read_noise_e"]),
        fit or ramp["fit"],
        float(conditions["full_well_e"]),
    )


@pytest.mark.parametrize("fit", ["ols", "optimal"])
def test_the_peers_ramp_is_the_read_by_read_brute_force(fit):
    # The peer's vectorised ramp (romancal's flags, the fit) against the test brute force, one pixel at a
    # time, over charges from empty to saturated in the second resultant, with a background.
    table = ramps.load_ma_table("C2A_IMG_HLWAS")
    peer = reference.PeerRamp(tuple(tuple(r) for r in table.resultants), table.frame_time_s, 9.3, fit)
    T = peer.exptime_s
    beta, background = 5e-7, 80.0
    charge = np.array([0.0, 37.0, 2.5e3, 4e4, 1.2e5, 2.9e5, 6e5, 2e6, 5e6]) + background
    taus = [np.array(r) * peer.frame_time_s / T for r in peer.resultants]
    R = np.array([np.mean([charge * t - beta * (charge * t) ** 2 for t in tau], axis=0) for tau in taus])
    usable = reference.romancal_usable(R, peer)
    image = reference.fit_ramp(R, usable, charge, peer)
    for i, q in enumerate(charge - background):
        expected, k = brute_force(q, table, T, (beta,), background, fit, 9.3, "signal", "unusable")
        assert usable[i] == k
        assert image[i] == pytest.approx(expected, rel=1e-13)


@pytest.mark.slow
@pytest.mark.parametrize(
    ("band", "sca", "position", "metric", "magnitude"),
    [("H158", 7, (1200.0, 2900.0), "size", 19.0), ("J129", 12, (3100.0, 1500.0), "e1", 20.0)],
    ids=["H158 size", "J129 e1"],
)
def test_polychromatic_default_agrees_with_galsim(band, sca, position, metric, magnitude):
    scene = replace(roman_default.base_scene(), position=position)  # the default's own star, the Pickles K0V
    answer = solve(
        band,
        sca,
        metric,
        magnitude=magnitude,
        tolerance=1e-4,
        fidelity="polychromatic",
        scene=scene,
        residual_nl="per_read_beta",  # the peer's residual model (module docstring)
    )
    conditions = answer.conditions
    offsets = (np.random.default_rng(conditions["seed"]).random((conditions["realizations"], 2)) - 0.5) * 3
    peer = reference.GalSimRomanDefault(
        band, sca, position, sed=conditions["scene"]["sed"], jitter_arcsec=0.006, diffusion_px=0.332
    )
    stamps = peer.unit_stamps(offsets)
    slopes = peer.corrected_slopes(
        stamps, magnitude, _peer_ramp(conditions), conditions["beta0"], conditions["scene"]["background_e"]
    )
    theirs, _ = slopes.mean({"size": "dR_over_R", "e1": "de1", "e2": "de2"}[metric])
    assert abs(answer.slope - theirs) <= 0.005 * abs(theirs)
