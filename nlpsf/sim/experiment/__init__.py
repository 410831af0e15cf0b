"""The experiment: Roman PSF -> oversampled stamps -> nonlinearity -> adaptive moments.

One :class:`SimulationConfig` fixes everything but the star and the detector (band, SCA,
realizations, seed, grid, exposure, optics and measurement settings). :func:`prepare` does the
work that does not depend on magnitude or beta, once: the optics, the rendered stamps for every
centroid realization (at unit flux) and their reference moments. It returns a :class:`Scene`,
the explicit cache the other calls take.

Magnitude and beta only scale and perturb the same rendered stamps: with I = s psi the charge
image (s = flux * N^2, psi the unit-flux stamp), NL gives s (psi - beta s psi^2), and adaptive
moments do not see the overall scale. So each (magnitude, beta) costs one perturbed fit per
realization, started from the reference fit, and the metrics depend on beta and flux only through
their product.

Up the ramp (``SimulationConfig.ramp``, see ``nlpsf.sim.ramps``) the fitted image is s (psi - beta s psi^2
c_2) with c_2 the per-pixel ramp factor, still linear in beta (the fit's weights do not depend on it),
so both methods run unchanged on the pattern psi^2 c_2. The beta x flux rule then holds only while
c_2 is one number for the whole stamp (OLS fit, no resultant saturated); saturated resultants and the
optimal fit's charge-dependent weights break it.

Methods ("fidelity"):
- ``monte_carlo``: every realization fitted to convergence (the paper's procedure);
- ``linear``: the first-order response, metric = beta * s * g . (-psi^2) with g the gradient of the
  moment estimator with respect to pixel values (``moments.pixel_response``). Scatter from
  per-pixel beta is then sigma_beta * s * ||g (.) psi^2||, in closed form.

The package holds, by module: ``config`` (SimulationConfig), ``prepared`` (the cached Scene and
``prepare``), ``readout`` (the ramp inside a simulation), ``correction`` (the
pipeline's linearity correction per resultant, the default's calibration residual), ``kernels`` (NL images and the bias and
scatter fits, returning typed results), ``validity`` (the flags a result carries), ``results``
(result types and serialisation) and ``measure`` (``simulate`` and ``slopes``). Every name is
re-exported here, so ``from nlpsf.sim import experiment; experiment.X`` works as before.
"""

# ruff: noqa: F401
from .config import (
    CORRECTED_RESIDUAL,
    LINEARISE_STATES,
    MAX_REALIZATIONS,
    MAX_STAMP_BYTES,
    METHODS,
    METRICS,
    PAPER_BETA_STEP,
    PAPER_SCENE,
    Progress,
    SimulationConfig,
    scenes,  # callers reach nlpsf.sim.scene through experiment.scenes
)
from .correction import (
    DEFAULT_RESIDUAL_MODEL,
    RESIDUAL_DESCRIPTIONS,
    RESIDUAL_MODELS,
    Correction,
    corrected_effect,
    star_free_correction,
)
from .kernels import (
    _SCATTER_CHUNK,
    _finite_difference_slopes,
    _linear_slopes,
    _per_pixel_beta_response,
    _perturbed_fit,
    _simulate_bias,
    _simulate_scatter,
    nl_images,
)
from .measure import (
    _cut_jump_flags,
    check_magnitudes,
    check_sigma_beta,
    simulate,
    slopes,
)
from .prepared import (
    Scene,
    _peak_electrons,
    _weighted_region,
    prepare,
    star_peak_electrons,
)
from .readout import (
    RampEffect,
    _nl_shape,
    _ramp_summary,
    _scene_ramp_effect,
    ramp_effect,
)
from .results import (
    SimulationResult,
    SlopeResult,
    Statistic,
    _metrics,
    _reference_summary,
    pooled,
)
from .validity import (
    MONTE_CARLO_SPREAD_FLOOR,
    _failure_flag,
    _noise_floor_flag,
    _scene_flags,
    _validity_flags,
    _zero_flag,
)
