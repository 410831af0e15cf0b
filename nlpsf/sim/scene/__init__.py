"""The scene model: what a real Roman star goes through besides the paper's idealised chain.

This module is the one owner of the scene effects. A :class:`SceneModel` is a frozen description
with every effect off by default (the paper's scene: SCA centre, one wavelength, the quadratic NL
only). The effects, in the order a photon meets them (DESIGN.md, "The scene model"):

``position``
    field position on the SCA in pixels (1-4088 each axis): the Zernikes are interpolated
    bilinearly between the SCA's corner field points exactly as ``galsim.roman.getPSF(SCA_pos=)``
    does (``nlpsf.roman.aberrations``).
``sed``
    the star's spectrum: ``flat`` (flat f_nu), ``blackbody:TEFF`` (kelvin), a vendored spectrum by
    name (``k0v``: ``nlpsf.roman.seds``) or a two-column table (wavelength nm, f_lambda or f_nu as
    ``sed_units`` says). The PSF is the photon-weighted mean
    over the band: counts per unit wavelength proportional to A_eff(lambda) f_lambda lambda. The
    flux in electrons stays the one the AB magnitude in the band gives (a band AB magnitude is a
    photon count relative to a flat-f_nu source's, whatever the SED).
``jitter`` / ``charge_diffusion``
    Gaussian blurs (arcsec rms per axis; native pixels rms). A convolution with a Gaussian of rms
    sigma multiplies the Fourier coefficients of the effective PSF by exp(-2 pi^2 sigma^2 f^2),
    which is exact on the periodic field the optics are kept on (``optics.EffectivePSF``).
``ipc``
    interpixel capacitance: a 3x3 kernel coupling *native* pixels (GalSim's normalised
    ``roman.ipc_kernel``, a symmetric nearest-neighbour alpha, or a 3x3 file), applied ``after``
    (default, as GalSim's Roman pipeline) or ``before`` the NL.
``nl_coefficients``
    NL beyond the quadratic: S = Q - b2 Q^2 - b3 Q^3 - b4 Q^4 ..., paper sign convention; the
    field holds (b3, b4, ...), b2 is the simulation's beta (so per-pixel scatter applies to b2).
``bfe_coefficient``
    brighter-fatter (see :func:`brighter_fatter`), no default.
``background_e``
    sky plus dark charge per native pixel over the exposure, added before the NL and subtracted
    afterwards as a local sky estimate does: a star-free pixel's own level, its NL included
    (S(Q + B) - S(B); ``experiment.sky``).

The package is the one owner of the scene's fields, in four modules: ``registry`` (one entry per
effect, the constants and limits), ``model`` (:class:`SceneModel` and its checks), ``io`` (presets,
JSON, files and user input) and ``kernels`` (what acts on the stamps: blurs, IPC, brighter-fatter,
the detector chain). Their public names are read from here (``from nlpsf.sim import scene``).

Rescaling rules. The tables' exposure and beta0 rescaling rests on the metrics depending on beta
and flux only through beta Q. Position, SED, jitter, diffusion and IPC (either order) are linear in
the charge and keep that rule. Polynomial NL (b3 Q^3 ...), brighter-fatter (a charge-dependent
redistribution, ~ a Q^2) and a background (beta (Q + B)^2 has a beta B term at fixed B) each add a
flux dependence of their own, so :meth:`SceneModel.breaks_beta_q_scaling` names them and callers
must simulate at the request's exposure and beta0 instead of rescaling.
"""

from .io import (
    PRESETS,
    from_dict,
    from_options,
    from_request,
    load,
    moved_or_changed,
    parse_coefficients,
    parse_ipc,
    parse_position,
    parse_sed,
    preset,
    read_table,
    save,
    to_json,
)
from .kernels import (
    apply_ipc,
    apply_ipc_adjoint,
    blur,
    brighter_fatter,
    charge_before_nl,
    detector_chain,
    gaussian_transfer,
)
from .model import SED_NAMES, SceneModel, binning_error, check_first_order, check_kernel, choose_wavelengths, planck_flambda
from .registry import (
    EFFECTS,
    IPC_ORDERS,
    MAX_BACKGROUND_E,
    MAX_BFE,
    MAX_DIFFUSION_PX,
    MAX_IPC_ALPHA,
    MAX_JITTER_ARCSEC,
    MAX_NL_ORDER,
    MODEL_UNCERTAINTY_FILE,
    NOMINAL,
    REGISTRY,
    ROMAN_CHARGE_DIFFUSION_PX,
    ROMAN_IPC_KERNEL,
    ROMAN_JITTER_ARCSEC,
    SED_UNITS,
    SLOPE_BINNING_FACTOR,
    WAVELENGTH_ACCURACY,
    SceneEffect,
    shipped_model_uncertainty,
)

__all__ = [
    "EFFECTS",
    "IPC_ORDERS",
    "MAX_BACKGROUND_E",
    "MAX_BFE",
    "MAX_DIFFUSION_PX",
    "MAX_IPC_ALPHA",
    "MAX_JITTER_ARCSEC",
    "MAX_NL_ORDER",
    "MODEL_UNCERTAINTY_FILE",
    "NOMINAL",
    "PRESETS",
    "REGISTRY",
    "ROMAN_CHARGE_DIFFUSION_PX",
    "ROMAN_IPC_KERNEL",
    "ROMAN_JITTER_ARCSEC",
    "SED_NAMES",
    "SED_UNITS",
    "SLOPE_BINNING_FACTOR",
    "WAVELENGTH_ACCURACY",
    "SceneEffect",
    "SceneModel",
    "apply_ipc",
    "apply_ipc_adjoint",
    "binning_error",
    "blur",
    "brighter_fatter",
    "charge_before_nl",
    "check_first_order",
    "check_kernel",
    "choose_wavelengths",
    "detector_chain",
    "from_dict",
    "from_options",
    "from_request",
    "gaussian_transfer",
    "load",
    "moved_or_changed",
    "parse_coefficients",
    "parse_ipc",
    "parse_position",
    "parse_sed",
    "planck_flambda",
    "preset",
    "read_table",
    "save",
    "shipped_model_uncertainty",
    "to_json",
]
