"""``nlpsf tradeoff``: measure each fidelity level's error and time against the most exact one."""

from __future__ import annotations

import argparse
import json

from . import progress_printer


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--write", action="store_true", help="store it in nlpsf/data/fidelity.json (read by --accuracy)")
    parser.add_argument("--json", action="store_true", help="print JSON instead of the markdown table")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument(
        "--scene",
        choices=("roman", "paper"),
        default="roman",
        help="measure inside the Roman default (stored under fidelity.json's 'roman') or the paper's scene (its top level)",
    )


def run(args: argparse.Namespace) -> int:
    from nlpsf.slopes import fidelity
    from nlpsf.solve import tradeoff

    result = tradeoff.tradeoff(progress=progress_printer(not args.quiet and not args.json), default=args.scene)
    if args.write:
        fidelity.write_measured(result, default=args.scene)
    print(json.dumps(result, indent=1) if args.json else tradeoff.markdown(result))
    return 0
