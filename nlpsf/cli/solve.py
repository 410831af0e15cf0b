"""``nlpsf solve``: given two of precision, tolerance and magnitude, the third (paper Eq. calib)."""

from __future__ import annotations

import argparse

from nlpsf.sim.levels import LEVELS

from .. import defaults
from . import progress_printer
from .options import add_exposure, add_scene_options, print_json, ramp_from, scene_from, with_error


def _sca(text: str):
    if text.strip().lower() == "all":
        return "all"
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 1-{defaults.N_SCA} or all, got {text!r}") from None


def configure(parser: argparse.ArgumentParser) -> None:
    add_star_options(parser, over_field=True)
    parser.add_argument("--metric", choices=defaults.METRICS, default="size", help="size (dR/R), e1, e2, or e (|de|)")
    parser.add_argument(
        "--mode", choices=defaults.MODES, default="bias", help="bias: error in the mean beta; scatter: per-pixel spread"
    )
    parser.add_argument("--precision", type=float, help="delta_beta / beta0 (bias) or sigma_beta / beta0 (scatter)")
    parser.add_argument("--tolerance", type=float, help="allowed PSF error: dR/R, |de1|, |de2| or |de|")
    _add_budget_options(parser)
    parser.add_argument(
        "--over-field",
        action="store_true",
        help="answer for the worst position on the SCA (all 18 SCAs with --sca all): the Roman default's field-grid "
        "nodes, read from its shipped grid; with --scene paper the centre and four corner field points, from the "
        "field-point tables; simulated with a changed scene or a simulating --fidelity",
    )
    parser.add_argument("--fidelity", choices=LEVELS, default=None, help="how the slope is obtained (default table)")
    parser.add_argument(
        "--accuracy",
        type=float,
        default=None,
        help="relative accuracy wanted: picks the cheapest fidelity whose measured error is below it (instead of --fidelity)",
    )
    parser.add_argument(
        "--batch",
        metavar="FILE.csv",
        help="solve every row of a CSV (header: any of " + ", ".join(BATCH_COLUMNS) + "; empty cells take the options' "
        "values); prints one CSV row per input row (or, with --json, a JSON list), each answered or failed on its own",
    )


def add_star_options(parser: argparse.ArgumentParser, over_field: bool) -> None:
    """The star and how it is observed, as a solve request reads them (band, SCA, beta0, exposure and
    readout, magnitude, photometry, pupil rule, detector state, the scene): ``solve``'s options that
    ``kernel`` and ``residual`` share. ``over_field``: an answer over the SCA (``solve``: without
    ``--position`` every field-grid node, ``--sca all`` with ``--over-field``), else one star (the SCA
    centre without ``--position``)."""
    parser.add_argument("--band", default=defaults.BAND, help=f"Roman band: {', '.join(defaults.BANDS)}")
    if over_field:
        parser.add_argument(
            "--sca",
            type=_sca,
            default=defaults.SCA,
            help=f"detector 1-{defaults.N_SCA} (the paper's is 18); all with --over-field",
        )
    else:
        parser.add_argument("--sca", type=int, default=defaults.SCA, help=f"detector 1-{defaults.N_SCA} (the paper's is 18)")
    parser.add_argument("--beta0", type=float, default=defaults.BETA0, help="nominal NL coefficient [1/e-], paper convention")
    add_exposure(parser)
    parser.add_argument("--magnitude", type=float, help="AB magnitude of the brightest PSF star")
    parser.add_argument(
        "--throughput",
        choices=defaults.THROUGHPUTS,
        default=None,
        help=f"photometry of the magnitude: default the tables' own ({defaults.THROUGHPUT}); another relabels them",
    )
    parser.add_argument(
        "--pupil-scale",
        choices=defaults.PUPIL_SCALE_RULES,
        default=None,
        help=f"pupil mask scale rule of fresh simulations: default the tables' own ({defaults.PUPIL_SCALE}); "
        "another one simulates (fidelity linear); see nlpsf/data/SOURCES.md",
    )
    from nlpsf.sim.experiment.config import LINEARISE_STATES

    parser.add_argument(
        "--linearise-at",
        choices=LINEARISE_STATES,
        default=None,
        help="the detector state the slope is taken at: corrected (after the pipeline's linearity correction; the "
        "Roman default's) or beta0 (the uncorrected detector; the paper's, --scene paper's default)",
    )
    from nlpsf.sim.experiment.correction import RESIDUAL_MODELS

    parser.add_argument(
        "--residual-nl",
        choices=RESIDUAL_MODELS,
        default=None,
        help="how a calibration error acts in the corrected state: per_resultant_correction (the default: the "
        "linearity correction evaluated on every resultant of the measured, IPC-coupled signal, as romancal's linearity "
        "step applies it) or per_read_beta (the earlier model: a residual beta on every read before IPC)",
    )
    add_scene_options(parser, "solve" if over_field else "roman")
    parser.add_argument("--json", action="store_true", help="print the JSON object other tools read")


def _add_budget_options(parser: argparse.ArgumentParser) -> None:
    """The shear budgets that stand in for the tolerance, and the stars a scatter answer averages."""
    parser.add_argument(
        "--shear-m",
        type=float,
        help="multiplicative shear-bias budget |m| (size metric); with --size-ratio, takes the place of --tolerance",
    )
    parser.add_argument(
        "--shear-c",
        type=float,
        help="additive shear-bias budget |c| (e1, e2, e metrics); with --size-ratio, takes the place of --tolerance",
    )
    parser.add_argument(
        "--size-ratio",
        help="R_gal/R_psf, intrinsic galaxy over PSF, R = det(M)^(1/4): a number, 'ratio:weight,...' or @FILE "
        "(lines 'ratio [weight]'); alone it reports the shear bias the tolerance implies",
    )
    parser.add_argument(
        "--stars",
        type=int,
        default=1,
        help="scatter mode: the PSF model averages this many stars/dithers on independent pixels (sigma / sqrt(n))",
    )


#: Request columns a batch CSV may carry, and how each cell is read.
BATCH_COLUMNS: dict[str, type] = {
    "band": str,
    "sca": int,
    "metric": str,
    "mode": str,
    "beta0": float,
    "exptime": float,
    "precision": float,
    "tolerance": float,
    "magnitude": float,
    "full_well": float,
    "fidelity": str,
    "accuracy": float,
    "throughput": str,
    "shear_m": float,
    "shear_c": float,
    "size_ratio": float,
    "stars": int,
}
#: Answer columns of the CSV output (the JSON output is ``Solution.to_dict()``).
ANSWER_COLUMNS = (
    "solved_for",
    "precision",
    "tolerance",
    "magnitude",
    "uncertainty",
    "uncertainty_statistical",
    "uncertainty_fidelity",
    "slope",
    "saturation_magnitude",
    "binding_limit",
    "fidelity",
    "flags",
)


#: The options that are SolveRequest fields as they are (exptime, scene and ramp are built from others).
_REQUEST_OPTIONS = (
    "band", "sca", "metric", "mode", "beta0", "precision", "tolerance", "magnitude", "full_well", "fidelity",
    "accuracy", "throughput", "shear_m", "shear_c", "size_ratio", "stars", "pupil_scale", "linearise_at",
    "residual_nl",
)  # fmt: skip


def _readout(args: argparse.Namespace, preset: str):
    """(ramp, exptime) of the options: None, None where the preset's own readout applies (the Roman
    default's HLWAS ramp and exposure; the paper's 168.1 s final frame)."""
    from nlpsf.request import presets

    ramp, exptime = ramp_from(args, presets.policy(preset).ramp_fit)
    return ramp, (exptime if ramp is not None or args.exptime is not None else None)


def run(args: argparse.Namespace) -> int:
    from nlpsf.request.resolve import SolveRequest
    from nlpsf.solve.solver import answer, solve_over_field

    if args.batch:
        return run_batch(args)
    scene, preset = _scene(args)
    ramp, exptime = _readout(args, preset)
    if args.over_field:
        if ramp is not None:
            from ..checks import InputError

            raise InputError("ramp", "--over-field works on the final frame; give no ramp")
        solution = solve_over_field(
            args.band,
            "all" if args.sca == "all" else [args.sca],
            scene=scene,
            filled_for=_FILLED_FOR if args.sca == "all" else args.sca,  # the SCA _default_with_changes filled
            preset=preset,
            linearise_at=args.linearise_at,
            residual_nl=args.residual_nl,
            progress=progress_printer(not args.json),
            metric=args.metric,
            mode=args.mode,
            beta0=args.beta0,
            exptime=exptime,
            precision=args.precision,
            tolerance=args.tolerance,
            magnitude=args.magnitude,
            full_well=args.full_well,
            fidelity=args.fidelity,
            accuracy=args.accuracy,
            throughput=args.throughput,
            shear_m=args.shear_m,
            shear_c=args.shear_c,
            size_ratio=args.size_ratio,
            stars=args.stars,
            pupil_scale=args.pupil_scale,
        )
        return _report(solution, args)
    if args.sca == "all":
        from ..checks import InputError

        raise InputError("sca", "--sca all needs --over-field")
    request = SolveRequest.from_mapping(
        {
            **{name: getattr(args, name) for name in _REQUEST_OPTIONS},
            "exptime": exptime,
            "scene": scene,
            "preset": preset,
            "ramp": ramp,
        }
    )
    solution = answer(request)
    return _report(solution, args, request.ramp)


def _report(solution, args: argparse.Namespace, ramp=None) -> int:
    from nlpsf.solve.model_part import Rule

    payload = solution.to_dict()
    if args.json:
        print_json(payload)
        return 0
    print(
        f"{solution.band} SCA {solution.sca}, {solution.metric} {solution.mode}, beta0={solution.beta0:g} /e-, "
        f"{solution.exptime:g} s, full well {solution.full_well:.4g} e-, fidelity {solution.fidelity}"
    )
    if "roman_default" in solution.conditions:  # the answer quotes the Roman default's values
        changed = " (changed by the options given)" if solution.conditions.get("roman_default_changed") else ""
        scene = solution.conditions.get("scene_description", "").removeprefix("roman: ")  # its name is said already
        from nlpsf.request.presets import RESIDUAL_NL

        state = solution.conditions["linearise_at"]
        residual = solution.conditions.get("residual_nl")
        state += f" (residual model {residual})" if residual and residual != RESIDUAL_NL else ""
        print(f"  scene      the Roman default{changed}: {scene}; linearised at {state}")
    units = {"precision": "(fraction of beta0)", "tolerance": _tolerance_unit(solution.metric), "magnitude": "AB"}
    for name in ("precision", "tolerance", "magnitude"):
        value = payload[name]
        solved = name == solution.solved_for
        text = with_error(value, payload["uncertainty"]) if solved else ("n/a" if value is None else f"{value:.6g}")
        print(f"  {name:<10} {text} {units[name]}{'  <- solved' if solved else ''}")
    if payload["uncertainty"] is not None:
        # The Roman default counts the optics' vintage as one of its model parts (listed below), not apart.
        optics_in_model = bool((solution.model or {}).get("optical_model_included"))
        parts = ", ".join(
            f"{k} {payload[f'uncertainty_{k}']:.2g}"
            for k in ("statistical", "fidelity", "optical_model", "model")
            if payload[f"uncertainty_{k}"] is not None and not (k == "optical_model" and optics_in_model)
        )
        print(f"  uncertainty ({parts})")
    slope_unit = "per (1/e-) of " + ("beta" if solution.mode == "bias" else "sigma_beta")
    print(f"  slope c(m) {with_error(payload['slope'], payload['slope_uncertainty'])} {slope_unit}")
    if ramp is None:
        print(f"  saturation at m={solution.saturation_magnitude:.2f} AB")
    else:
        print(f"  ramp: {ramp.describe()}; slopes from {solution.conditions['ramp_slopes_from']}")
        print(
            f"  saturation at m={solution.saturation_magnitude:.2f} AB (ramp rule: resultant "
            f"{solution.conditions['ramp']['limit_resultant']}, the one a slope needs), "
            f"final frame m={solution.final_frame_saturation_magnitude:.2f} AB"
        )
    print(f"  applies to {solution.applies_to}")
    if solution.shear:
        _print_shear(solution.shear)
    if solution.binding_limit:
        print(f"  brightest usable star m={solution.brightest_usable_magnitude:.2f} AB ({solution.binding_limit} binds)")
    if solution.model:
        # An impact is measured only where the accuracy search ran (else the whole scene is simulated).
        # Entries with a reason are the Roman default's parts the request set or simulates (not counted).
        simulated = [e for e in solution.model["included"] if "why" not in e]
        dropped = [e for e in solution.model["included"] if "why" in e]
        included = ", ".join(e["name"] if e["impact"] is None else f"{e['name']} {_percent(e['impact'])}" for e in simulated)
        if "accuracy" in solution.model:
            print(f"  effects simulated (accuracy {solution.model['accuracy']:g}, the full scene's): {included or 'none'}")
        elif simulated:
            how = "held by the tables" if solution.conditions.get("fidelity") == "table" else "simulated by the scene"
            print(f"  effects {how}: {', '.join(e['name'] for e in simulated)}")
        if dropped:
            print(f"  parts not counted (the request sets or simulates them): {', '.join(e['name'] for e in dropped)}")
        # Measured at the point (accuracy): signed; from the shipped worst cases: a magnitude only.
        measured = "accuracy" in solution.model and solution.model["combine"] != Rule.ROMAN_PARTS
        left = ", ".join(
            f"{e['name']} {_percent(e['impact'], measured or bool(e.get('measured_here')))}" for e in solution.model["left_out"]
        )
        print(f"  left out (in the model uncertainty): {left}")
    _print_beside(solution)
    for flag in solution.flags:
        print(f"  ! {flag}")
    return 0


def _print_beside(solution) -> None:
    """The conservative answer and the star-to-star ranges, beside the nominal one."""
    solved = solution.solved_for
    conservative = solution.conservative
    if conservative and conservative.get(solved) is not None:
        print(
            f"  conservative {solved} {conservative[solved]:.4g} (holds for a slope up to "
            f"{100 * conservative['relative_slope_bound']:.3g} % steeper: k = {conservative['coverage_factor']:g} on the "
            "standard parts, the left-out shifts in full)"
        )
    for name, entry in (solution.ranges or {}).items():
        values = entry.get(solved) or []
        if len(values) == 2 and None not in values:
            ends = " and ".join(entry["ends"])
            print(f"  range over stars ({name}: {ends}): {solved} {values[0]:.4g} to {values[1]:.4g}")


def _percent(value: float | None, signed: bool = True) -> str:
    if value is None:
        return "n/a"
    return f"{100 * value:+.2g} %" if signed else f"±{100 * value:.2g} %"


def _scene(args: argparse.Namespace):
    """(scene, preset): the scene options on their base -- the Roman default unless ``--scene``
    names another preset or a file -- or (None, preset) when no effect was changed (the preset's
    own scene: the Roman default's at the star's position, or the paper's)."""
    from nlpsf.request import presets as roman_default

    named = roman_default.named(args.scene)
    preset = roman_default.preset_of(None, named)
    changed = any(
        getattr(args, name, None) is not None
        for name in ("position", "sed", "jitter", "charge_diffusion", "ipc", "ipc_order", "nl_coefficients", "bfe", "background")
    )
    if not changed and (args.scene is None or named is not None):
        if getattr(args, "save_scene", None):
            _save_preset_scene(args, preset)
        return None, preset  # the preset's own scene (the request fills it)
    if roman_default.policy(preset).sky and (args.scene is None or named is not None):
        # Options change only what they name of the Roman default; its sky stays unless --background.
        return _default_with_changes(args), preset
    return _scene_of_options(args), preset


#: The SCA whose sky a changed Roman default is filled with under ``--sca all`` (each SCA of an
#: over-field answer then gets its own: ``over_field.own_conditions``).
_FILLED_FOR = 18


def _save_preset_scene(args: argparse.Namespace, preset: str) -> None:
    """``--save-scene`` with no effect changed: the preset's own scene, as a changed one would be
    written (the Roman default's with its sky for this band, SCA and readout; without ``--position``
    none, as the preset's own)."""
    from nlpsf.request import presets as roman_default
    from nlpsf.sim import scene as scenes

    if roman_default.policy(preset).sky:
        _default_with_changes(args)  # writes it (``scene_from``)
    else:
        scenes.save(roman_default.load_scene(preset), args.save_scene)


def _default_with_changes(args: argparse.Namespace):
    from nlpsf.request import presets as roman_default

    sca = args.sca if isinstance(args.sca, int) else _FILLED_FOR
    preset = roman_default.preset_of(None, roman_default.named(args.scene))
    ramp, exptime = _readout(args, preset)
    base = roman_default.sky_base(preset, args.band, sca, exptime, ramp)
    return _scene_of_options(argparse.Namespace(**{**vars(args), "scene": base}))


def _scene_of_options(args: argparse.Namespace):
    """The scene options on ``args.scene`` (a preset, a file or a SceneModel), or None when none was given."""
    given = any(
        getattr(args, name, None) is not None
        for name in (
            "scene",
            "position",
            "sed",
            "jitter",
            "charge_diffusion",
            "ipc",
            "ipc_order",
            "nl_coefficients",
            "bfe",
            "background",
        )
    )
    if not given:
        return None
    model, b2 = scene_from(args)
    if b2 is not None and b2 != args.beta0:
        from ..checks import InputError

        raise InputError("nl_coefficients", f"b2={b2:g} must equal --beta0 ({args.beta0:g}) in solve")
    return model


def _tolerance_unit(metric: str) -> str:
    return "(fractional size error dR/R)" if metric == "size" else f"(ellipticity error |d{metric}|)"


def _print_shear(budget: dict) -> None:
    kind = "m" if "m" in budget else "c"
    ratio = budget["size_ratio"]
    ratio_text = (
        f"{ratio:g}" if isinstance(ratio, float) else f"{len(ratio['ratios'])} ratios, effective {ratio['effective']:.4g}"
    )
    if budget["given"] == "tolerance":
        value = with_error(budget[kind], budget.get("uncertainty"))
        print(f"  implied shear bias |{kind}| {value} for R_gal/R_psf {ratio_text} ({budget['relation']})")
    else:
        print(f"  shear budget |{kind}| {budget[kind]:.4g}, R_gal/R_psf {ratio_text} -> tolerance {budget['tolerance']:.4g}")


def _batch_arguments(args: argparse.Namespace, row: dict[str, str], exptime: float) -> dict:
    from ..checks import InputError

    unknown = [name for name in row if name and name not in BATCH_COLUMNS]
    if unknown:
        raise InputError(unknown[0], f"unknown batch column (known: {', '.join(BATCH_COLUMNS)})")
    arguments = {name: getattr(args, name) for name in BATCH_COLUMNS}
    arguments["exptime"] = exptime
    for name, cell in row.items():
        if not cell:
            continue
        try:
            arguments[name] = BATCH_COLUMNS[name](cell)
        except ValueError:
            raise InputError(name, f"cannot read {cell!r} as a {BATCH_COLUMNS[name].__name__}") from None
    return arguments


def run_batch(args: argparse.Namespace) -> int:
    """One solve per CSV row; a refused row is reported in its own row and does not stop the others."""
    import csv
    import sys

    from nlpsf.request.resolve import SolveRequest
    from nlpsf.request.rows import request_rows
    from nlpsf.solve.solver import answer

    from ..checks import InputError, SimulationError

    scene, preset = _scene(args)
    ramp, exptime = _readout(args, preset)
    try:
        with open(args.batch, newline="", encoding="utf-8") as handle:
            text = handle.read()
    except OSError as error:
        raise InputError("batch", f"cannot read {args.batch}: {error.strerror}") from None
    except UnicodeDecodeError as error:
        raise InputError("batch", f"{args.batch} is not UTF-8 text (byte {error.start})") from None
    try:
        rows = request_rows(text)
    except InputError as error:
        raise InputError("batch", f"{args.batch}: {error.reason}") from None
    answers: list[dict] = []
    for index, row in enumerate(rows):
        try:
            arguments = _batch_arguments(args, row, exptime)
            row_ramp = ramp
            if ramp is not None and args.read_noise is None and arguments["sca"] != args.sca:
                # No read noise given: each row's ramp fit uses its own SCA's official value.
                row_ramp = _readout(argparse.Namespace(**{**vars(args), "sca": arguments["sca"]}), preset)[0]
            request = SolveRequest.from_mapping(
                {**arguments, "ramp": row_ramp, "pupil_scale": args.pupil_scale, "scene": scene, "preset": preset,
                 "linearise_at": args.linearise_at, "residual_nl": args.residual_nl}
            )  # fmt: skip
            solution = answer(request)
            answers.append({"index": index, "ok": True, "solution": solution.to_dict()})
        except (InputError, SimulationError) as error:
            field = getattr(error, "argument", None)
            reason = getattr(error, "reason", str(error))
            answers.append({"index": index, "ok": False, "error": {"field": field, "message": reason}})
    if args.json:
        print_json(answers)
    else:
        writer = csv.writer(sys.stdout, lineterminator="\n")
        inputs = list(rows[0]) if rows else []
        writer.writerow(["row", *inputs, *ANSWER_COLUMNS, "error_field", "error"])
        for row, answer in zip(rows, answers, strict=True):
            cells = [answer["index"], *(row.get(name, "") for name in inputs)]
            if answer["ok"]:
                solution = answer["solution"]
                values = ["; ".join(solution[k]) if k == "flags" else solution[k] for k in ANSWER_COLUMNS]
                writer.writerow([*cells, *("" if v is None else v for v in values), "", ""])
            else:
                writer.writerow(
                    [*cells, *([""] * len(ANSWER_COLUMNS)), answer["error"]["field"] or "", answer["error"]["message"]]
                )
    failed = sum(1 for a in answers if not a["ok"])
    if failed:
        print(f"{failed} of {len(answers)} rows could not be solved (see their error column)", file=sys.stderr)
    return 0 if not failed else 1
