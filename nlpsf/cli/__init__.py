"""The ``nlpsf`` command line.

Subcommands print a readable table, or with ``--json`` the same objects the Python API and the
REST API return. Bad arguments exit with status 2 and a message naming the option; a valid request
that fails while computing exits with status 1 and the reason.

Startup is kept cheap: this module imports nothing heavy, and only the chosen subcommand's module
is imported (each of those imports the library inside its ``run``), so ``nlpsf --help`` and
``nlpsf solve`` do not pay for scipy, astropy or the simulator.
"""

from __future__ import annotations

import argparse
import importlib
import os
import re
import sys
from collections.abc import Sequence

from .._version import __version__

#: name -> (module, one-line help). The modules are imported only when their command is chosen.
COMMANDS: dict[str, tuple[str, str]] = {
    "simulate": ("nlpsf.cli.simulate", "simulate NL-induced PSF size and ellipticity changes"),
    "slopes": ("nlpsf.cli.slopes", "bias slopes d(metric)/dbeta and scatter slopes sigma(metric)/sigma_beta vs magnitude"),
    "solve": ("nlpsf.cli.solve", "given two of precision, tolerance, magnitude, get the third"),
    "sweep": ("nlpsf.cli.sweep", "run a grid of simulations (bands x SCAs x magnitudes x betas), locally or on dask; resumable"),
    "tables": ("nlpsf.cli.tables", "slope tables: build, show, power-law fits"),
    "tradeoff": ("nlpsf.cli.tradeoff", "measure each fidelity level's error and time against the most exact one"),
    "impact": ("nlpsf.cli.impact", "what each scene effect (position, SED, jitter, IPC, ...) changes in the slopes"),
    "kernel": ("nlpsf.cli.kernel", "the response kernel K(Q): how a star's PSF metrics respond to a calibration residual"),
    "residual": ("nlpsf.cli.residual", "a calibration residual's effect on a star's PSF; the scale a residual shape may have"),
    "serve": ("nlpsf.cli.serve", "start the web service: REST API under /api/v1, docs at /docs, the page at /"),
}

#: Library argument names that differ from the option a user typed.
OPTION_FOR_ARGUMENT = {
    "exptime_s": "--exptime",
    "full_well_e": "--full-well",
    "weight_cut_rho2": "--weight-cut",
    "pupil_bin": "--pupil-bin",
    "offsets": "--realizations",
    "scene": "--scene",
    "bfe_coefficient": "--bfe",
    "background_e": "--background",
    "ma_table.resultants": "--ma-table",
    "ma_table.frame_time_s": "--ma-table",
    "ramp_single_resultant": "--single-resultant",
}


def option_name(argument: str) -> str:
    """The command-line option behind a library argument name (``full_well`` -> ``--full-well``)."""
    return OPTION_FOR_ARGUMENT.get(argument, "--" + argument.replace("_", "-"))


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows each option's default unless it has none (or its help already states it)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if action.default in (None, False, argparse.SUPPRESS) or "default" in text:
            return text
        return super()._get_help_string(action)


class Parser(argparse.ArgumentParser):
    """argparse with scientific-notation negative numbers as values (``--beta -6e-7``).

    argparse treats a token starting with '-' as an option unless it matches its negative-number
    pattern, which does not know exponents; this parser's pattern does (none of our options looks
    like a number, so nothing is lost).
    """

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = re.compile(r"^-(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?$")


def _chosen(argv: Sequence[str]) -> str | None:
    for token in argv:
        if token in COMMANDS:
            return token
        if not token.startswith("-"):
            return None
    return None


def build_parser(argv: Sequence[str] = ()) -> tuple[Parser, dict[str, object]]:
    """The parser, with only the chosen subcommand's options configured (all of them if none)."""
    parser = Parser(prog="nlpsf", description="Detector nonlinearity requirements for Roman PSF modelling.")
    parser.add_argument("--version", action="version", version=f"nlpsf {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=Parser)
    chosen = _chosen(argv)
    modules: dict[str, object] = {}
    for name, (module_name, help_text) in COMMANDS.items():
        subparser = sub.add_parser(name, help=help_text, description=help_text)
        if chosen == name:
            module = importlib.import_module(module_name)
            module.configure(subparser)
            modules[name] = module
    return parser, modules


def progress_printer(enabled: bool):
    """A one-line progress bar on stderr, only when stderr is a terminal (never in a pipe or log)."""
    if not enabled or not sys.stderr.isatty():
        return None

    def show(done: float, total: int, message: str) -> None:
        width = 30
        filled = int(width * done / max(total, 1))
        sys.stderr.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {100 * done / max(total, 1):5.1f} % {message:<30}")
        if done >= total:
            sys.stderr.write("\n")
        sys.stderr.flush()

    return show


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser, modules = build_parser(argv)
    args = parser.parse_args(argv)
    from ..checks import InputError, SimulationError

    try:
        return int(modules[args.command].run(args))
    except InputError as error:
        print(f"nlpsf {args.command}: error: {option_name(error.argument)}: {error.reason}", file=sys.stderr)
        return 2
    except SimulationError as error:
        print(f"nlpsf {args.command}: failed: {error}", file=sys.stderr)
        return 1
    except BrokenPipeError:
        # The reader went away (`| head`): stop quietly, as Unix tools do, without a traceback
        # from the interpreter's own flush at exit.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    raise SystemExit(main())
