"""The ``nlpsf`` command line.

Subcommands print a readable table, or with ``--json`` the same objects the Python API and the
REST API return. Bad arguments exit with status 2 and a message naming the argument.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable, Sequence

from . import __version__, experiment, moments, roman
from .checks import InputError

Command = Callable[[argparse.Namespace], int]
_COMMANDS: dict[str, Command] = {}


def register(name: str, configure: Callable[[argparse.ArgumentParser], None], help_text: str):
    """Decorator adding a subcommand; other modules (tables, solver, serve) plug in this way."""

    def wrap(function: Command) -> Command:
        _COMMANDS[name] = function
        _CONFIGURERS.append((name, configure, help_text))
        return function

    return wrap


_CONFIGURERS: list[tuple[str, Callable[[argparse.ArgumentParser], None], str]] = []


def _weight_cut(text: str) -> float:
    lowered = text.strip().lower()
    if lowered == "paper":
        return moments.PAPER_WEIGHT_CUT_RHO2
    if lowered == "galsim":
        return moments.GALSIM_WEIGHT_CUT_RHO2
    if lowered in ("none", "inf"):
        return math.inf
    return float(text)


def add_simulation_options(parser: argparse.ArgumentParser) -> None:
    """Options shared by every command that runs the simulator."""
    parser.add_argument("--band", default="H158", help=f"Roman band: {', '.join(roman.BANDS)} (default H158)")
    parser.add_argument("--sca", type=int, default=18, help="detector 1-18 (default 18, the paper's)")
    parser.add_argument(
        "--realizations", type=int, default=100, help="centroid realizations, or beta-map draws with --sigma-beta (default 100)"
    )
    parser.add_argument("--seed", type=int, default=1, help="random seed; the same seed gives the same numbers (default 1)")
    parser.add_argument("--oversampling", type=int, default=3, help="fine pixels per native pixel, N (default 3)")
    parser.add_argument("--stamp", type=int, default=96, help="stamp side in fine pixels (default 96)")
    parser.add_argument("--exptime", type=float, default=roman.DEFAULT_EXPTIME_S, help="exposure time in s (default 168.1)")
    parser.add_argument(
        "--full-well", type=float, default=roman.DEFAULT_FULL_WELL_E, help="full-well depth in e- (default 1.1e5)"
    )
    parser.add_argument(
        "--n-wavelengths",
        type=int,
        default=1,
        help="1: achromatic at the effective wavelength (paper); >1: integrate the band (polychromatic)",
    )
    parser.add_argument(
        "--weight-cut",
        type=_weight_cut,
        default=moments.PAPER_WEIGHT_CUT_RHO2,
        help="adaptive-moment weight cut rho^2: 'paper' (25, default), 'galsim' (32.24), 'none' or a number",
    )
    parser.add_argument(
        "--pupil-scale",
        choices=roman.PUPIL_SCALE_RULES,
        default="galsim",
        help="pupil mask scale rule (default galsim, see nlpsf/data/SOURCES.md)",
    )
    parser.add_argument(
        "--throughput",
        choices=roman.THROUGHPUTS,
        default=roman.DEFAULT_THROUGHPUT,
        help=f"effective-area data: {roman.DEFAULT_THROUGHPUT} (official, per SCA; default) or galsim-2021 (GalSim's)",
    )
    parser.add_argument(
        "--method", choices=experiment.METHODS, default="monte_carlo", help="monte_carlo (default) or linear response"
    )
    parser.add_argument(
        "--beta-convention",
        choices=("paper", "galsim"),
        default="paper",
        help="paper: S = Q - beta Q^2 (beta > 0); galsim: S = Q + beta Q^2 (beta < 0)",
    )


def config_from(args: argparse.Namespace) -> experiment.SimulationConfig:
    return experiment.SimulationConfig(
        band=args.band,
        sca=args.sca,
        realizations=args.realizations,
        seed=args.seed,
        oversampling=args.oversampling,
        stamp=args.stamp,
        exptime_s=args.exptime,
        full_well_e=args.full_well,
        n_wavelengths=args.n_wavelengths,
        weight_cut_rho2=args.weight_cut,
        pupil_scale=args.pupil_scale,
        method=args.method,
        throughput=args.throughput,
    )


def _progress_printer(enabled: bool):
    if not enabled:
        return None

    def show(done: int, total: int, message: str) -> None:
        width = 30
        filled = int(width * done / max(total, 1))
        sys.stderr.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {100 * done / max(total, 1):5.1f} % {message:<30}")
        if done >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()

    return show


def _configure_simulate(parser: argparse.ArgumentParser) -> None:
    add_simulation_options(parser)
    parser.add_argument("--magnitude", type=float, action="append", help="AB magnitude; repeat for several (default 18.3)")
    parser.add_argument("--beta", type=float, action="append", help="NL coefficient per e-; repeat for several (default 5e-7)")
    parser.add_argument(
        "--sigma-beta", type=float, default=0.0, help="per-pixel beta scatter; > 0 draws beta maps at a fixed centroid"
    )
    parser.add_argument("--json", action="store_true", help="print JSON (one object, or a list for several magnitudes/betas)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def _fmt(value: float | None, spec: str = ".4e") -> str:
    return "n/a" if value is None else format(value, spec)


@register("simulate", _configure_simulate, "simulate NL-induced PSF size and ellipticity changes")
def _simulate(args: argparse.Namespace) -> int:
    config = config_from(args)
    magnitudes = args.magnitude or [18.3]
    betas = args.beta or [5e-7]
    results = experiment.simulate(
        config,
        magnitudes,
        betas,
        sigma_beta=args.sigma_beta,
        beta_convention=args.beta_convention,
        progress=_progress_printer(not args.quiet and not args.json and len(magnitudes) * len(betas) > 1),
    )
    payload = [r.to_dict() for r in results]
    if args.json:
        print(json.dumps(payload[0] if len(payload) == 1 else payload, indent=2, allow_nan=False))
        return 0
    print(
        f"{config.band} SCA {config.sca}, {config.exptime_s:g} s, N={config.oversampling}, {config.stamp}x{config.stamp}, "
        f"{config.realizations} realizations, seed {config.seed}, {config.fidelity}"
    )
    print(f"{'mag':>6} {'beta':>10} {'flux e-':>10} {'peak e-':>10} {'dR/R':>12} {'+-':>9} {'de1':>12} {'de2':>12}")
    for r in results:
        print(
            f"{r.magnitude:6.2f} {r.beta:10.3e} {r.flux_electrons:10.4g} {r.peak_electrons:10.4g} "
            f"{_fmt(r.dR_over_R.mean)} {_fmt(r.dR_over_R.stderr, '.1e'):>9} {_fmt(r.de1.mean)} {_fmt(r.de2.mean)}"
        )
        for flag in r.flags:
            print(f"       ! {flag}")
    return 0


def _configure_slopes(parser: argparse.ArgumentParser) -> None:
    add_simulation_options(parser)
    parser.add_argument(
        "--magnitude", type=float, action="append", help="AB magnitude; repeat (default 18.3 19 20 21 22, the paper's)"
    )
    parser.add_argument("--beta0", type=float, default=5e-7, help="beta at which slopes are taken (default 5e-7)")
    parser.add_argument(
        "--sigma-beta",
        type=float,
        default=None,
        help="per-pixel beta scatter for the Monte Carlo scatter slope (default 0.1 beta0)",
    )
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--quiet", action="store_true")


@register("slopes", _configure_slopes, "bias slopes d(metric)/dbeta and scatter slopes sigma(metric)/sigma_beta vs magnitude")
def _slopes(args: argparse.Namespace) -> int:
    config = config_from(args)
    magnitudes = args.magnitude or [18.3, 19.0, 20.0, 21.0, 22.0]
    results = experiment.slopes(
        config,
        magnitudes,
        beta0=args.beta0,
        sigma_beta=args.sigma_beta,
        beta_convention=args.beta_convention,
        progress=_progress_printer(not args.quiet and not args.json),
    )
    payload = [r.to_dict() for r in results]
    if args.json:
        print(json.dumps(payload, indent=2, allow_nan=False))
        return 0
    print(
        f"{config.band} SCA {config.sca}, beta0={args.beta0:g}, {config.fidelity}; "
        "bias slope d(metric)/dbeta and scatter slope sigma(metric)/sigma_beta"
    )
    print(
        f"{'mag':>6} {'size bias':>11} {'+-':>8} {'e1 bias':>10} {'e2 bias':>10} "
        f"{'size scat':>11} {'e1 scat':>10} {'e2 scat':>10}"
    )
    for r in results:
        b, s = r.bias, r.scatter
        print(
            f"{r.magnitude:6.2f} {_fmt(b['dR_over_R'].mean, '11.5g')} {_fmt(b['dR_over_R'].stderr, '8.2g')} "
            f"{_fmt(b['de1'].mean, '10.5g')} {_fmt(b['de2'].mean, '10.5g')} {_fmt(s['dR_over_R']['value'], '11.5g')} "
            f"{_fmt(s['de1']['value'], '10.5g')} {_fmt(s['de2']['value'], '10.5g')}"
        )
        for flag in r.flags:
            print(f"       ! {flag}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    _load_plugins()
    parser = argparse.ArgumentParser(prog="nlpsf", description="Detector nonlinearity requirements for Roman PSF modelling.")
    parser.add_argument("--version", action="version", version=f"nlpsf {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name, configure, help_text in _CONFIGURERS:
        configure(sub.add_parser(name, help=help_text, description=help_text))
    return parser


def _load_plugins() -> None:
    """Import the modules that register further subcommands (kept out of the import of this one)."""
    import importlib

    for module in ("nlpsf.tables", "nlpsf.solver", "nlpsf.fidelity", "nlpsf.serve"):
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as error:
            if error.name != module:
                raise


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return _COMMANDS[args.command](args)
    except InputError as error:
        print(f"nlpsf {args.command}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
