"""Agreement with the GalSim pipeline the paper used (needs ``pip install nlpsf[reference]``).

The peer is galsim.roman.getPSF + Convolve(Pixel) + drawImage(no_pixel) on float64 stamps, x N^2,
applyNonlinearity, hsm.FindAdaptiveMom (precision 1e-10, and the same weight cut). Two versions:

- ``converged``: getPSF's own optical model with the pupil plane padded 4x (GalSim's
  Aperture(oversampling=4)); GalSim's image then stops changing, and this is what our numbers must
  reproduce (Delta R / R to 1 %, Delta e to 3 % or 1e-7);
- ``default``: getPSF as shipped, whose Nyquist-sampled PSF interpolation moves the drawn PSF by up
  to 2.5 % of its peak for some SCAs. There we check that the measurement agrees exactly (our
  moments on GalSim's images give GalSim's numbers) and that on the paper's configuration, where
  GalSim's sampling is finer, the whole pipeline agrees to 1 %.
"""

import numpy as np
import pytest

from nlpsf.sim import experiment, moments, reference

from ..conftest import requires_galsim

pytestmark = [requires_galsim, pytest.mark.reference, pytest.mark.slow]

REALIZATIONS = 6
CASES = {
    "paper H158 SCA18 m18.3": ("H158", 18, 18.3, 5e-7, moments.PAPER_WEIGHT_CUT_RHO2),
    "long-wavelength F184 SCA1": ("F184", 1, 18.3, 5e-7, moments.PAPER_WEIGHT_CUT_RHO2),
    "bright Y106 SCA7 m16.5": ("Y106", 7, 16.5, 5e-7, moments.GALSIM_WEIGHT_CUT_RHO2),
    "faint J129 SCA11 m24": ("J129", 11, 24.0, 5e-7, moments.PAPER_WEIGHT_CUT_RHO2),
    "K213 SCA4 beta 1e-6": ("K213", 4, 19.0, 1e-6, moments.GALSIM_WEIGHT_CUT_RHO2),
}
_PIPELINES: dict = {}


def pipeline(band, sca, cut, pupil_oversampling):
    key = (band, sca, cut, pupil_oversampling)
    if key not in _PIPELINES:
        _PIPELINES[key] = reference.GalSimPipeline(band, sca, weight_cut_rho2=cut, pupil_oversampling=pupil_oversampling)
    return _PIPELINES[key]


def ours(band, sca, magnitude, beta, cut):
    # GalSim's Roman module uses its 2021 effective areas: compare like with like.
    config = experiment.SimulationConfig(
        band=band, sca=sca, realizations=REALIZATIONS, weight_cut_rho2=cut, seed=7, throughput="galsim-2021"
    )
    scene = experiment.prepare(config)
    return scene, experiment.simulate(config, [magnitude], [beta], scene=scene)[0]


def close(ours_value, theirs_value, rel, floor):
    return abs(ours_value - theirs_value) <= max(rel * abs(theirs_value), floor)


@pytest.mark.parametrize("case", list(CASES))
def test_agrees_with_galsim_at_converged_pupil_sampling(case):
    band, sca, magnitude, beta, cut = CASES[case]
    scene, result = ours(band, sca, magnitude, beta, cut)
    peer = pipeline(band, sca, cut, 4.0).run(magnitude, beta, scene.offsets, 168.1, redraw=False, keep_images=True)
    # Faint stars: GalSim's float32 outputs limit it, so compare with a float64 measurement of
    # GalSim's own images too; we must match that one closely.
    images = np.array(peer.reference_images)
    ref = moments.fit(images, experiment.SimulationConfig(weight_cut_rho2=cut).moment_settings)
    fit = moments.fit_perturbed(images, -beta * images**2, ref, experiment.SimulationConfig(weight_cut_rho2=cut).moment_settings)
    f64 = [v.mean() for v in moments.differences(fit, ref)]
    assert close(result.dR_over_R.mean, peer.dR_over_R.mean(), 0.01, 0)
    assert close(result.dR_over_R.mean, f64[0], 1e-3, 0)
    for k, metric in enumerate(("de1", "de2")):
        assert close(getattr(result, metric).mean, getattr(peer, metric).mean(), 0.03, 1e-7)
        assert close(getattr(result, metric).mean, f64[k + 1], 0.01, 2e-8)


@pytest.mark.parametrize("case", list(CASES))
def test_measures_galsim_images_as_find_adaptive_mom_does(case):
    band, sca, magnitude, beta, cut = CASES[case]
    scene, _ = ours(band, sca, magnitude, beta, cut)
    peer = pipeline(band, sca, cut, 1.0)
    result = peer.run(magnitude, beta, scene.offsets[:3], 168.1, redraw=False, keep_images=True)
    settings = experiment.SimulationConfig(weight_cut_rho2=cut).moment_settings
    fitted = moments.fit(np.array(result.reference_images), settings)
    assert fitted.sigma == pytest.approx(result.sigma0, rel=1e-6)
    assert fitted.e1 == pytest.approx(result.e1_0, abs=1e-6)
    assert fitted.e2 == pytest.approx(result.e2_0, abs=1e-6)


def test_whole_pipeline_agrees_with_default_getpsf_on_the_paper_configuration():
    band, sca, magnitude, beta, cut = CASES["paper H158 SCA18 m18.3"]
    scene, result = ours(band, sca, magnitude, beta, cut)
    peer = pipeline(band, sca, cut, 1.0).run(magnitude, beta, scene.offsets, 168.1, redraw=True)
    assert close(result.dR_over_R.mean, peer.dR_over_R.mean(), 0.01, 0)
    assert close(result.de1.mean, peer.de1.mean(), 0.03, 1e-7)
    assert close(result.de2.mean, peer.de2.mean(), 0.03, 1e-7)


def test_photometry_matches_galsim_bandpasses():
    for band in ("R062", "Z087", "Y106", "J129", "H158", "F184", "W146", "K213"):
        theirs, ours_e = reference.galsim_electrons(band, 18.3, 168.1)
        # GalSim thins its bandpass table (rel_err 1e-4) before integrating.
        assert ours_e == pytest.approx(theirs, rel=1e-4)


@pytest.mark.parametrize(("band", "magnitude"), [("Y106", 22.0), ("J129", 18.3), ("F184", 20.0)])
def test_whole_pipeline_agrees_with_default_getpsf_on_sca18(band, magnitude):
    # SCA 18's short- and long-wavelength masks reach far enough out that GalSim pads its pupil
    # plane more, and its default PSF is accurate there: the shipped pipeline itself agrees.
    scene, result = ours(band, 18, magnitude, 5e-7, moments.PAPER_WEIGHT_CUT_RHO2)
    peer = pipeline(band, 18, moments.PAPER_WEIGHT_CUT_RHO2, 1.0).run(magnitude, 5e-7, scene.offsets, 168.1, redraw=False)
    assert close(result.dR_over_R.mean, peer.dR_over_R.mean(), 0.01, 0)
    assert close(result.de1.mean, peer.de1.mean(), 0.03, 1e-7)
    assert close(result.de2.mean, peer.de2.mean(), 0.03, 1e-7)
