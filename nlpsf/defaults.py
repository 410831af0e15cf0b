"""The paper's defaults, the tool's names and the ranges every entry point accepts: defined once.

This module imports nothing heavy (no numpy), so the command line can build its parser, help
texts and choices from it in milliseconds. Library modules take their defaults from here; the
CLI and the web layer read them from here to show them; nothing else repeats these numbers.
"""

from __future__ import annotations

import math

# --- the instrument (Roman WFI) -------------------------------------------------------------------

#: Imaging bands, bluest first. F184 and K213 use the long-wavelength (cold) pupil mask.
BANDS: tuple[str, ...] = ("R062", "Z087", "Y106", "J129", "H158", "F184", "W146", "K213")
#: The four High Latitude Survey bands the paper studies.
PAPER_BANDS: tuple[str, ...] = ("Y106", "J129", "H158", "F184")
#: Detectors in the focal plane.
N_SCA = 18
#: Native WFI pixel scale [arcsec / pixel].
PIXEL_SCALE_ARCSEC = 0.11

# --- the paper's experiment (Plazas et al. 2016, section 3) ---------------------------------------

BAND = "H158"
#: The paper simulates SCA 18.
SCA = 18
#: Nominal NL coefficient [1/e-], paper convention S = Q - beta Q^2.
BETA0 = 5e-7
#: High Latitude Survey exposure time [s].
EXPTIME_S = 168.1
#: Full-well depth [e-].
FULL_WELL_E = 1.1e5
#: Fine pixels per native pixel, N.
OVERSAMPLING = 3
#: Stamp side in fine pixels.
STAMP = 96
#: Centroid realizations (or beta-map draws with sigma_beta).
REALIZATIONS = 100
SEED = 1
#: The paper's (GalSim 1.3's) cut of the adaptive-moment weight: rho^2 = 25.
PAPER_WEIGHT_CUT_RHO2 = 25.0
#: GalSim >= 2.4 cuts where exp(-rho^2/2) falls below a tenth of its convergence threshold
#: (1e-6): rho^2 = -2 ln(1e-7) = 32.24.
GALSIM_WEIGHT_CUT_RHO2 = -2.0 * math.log(1e-7)
#: Magnitudes of the paper's slopes (Figs. 3 and 5).
PAPER_MAGNITUDES: tuple[float, ...] = (18.3, 19.0, 20.0, 21.0, 22.0)
#: Magnitude of the paper's worked example and of a single simulation by default.
MAGNITUDE = 18.3
#: Fractional beta steps of the paper's finite-difference slopes: beta0 * {0.99, 1, 1.01}.
PAPER_BETA_STEP = 0.01
#: Default per-pixel scatter of the Monte Carlo scatter slope, as a fraction of beta0.
SIGMA_BETA_FRACTION = 0.1

#: Slope tables: the magnitude grid's step and faint end (it starts 1.5 mag brighter than saturation).
TABLE_MAGNITUDE_STEP = 0.25
TABLE_FAINT_LIMIT = 28.0

# --- up-the-ramp exposures (nlpsf.sim.ramps) ---------------------------------------------------------

#: WFI frame time [s]: one read of the full array (romanisim ``parameters.read_time``).
ROMAN_FRAME_TIME_S = 3.04
#: Read noise per read [e-] for the optimal ramp fit: romanisim's default reference data
#: (5 DN at a gain of 2 e-/DN).
READ_NOISE_E = 10.0
#: Most reads an MA table (or ``--ramp N``) may have.
MAX_RAMP_READS = 10_000
READ_NOISE_RANGE_E = (0.0, 1e4)
#: The optimal fit diagonalises a resultant covariance per number of usable resultants (O(K^3)
#: each): at most this many resultants (Roman's imaging tables have 6 to 16).
MAX_OPTIMAL_RESULTANTS = 100

# --- names (one owner each) -------------------------------------------------------------------------

#: Requirement metrics: size Delta R / R, ellipticity components, and the modulus |Delta e|.
METRICS: tuple[str, ...] = ("size", "e1", "e2", "e")
#: What a simulation measures per realization (result and table column names): Delta R / R, Delta e1, Delta e2.
MEASURED: tuple[str, ...] = ("dR_over_R", "de1", "de2")
#: Each requirement metric as the measured quantities it is made of (``e``: hypot(de1, de2)).
METRIC_COLUMNS: dict[str, tuple[str, ...]] = {"size": ("dR_over_R",), "e1": ("de1",), "e2": ("de2",), "e": ("de1", "de2")}
#: bias: an error in the mean beta; scatter: a per-pixel spread of beta.
MODES: tuple[str, ...] = ("bias", "scatter")
#: Simulation methods: the first-order (linear) response, or every realization fitted.
METHODS: tuple[str, ...] = ("linear", "monte_carlo")
#: Sign conventions of beta: paper S = Q - beta Q^2; GalSim/romanisim S = Q + beta Q^2.
BETA_CONVENTIONS: tuple[str, ...] = ("paper", "galsim")
#: Ramp slope fits: ordinary least squares, or optimally weighted for read + Poisson noise.
RAMP_FITS: tuple[str, ...] = ("ols", "optimal")
#: How the pupil mask's pixel scale is set (see ``roman.pupil``).
PUPIL_SCALE_RULES: tuple[str, ...] = ("galsim", "header", "official")
PUPIL_SCALE = "galsim"
#: Throughput (effective-area) data, newest first: the official per-SCA curves of
#: roman-technical-information 1.5.0, and GalSim 2.8.5's 2021 table (one curve for every SCA).
THROUGHPUTS: tuple[str, ...] = ("roman-2024", "galsim-2021")
THROUGHPUT = "roman-2024"

# --- ranges every entry point accepts ------------------------------------------------------------

MAGNITUDE_RANGE = (-5.0, 40.0)
#: |beta| in either convention [1/e-].
MAX_ABS_BETA = 1e-3
BETA0_RANGE = (1e-12, 1e-3)
#: Exposure time [s]: below a microsecond no Roman read exists, and the flux arithmetic of a
#: subnormal exposure underflows (log10 of zero), so it is refused rather than computed.
EXPTIME_RANGE_S = (1e-6, 1e6)
#: Full well [e-]: at least one electron.
FULL_WELL_RANGE_E = (1.0, 1e9)
MAX_REALIZATIONS = 100_000
STAMP_RANGE = (16, 512)
OVERSAMPLING_RANGE = (1, 8)
MAX_WAVELENGTHS = 64
#: Precision (Delta beta / beta0) and tolerance ranges of the calculator.
PRECISION_RANGE = (1e-12, 1e3)
TOLERANCE_RANGE = (1e-15, 1e3)
#: The smallest relative accuracy a request may ask for: below the best measured fidelity error
#: (~1e-3) no level can promise it, and a target of 1e-320 is a typo, not a request.
ACCURACY_RANGE = (1e-4, 10.0)
#: Adaptive-moment weight cut rho^2: from a window of two sigma (the moments' own floor) to one far
#: past any stamp (1e308 overflowed the window's pixel count). The library also takes inf (no cut).
WEIGHT_CUT_RHO2_RANGE = (4.0, 1e4)
#: Random seeds: what numpy's generator takes.
SEED_RANGE = (0, 2**63 - 1)
#: Time between reads of an MA table [s] (the low end open).
FRAME_TIME_RANGE_S = (0.0, 1e4)
