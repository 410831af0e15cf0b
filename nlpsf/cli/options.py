"""Options shared by the subcommands that run the simulator, and the printing helpers.

Built from ``nlpsf.defaults`` alone, so configuring a parser costs nothing; the simulator is
imported by ``config_from`` when a command runs.
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

from .. import defaults

#: The weight cuts ``--weight-cut`` takes by name.
WEIGHT_CUTS = {
    "paper": defaults.PAPER_WEIGHT_CUT_RHO2,
    "galsim": defaults.GALSIM_WEIGHT_CUT_RHO2,
    "none": math.inf,
    "inf": math.inf,
}


def weight_cut(text: str) -> float:
    lowered = text.strip().lower()
    if lowered in WEIGHT_CUTS:
        return WEIGHT_CUTS[lowered]
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected paper, galsim, none or a number, got {text!r}") from None


def add_band_sca(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--band", default=defaults.BAND, help=f"Roman band: {', '.join(defaults.BANDS)}")
    parser.add_argument("--sca", type=int, default=defaults.SCA, help=f"detector 1-{defaults.N_SCA} (the paper's is 18)")


def add_throughput(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--throughput",
        choices=defaults.THROUGHPUTS,
        default=defaults.THROUGHPUT,
        help="effective-area data: the official per-SCA curves of 2024, or GalSim's 2021 table (the paper comparison)",
    )


def add_exposure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--exptime",
        type=float,
        default=None,
        help="exposure time [s]; default: the scene's readout's (the Roman default: its HLWAS table's last read, "
        "139.149 s; the paper's: 168.1 s; with --ma-table, the table's last read)",
    )
    parser.add_argument("--full-well", type=float, default=defaults.FULL_WELL_E, help="full-well depth [e-]")
    add_ramp_options(parser)


def add_ramp_options(parser: argparse.ArgumentParser) -> None:
    """Up the ramp instead of the paper's single final frame (see nlpsf.sim.ramps)."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--ramp", type=int, default=None, metavar="N", help="N uniformly spaced reads over the exposure, one per resultant"
    )
    group.add_argument(
        "--ma-table",
        default=None,
        metavar="FILE|NAME",
        help="MultiAccum table: a JSON file ({'resultants': [[1], [2, 3], ...], 'frame_time_s': 3.04}) or a shipped name "
        "(romanisim-1, romanisim-109, romanisim-110)",
    )
    parser.add_argument(
        "--ramp-fit",
        choices=defaults.RAMP_FITS,
        default=None,
        help="slope fit: ols (ordinary least squares) or optimal (read + Poisson noise weighting); default ols, "
        "optimal (romancal's likelihood fit) for the Roman default's solve",
    )
    parser.add_argument(
        "--read-noise",
        type=float,
        default=None,
        metavar="E",
        help="read noise per read [e-] for --ramp-fit optimal (default: the SCA's official value, its median CDS noise / sqrt 2)",
    )
    from nlpsf.sim.ramps import SATURATION_RULES, SINGLE_RESULTANT_RULES

    # None: the ramp's own default (ramps.build: romancal's rules), so the default has one owner.
    parser.add_argument(
        "--ramp-saturation",
        choices=SATURATION_RULES,
        default=None,
        help="which resultants saturate: signal (romancal's: the NL-lowered signal reaches the saturation level; the "
        "default) or charge (the charge at the resultant's last read passes the full well)",
    )
    parser.add_argument(
        "--single-resultant",
        choices=SINGLE_RESULTANT_RULES,
        default=None,
        help="a pixel left with one usable resultant: unusable (romancal, no slope; the default) or through_zero (S_1 / t_1)",
    )


def ramp_from(args: argparse.Namespace, default_fit: str = "ols"):
    """(ramps.Ramp or None, exposure time [s]) for these options (``default_fit`` unless --ramp-fit)."""
    from nlpsf.sim.ramps import build

    sca = getattr(args, "sca", None)
    rules = {"saturation": args.ramp_saturation, "single_resultant": args.single_resultant}
    return build(
        args.ramp,
        args.ma_table,
        args.ramp_fit or default_fit,
        args.read_noise,
        args.exptime,
        sca=sca if isinstance(sca, int) else defaults.SCA,  # the official read noise of this SCA unless given
        **{k: v for k, v in rules.items() if v is not None},
    )


def add_simulation_options(parser: argparse.ArgumentParser, band_sca: bool = True, scene_base: str = "paper") -> None:
    """Options shared by every command that runs the simulator (``band_sca=False``: the caller adds
    its own; ``scene_base``: the scene its scene options change, a key of :data:`SCENE_BASES`)."""
    if band_sca:
        add_band_sca(parser)
    parser.add_argument(
        "--realizations",
        type=int,
        default=defaults.REALIZATIONS,
        help="centroid realizations, or beta-map draws with --sigma-beta",
    )
    parser.add_argument("--seed", type=int, default=defaults.SEED, help="random seed; the same seed gives the same numbers")
    parser.add_argument("--oversampling", type=int, default=defaults.OVERSAMPLING, help="fine pixels per native pixel, N")
    parser.add_argument("--stamp", type=int, default=defaults.STAMP, help="stamp side [fine pixels]")
    add_exposure(parser)
    parser.add_argument(
        "--n-wavelengths",
        type=int,
        default=1,
        help="1: achromatic at the band's effective wavelength (the paper); >1: integrate the band for a flat-f_nu star",
    )
    parser.add_argument(
        "--weight-cut",
        type=weight_cut,
        default=defaults.PAPER_WEIGHT_CUT_RHO2,
        help="adaptive-moment weight cut rho^2: 'paper' (25, the default), 'galsim' (32.24), 'none' or a number",
    )
    parser.add_argument(
        "--pupil-scale",
        choices=defaults.PUPIL_SCALE_RULES,
        default=None,
        help="pupil mask scale rule (see nlpsf/data/SOURCES.md); default official for the Roman default, "
        f"{defaults.PUPIL_SCALE} for --scene paper",
    )
    add_throughput(parser)
    parser.add_argument(
        "--method", choices=defaults.METHODS, default="monte_carlo", help="every realization fitted, or the linear response"
    )
    parser.add_argument(
        "--beta-convention",
        choices=defaults.BETA_CONVENTIONS,
        default="paper",
        help="paper: S = Q - beta Q^2 (beta > 0); galsim: S = Q + beta Q^2 (beta < 0, e.g. -6e-7)",
    )
    add_scene_options(parser, scene_base)
    parser.add_argument("--json", action="store_true", help="print JSON instead of a table")
    parser.add_argument("--quiet", action="store_true", help="no progress bar (there is none unless stderr is a terminal)")


#: The scene a command's scene options change (its group's description) and where it puts the star
#: without ``--position``, by the command's base: the Roman default's (``solve``: every field-grid
#: node of the SCA; ``simulate``, ``slopes``: the SCA centre) or the paper's (``sweep``, ``impact``).
_ROMAN_SCENE = (
    "the Roman default's scene (nlpsf.request.presets: its effects on, its sky) unless --scene names another; "
    "each option changes what it names"
)
SCENE_BASES = {
    "solve": (_ROMAN_SCENE, "every field-grid node of the SCA: the answer that holds everywhere on it"),
    "roman": (_ROMAN_SCENE, "the SCA centre"),
    "paper": ("effects beyond the paper's scene (all off by default)", "the centre"),
}


def add_scene_options(parser: argparse.ArgumentParser, scene_base: str = "paper") -> None:
    """The scene effects (``nlpsf.sim.scene``) over the command's base scene (:data:`SCENE_BASES`); a
    preset or file first, then overrides."""
    description, where = SCENE_BASES[scene_base]
    group = parser.add_argument_group("scene", description)
    group.add_argument(
        "--scene",
        help="a preset (roman: the Roman default, solve's default; paper: the paper's idealised scene and final frame; "
        "galsim-roman: GalSim's Roman jitter 0.014\", diffusion 0.1 px, IPC, flat f_nu) or a JSON file",
    )
    group.add_argument("--position", help=f"X,Y on the SCA [pixels, 1-4088] (default {where})")
    group.add_argument(
        "--sed", help="star SED: flat (f_nu), blackbody:TEFF, k0v (Pickles 1998 K0V spectrum), or a two-column file (nm, flux)"
    )
    group.add_argument("--sed-units", choices=("flambda", "fnu"), default="flambda", help="what a SED file's flux column is")
    group.add_argument("--jitter", type=float, help="pointing jitter [arcsec rms per axis] (GalSim's Roman: 0.014)")
    group.add_argument("--charge-diffusion", type=float, help="charge diffusion [native pixels rms] (GalSim's Roman: 0.1)")
    group.add_argument("--ipc", help="interpixel capacitance: roman, a nearest-neighbour alpha, a 3x3 file, or none")
    group.add_argument("--ipc-order", choices=("after", "before"), help="IPC after (default, as GalSim) or before the NL")
    group.add_argument(
        "--nl-coefficients",
        help="polynomial NL b2,b3,... (S = Q - b2 Q^2 - b3 Q^3 ..., in --beta-convention); b2 sets beta/beta0",
    )
    group.add_argument(
        "--bfe", type=float, help="brighter-fatter coefficient a [1/e-] (Antilogus et al. 2014, nearest neighbours; no default)"
    )
    group.add_argument("--background", type=float, help="sky + dark [e- per native pixel over the exposure]")
    group.add_argument("--save-scene", metavar="FILE", help="also write the scene to FILE as JSON (reload with --scene FILE)")


def scene_from(args: argparse.Namespace):
    """(scene, b2): the scene these options describe, and b2 when --nl-coefficients gave it."""
    from nlpsf.sim import scene as scenes

    from ..checks import InputError

    b2 = None
    higher = None
    if getattr(args, "nl_coefficients", None) is not None:
        values = scenes.parse_coefficients(args.nl_coefficients)
        if not values:
            raise InputError("nl_coefficients", "give b2 and any higher-order coefficients, comma-separated")
        b2, higher = values[0], values[1:]
        if getattr(args, "beta_convention", "paper") == "galsim":
            higher = tuple(-c for c in higher)  # the scene holds the paper's convention
    base = getattr(args, "scene", None)
    if isinstance(base, str):
        from nlpsf.request import presets as roman_default

        base = roman_default.load_scene(base)  # a preset's scene (the default's "roman" included) or a file
    model = scenes.from_options(
        base,
        position=getattr(args, "position", None),
        sed=getattr(args, "sed", None),
        sed_units=getattr(args, "sed_units", "flambda"),
        jitter=getattr(args, "jitter", None),
        charge_diffusion=getattr(args, "charge_diffusion", None),
        ipc=getattr(args, "ipc", None),
        ipc_order=getattr(args, "ipc_order", None),
        nl_coefficients=higher,
        bfe=getattr(args, "bfe", None),
        background=getattr(args, "background", None),
    )
    if getattr(args, "save_scene", None):
        scenes.save(model, args.save_scene)
    return model, b2


def beta_from_coefficients(given: float | None, b2: float | None, default: float) -> float:
    """beta (or beta0): --nl-coefficients' b2 when given, which must then agree with --beta/--beta0."""
    from ..checks import InputError

    if b2 is None:
        return default if given is None else given
    if given is not None and given != b2:
        raise InputError("nl_coefficients", f"b2={b2:g} disagrees with the beta given ({given:g}); give one of them")
    return b2


def simulation_preset(args: argparse.Namespace) -> str:
    """The preset a simulating command builds on: the Roman default unless ``--scene`` names
    another preset or a file (a file's scene on the paper's readout, as before)."""
    from nlpsf.request import presets as roman_default

    given = getattr(args, "scene", None)
    if given is None:
        return roman_default.preset_of(None)
    return roman_default.named(given) or roman_default.FILE_PRESET


def config_from(args: argparse.Namespace, roman_default_applies: bool = False):
    """The simulator's configuration for these options (validated by the library).

    ``roman_default_applies`` (``simulate``, ``slopes``): without ``--scene`` (or with ``--scene
    roman``) the star is the Roman default's (``nlpsf.request.presets``: its scene at ``--position``
    or the SCA centre, its sky, the HLWAS readout and exposure unless ``--ramp`` / ``--ma-table`` /
    ``--exptime`` are given, the official pupil scale unless ``--pupil-scale``); the scene options
    change only what they name. Otherwise (and with ``--scene paper``) the paper's, as before."""
    from nlpsf.request import presets as roman_default
    from nlpsf.sim.experiment import SimulationConfig

    preset = simulation_preset(args) if roman_default_applies else roman_default.FILE_PRESET
    settings = dict(vars(args))
    if roman_default.policy(preset).sky:
        ramp, exptime = ramp_from(args, roman_default.policy(preset).ramp_fit)
        sca = args.sca if isinstance(args.sca, int) else defaults.SCA
        filled = roman_default.fill(
            preset, args.band, sca, exptime if ramp is not None or args.exptime is not None else None, ramp, None, None
        )
        ramp, exptime = filled.ramp, filled.exptime
        base = roman_default.sky_base(preset, args.band, sca, exptime, ramp)
        scene = scene_from(argparse.Namespace(**{**settings, "scene": base}))[0]
        settings["pupil_scale"] = args.pupil_scale or filled.pupil_scale
    else:
        ramp, exptime = ramp_from(args)
        scene = scene_from(args)[0]
        settings["pupil_scale"] = args.pupil_scale or defaults.PUPIL_SCALE
    # The options named as the fields are taken as they are; these differ in name or meaning.
    return SimulationConfig.from_settings(
        settings,
        exptime_s=exptime,
        full_well_e=args.full_well,
        weight_cut_rho2=args.weight_cut,
        scene=scene,
        ramp=ramp,
    )


def with_default_conditions(payloads: list[dict], args: argparse.Namespace) -> list[dict]:
    """Results of the Roman default (``simulate``, ``slopes``) with its values and their sources in
    their conditions, as a solve quotes them; other presets' results as they are."""
    from nlpsf.request import presets as roman_default

    preset = simulation_preset(args)
    if not roman_default.policy(preset).quotes_default:
        return payloads
    values = roman_default.conditions()
    return [{**p, "conditions": {**p.get("conditions", {}), "scene_name": preset, "roman_default": values}}
            for p in payloads]  # fmt: skip


def print_json(payload: Any) -> None:
    print(json.dumps(payload, indent=2, allow_nan=False))


def number(value: float | None, digits: int = 4) -> str:
    """``digits`` significant digits, or n/a."""
    if value is None or not math.isfinite(value):
        return "n/a"
    return f"{value:.{digits}g}"


def with_error(value: float | None, error: float | None, digits: int = 4) -> str:
    """value ± error, the value to the error's second significant digit (at most ``digits``)."""
    if value is None or not math.isfinite(value):
        return "n/a"
    if error is None or not math.isfinite(error) or error <= 0:
        return number(value, digits)
    if value == 0:
        return f"0 ± {error:.2g}"
    # Significant digits of the value that reach the error's second digit.
    shown = max(2, min(digits + 2, int(math.floor(math.log10(abs(value))) - math.floor(math.log10(error)) + 2)))
    return f"{value:.{shown}g} ± {error:.2g}"
