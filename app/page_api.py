"""What the page needs from the server beyond the resource endpoints: the calculator's plots, the
limits a refusal quotes, requirement presets with their sources, a CSV batch, and the user guide.

The page draws; every number it draws comes from here or from the resource endpoints. The curves are
the solver's own answers on a magnitude grid (``solver.solve`` at each point, 60 µs each), so the
relation T = |c(m)| p β₀ (× 1/√n for a scatter average) has one owner, the library.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from importlib import resources
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, Body, Query
from fastapi.responses import PlainTextResponse, Response

from nlpsf import defaults
from nlpsf.checks import InputError
from nlpsf.slopes import tables
from nlpsf.solve import relation
from nlpsf.solve import solver as solver_module

from . import models, params, solve_api
from .errors import SafeJSONResponse, json_safe

# The page's own endpoints: outside the versioned public schema (/openapi.json), which they would
# otherwise have to follow (typed models, units on every field); docs/page.md lists them.
router = APIRouter(prefix="/api/v1/page", tags=["page"], include_in_schema=False)

Positive = Annotated[float, Query(allow_inf_nan=False, gt=0)]
Tolerance = Annotated[float, Query(allow_inf_nan=False, gt=0, description="the chosen tolerance T (dimensionless)")]
At = Annotated[
    float | None, Query(allow_inf_nan=False, description="a magnitude (AB mag) added to the grid: the answer's, for the legend")
]
Stars = Annotated[int, Query(ge=1, le=1_000_000, description="stars averaged (count; scatter mode)")]
RampFactor = Annotated[
    float | None,
    Query(allow_inf_nan=False, gt=0, le=10, description="the answer's ramp factor beta_eff / beta0 (conditions.ramp)"),
]
ExactFrom = Annotated[
    float | None, Query(allow_inf_nan=False, description="the answer's ramp_table_exact_from_magnitude (AB mag)")
]

#: Tolerances drawn around the chosen one (multiples of T).
TOLERANCE_FACTORS = (0.1, 1 / 3, 1.0, 3.0, 10.0)


def _args(band: str, sca: int, metric: str, mode: str, exptime: float, beta0: float, full_well: float) -> dict[str, Any]:
    # The plots are the shipped tables' curves: the paper's scene (the calculator's answer, POST
    # /solve, is the Roman default's unless the page asks for the paper's).
    common = {"band": band, "sca": sca, "metric": metric, "mode": mode, "exptime": exptime, "beta0": beta0}
    return {**common, "full_well": full_well, "scene": "paper"}


def _grid(curve: dict[str, Any], at: float | None) -> list[float]:
    grid = list(curve["magnitude"])
    lo, hi = (grid[0], grid[-1]) if grid else (None, None)
    if at is not None and lo is not None and lo <= at <= hi and all(abs(m - at) > 1e-9 for m in grid):
        grid = sorted([*grid, at])
    return grid


def _safe_solve(**arguments: Any) -> dict[str, Any] | None:
    try:
        return solver_module.solve(**arguments).to_dict()
    except InputError:
        return None


def _fidelity_relative(points: list[dict[str, Any] | None]) -> float | None:
    # At precision 1 the solved tolerance is |c| beta0 and its fidelity part the level's relative error times it.
    for p in points:
        if p and p.get("uncertainty_fidelity") is not None and p.get("tolerance"):
            return abs(p["uncertainty_fidelity"] / p["tolerance"])
    return None


def limits(band: str, sca: int, metric: str, mode: str, exptime: float, beta0: float, full_well: float) -> dict[str, Any]:
    """Saturation, the non-monotonic limit and the brightest magnitude the solver answers for."""
    curve = tables.curve(band, sca, metric, mode, exptime=exptime, beta0=beta0, full_well=full_well)
    saturation = curve["saturation_magnitude"]
    common = _args(band, sca, metric, mode, exptime, beta0, full_well)

    def answered(m: float) -> bool:
        return _safe_solve(**common, precision=1.0, magnitude=m) is not None

    # Bisection on the solver's own acceptance: fainter is always answered, so the boundary is one number.
    bright, faint = saturation - 15.0, curve["magnitude"][-1] if curve["magnitude"] else saturation + 10
    if answered(bright):
        brightest = bright
    else:
        for _ in range(40):
            middle = 0.5 * (bright + faint)
            bright, faint = (bright, middle) if answered(middle) else (middle, faint)
        brightest = faint
    return {
        "saturation_magnitude": saturation,
        "nonmonotonic_magnitude": relation.nl_invalid_magnitude(band, sca, beta0, exptime),
        "brightest_answered_magnitude": brightest,
        "rules": {
            "saturation_magnitude": "brighter than this the brightest pixel passes the full well in a single final frame",
            "nonmonotonic_magnitude": "brighter than this 2 beta0 Q_peak >= 1: S = Q - beta Q^2 no longer rises with Q",
            "brightest_answered_magnitude": "the brightest magnitude the calculator answers for at these conditions "
            "(within 0.01 mag)",
        },
    }


@router.get("/limits", summary="Saturation, the non-monotonic limit and the brightest magnitude answered (AB mag)")
def limits_endpoint(
    band: params.Band = "H158",
    sca: params.Sca = 18,
    metric: params.MetricQuery = "size",
    mode: params.ModeQuery = "bias",
    exptime: params.Exptime = defaults.EXPTIME_S,
    beta0: params.Beta0 = defaults.BETA0,
    full_well: params.FullWell = defaults.FULL_WELL_E,
) -> SafeJSONResponse:
    return SafeJSONResponse(json_safe(limits(band.upper(), sca, metric, mode, exptime, beta0, full_well)))


@router.get("/requirement", summary="The calculator's two plots: p(m) around T, the slope c(m), limits")
def requirement(
    tolerance: Tolerance,
    band: params.Band = "H158",
    sca: params.Sca = 18,
    metric: params.MetricQuery = "size",
    mode: params.ModeQuery = "bias",
    exptime: params.Exptime = defaults.EXPTIME_S,
    beta0: params.Beta0 = defaults.BETA0,
    full_well: params.FullWell = defaults.FULL_WELL_E,
    stars: Stars = 1,
    at: At = None,
    ramp_factor: RampFactor = None,
    exact_from: ExactFrom = None,
) -> SafeJSONResponse:
    band = band.upper()
    common = _args(band, sca, metric, mode, exptime, beta0, full_well)
    curve = tables.curve(band, sca, metric, mode, exptime=exptime, beta0=beta0, full_well=full_well)
    bounds = limits(band, sca, metric, mode, exptime, beta0, full_well)
    saturation = bounds["saturation_magnitude"]
    grid = _grid(curve, at)
    usable = [m for m in grid if m >= saturation]  # curves stop at saturation
    requirement_curves = []
    for factor in TOLERANCE_FACTORS:
        t = tolerance * factor
        points = [_safe_solve(**common, tolerance=t, magnitude=m, stars=stars) for m in usable]
        requirement_curves.append(
            {
                "tolerance": t,
                "factor": factor,
                "magnitude": usable,
                "precision": [p["precision"] if p else None for p in points],
                "statistical": [p["uncertainty_statistical"] if p else None for p in points],
                "fidelity": [p["uncertainty_fidelity"] if p else None for p in points],
            }
        )
    slopes = [_safe_solve(**common, precision=1.0, magnitude=m, stars=stars) for m in usable]
    slope = {
        "magnitude": usable,
        "slope": [abs(s["slope"]) if s and s["slope"] is not None else None for s in slopes],
        "signed": any(s and s["slope"] is not None and s["slope"] < 0 for s in slopes),
        "statistical": [s["slope_uncertainty"] if s else None for s in slopes],
        "fidelity_relative_uncertainty": _fidelity_relative(slopes),
    }
    ramp = None
    if ramp_factor is not None:
        # OLS up the ramp: the final frame at beta_eff = factor β₀ wherever no pixel drops a resultant
        # (the solver's mapping), slope × factor.
        mapped = tables.curve(band, sca, metric, mode, exptime=exptime, beta0=beta0 * ramp_factor, full_well=full_well)
        keep = [i for i, m in enumerate(mapped["magnitude"]) if exact_from is None or m >= exact_from]
        ramp = {
            "factor": ramp_factor,
            "magnitude": [mapped["magnitude"][i] for i in keep],
            "slope": [abs(mapped["slope"][i] * ramp_factor) for i in keep],
            "statistical": [mapped["uncertainty"][i] * ramp_factor for i in keep],
        }
    return SafeJSONResponse(
        json_safe(
            {
                "source": "the solver at each magnitude of the shipped tables' grid (table fidelity, final-frame slopes)",
                "relation": "T = |c(m)| p beta0 (scatter: divided by sqrt(stars))",
                "conditions": curve["conditions"],
                "requirement": requirement_curves,
                "slope": slope,
                "ramp": ramp,
                "limits": bounds,
            }
        )
    )


@router.get("/slopes", summary="Slope vs magnitude for every band, stopping at saturation, with a chosen magnitude")
def slopes(
    metric: params.MetricQuery = "size",
    mode: params.ModeQuery = "bias",
    sca: params.Sca = 18,
    exptime: params.Exptime = defaults.EXPTIME_S,
    beta0: params.Beta0 = defaults.BETA0,
    full_well: params.FullWell = defaults.FULL_WELL_E,
    at: At = None,
) -> SafeJSONResponse:
    out = []
    for band in tables.load_tables().bands:
        curve = tables.curve(band, sca, metric, mode, exptime=exptime, beta0=beta0, full_well=full_well)
        common = _args(band, sca, metric, mode, exptime, beta0, full_well)
        usable = [m for m in _grid(curve, at) if m >= curve["saturation_magnitude"]]
        points = [_safe_solve(**common, precision=1.0, magnitude=m) for m in usable]
        out.append(
            {
                "band": band,
                "magnitude": usable,
                "slope": [abs(p["slope"]) if p and p["slope"] is not None else None for p in points],
                "statistical": [p["slope_uncertainty"] if p else None for p in points],
                "fidelity_relative_uncertainty": _fidelity_relative(points),
                "saturation_magnitude": curve["saturation_magnitude"],
                "conditions": curve["conditions"],
            }
        )
    return SafeJSONResponse(json_safe({"source": "the solver on the shipped tables' grid; absolute values", "curves": out}))


@router.get("/impact-terms", summary="What a change of the slope does to the precision an answer requires")
def impact_terms(
    precision: Positive,
    impact: Annotated[list[float], Query(max_length=50, description="slope with ÷ without − 1 for each effect")],
) -> SafeJSONResponse:
    # The relation is the library's (nlpsf.solve.relation); a vanishing slope asks no precision (null).
    asked = [relation.precision_with_impact(precision, x) for x in impact]
    return SafeJSONResponse(
        {
            "relation": "p_with = p / |1 + impact|: T = |c| p beta0 at fixed T and beta0",
            "precision": [p if math.isfinite(p) else None for p in asked],
        }
    )


# ---- requirement presets --------------------------------------------------------------------------

PRESETS: list[dict[str, Any]] = [
    {
        "id": "paper-size",
        "name": "The paper: size, 10 % of 1e-3",
        "fields": {"metric": "size", "tolerance": 1e-4},
        "source": "Plazas et al. 2016 (PASP 128, 104001): NL allotted 10 % of Roman's 1e-3 requirement on ΔR/R",
        "share": "10 % of the total, as the paper assumes",
    },
    {
        "id": "paper-e",
        "name": "The paper: ellipticity, 10 % of 4.7e-4",
        "fields": {"metric": "e", "tolerance": 4.7e-5},
        "source": "Plazas et al. 2016: NL allotted 10 % of Roman's 4.7e-4 requirement on |Δe|",
        "share": "10 % of the total, as the paper assumes",
    },
    {
        "id": "roman-m",
        "name": "Roman shear |m| < 3.2e-4",
        "fields": {"metric": "size", "shear_m": 3.2e-4, "size_ratio": 1.5},
        "source": "Roman's multiplicative shear-bias requirement (Berlfein et al. 2025, arXiv:2505.00093)",
        "share": "not public: the preset gives NL the whole budget; scale |m| by NL's share. The size ratio 1.5 is an "
        "example, not from the paper: set your galaxies' R_gal/R_psf",
    },
    {
        "id": "roman-m-relaxed",
        "name": "Roman shear |m| < 1e-3 (relaxed)",
        "fields": {"metric": "size", "shear_m": 1e-3, "size_ratio": 1.5},
        "source": "the relaxed multiplicative shear-bias requirement in Berlfein et al. 2025 (arXiv:2505.00093)",
        "share": "not public: the preset gives NL the whole budget; the size ratio 1.5 is an example",
    },
    {
        "id": "euclid-e",
        "name": "Euclid VIS: 3e-5 per ellipticity component",
        "fields": {"metric": "e1", "tolerance": 3e-5},
        "source": "Euclid VIS's published NL allotment, 3e-5 per ellipticity component (Cropper et al. 2013, MNRAS "
        "431, 3103; the value as issue 18 quotes it)",
        "share": "the NL share itself (published)",
    },
    {
        "id": "euclid-size",
        "name": "Euclid VIS: 1e-4 on σ(R²)/R²",
        "fields": {"metric": "size", "tolerance": 5e-5},
        "source": "Euclid VIS's published NL allotment, 1e-4 on σ(R²)/R² (Cropper et al. 2013); ΔR²/R² = 2 ΔR/R, so ΔR/R ≤ 5e-5",
        "share": "the NL share itself (published)",
    },
]


def scene_presets() -> dict[str, Any]:
    """The scene form's fields for each library scene preset, and the name the library gives the scene."""
    from nlpsf.request import presets as roman_default

    out = {}
    for name in roman_default.PRESETS:
        model = roman_default.preset_base(name)
        out[name] = {
            "description": model.describe(),
            "fields": {
                "sed": model.sed or "",
                "jitter": model.jitter_arcsec or "",
                "charge_diffusion": model.charge_diffusion_px or "",
                "ipc": model.ipc_label or "",
            },
        }
    return out


@router.get("/presets", summary="Requirement presets with their sources, and the scene presets' fields")
def presets() -> SafeJSONResponse:
    return SafeJSONResponse(json_safe({"presets": PRESETS, "scenes": scene_presets()}))


# ---- batch over CSV ---------------------------------------------------------------------------------

_INTEGER_COLUMNS = {"sca", "stars", "ramp"}
# "scene": a preset's name per row (empty: the Roman default); "position": "X Y" in pixels on the SCA
# (or "X;Y"). The batch answers at table cost, by POST /api/v1/solve/batch's rule: the paper's tables
# and the Roman default's field grid; a row that needs a simulation is refused with where to send it.
_TEXT_COLUMNS = {"band", "metric", "mode", "fidelity", "ma_table", "ramp_fit", "throughput", "over_field", "scene", "position"}
_ANSWER_COLUMNS = [
    "band",
    "sca",
    "metric",
    "mode",
    "beta0",
    "exptime",
    "full_well",
    "stars",
    "precision",
    "tolerance",
    "magnitude",
    "solved_for",
    "uncertainty",
    "uncertainty_statistical",
    "uncertainty_fidelity",
    "uncertainty_optical_model",
    "uncertainty_model",
    "saturation_magnitude",
    "fidelity",
]


def _cell(name: str, text: str) -> Any:
    text = text.strip()
    if name in _TEXT_COLUMNS:
        return text
    if name == "precision" and text.endswith("%"):
        # Percent in, as on the page's precision field ("1 %" = 0.01).
        text = text[:-1].strip()
        try:
            return float(text) / 100.0
        except ValueError:
            return text
    try:
        return int(text) if name in _INTEGER_COLUMNS else float(text)
    except ValueError:
        return text  # the solve request names the field it cannot read


def _with_position(row: dict[str, Any]) -> dict[str, Any]:
    """A row's "position" cell ("X Y" or "X;Y") as its scene's position, on the row's preset."""
    if "position" not in row:
        return row
    row = dict(row)
    text = str(row.pop("position"))
    parts = text.replace(";", " ").split()
    try:
        position: Any = [float(p) for p in parts]
    except ValueError:
        position = text  # the solve request names scene.position and what it expects
    scene = row.get("scene")
    row["scene"] = {"position": position, **({"preset": scene} if isinstance(scene, str) and scene else {})}
    return row


def parse_batch_csv(text: str) -> list[dict[str, Any]]:
    lines = [line for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    if not lines:
        raise InputError("csv", "the CSV is empty: give a header row (e.g. band,tolerance,magnitude) and one row per request")
    reader = csv.DictReader(io.StringIO("\n".join(lines)))
    if not reader.fieldnames or any(not (name or "").strip() for name in reader.fieldnames):
        raise InputError("csv", "the header row has an empty column name")
    rows = []
    for row in reader:
        cells = {k.strip(): _cell(k.strip(), v or "") for k, v in row.items() if k is not None and (v or "").strip() != ""}
        rows.append(_with_position(cells))
    if not rows:
        raise InputError("csv", "the CSV has a header but no requests")
    return rows


def _answers_csv(results: list[dict[str, Any]]) -> str:
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    units = "precision is a fraction of beta0, tolerance dimensionless, magnitudes AB"
    out.write(f"# nlpsf batch answers; table fidelity; {units}\n")
    writer.writerow(["row", "ok", *_ANSWER_COLUMNS, "flags", "error"])
    for item in results:
        s = item.get("solution") or {}
        error = (item.get("error") or {}).get("detail", "")
        values = [s.get(k, "") for k in _ANSWER_COLUMNS]
        writer.writerow([item["index"] + 1, item["ok"], *values, "; ".join(s.get("flags", [])), error])
    return out.getvalue()


@router.post("/batch", summary="A CSV of solve requests (one per row, header = request fields) -> answers as JSON or CSV")
def batch(
    csv_text: Annotated[str, Body(media_type="text/csv", description="CSV: a header row of request fields, a request a row")],
    format: Annotated[str, Query(pattern="^(json|csv)$", description="json (default) or csv")] = "json",
) -> Response:
    rows = parse_batch_csv(csv_text)
    answered = json.loads(solve_api.solve_batch(models.BatchSolveRequest(requests=rows)).body)
    if format == "csv":
        return PlainTextResponse(
            _answers_csv(answered["results"]),
            media_type="text/csv",
            headers={"Content-Disposition": 'attachment; filename="nlpsf-batch-answers.csv"'},
        )
    return SafeJSONResponse({**answered, "requests": rows})


# ---- the user guide --------------------------------------------------------------------------------

_DOC_NAME = re.compile(r"^[a-z][a-z0-9_-]{0,40}$")


def docs_dir() -> Path:
    """docs/*.md as installed (package data nlpsf.docs), else the checkout's docs/ folder."""
    try:
        installed = Path(str(resources.files("nlpsf.docs")))
        if installed.is_dir() and any(installed.glob("*.md")):
            return installed
    except (ModuleNotFoundError, TypeError):
        pass
    return Path(__file__).resolve().parent.parent / "docs"


@router.get("/docs", summary="The user documentation pages (names of docs/*.md)")
def docs_index() -> SafeJSONResponse:
    directory = docs_dir()
    names = sorted(p.stem for p in directory.glob("*.md")) if directory.is_dir() else []
    return SafeJSONResponse({"pages": names})


@router.get("/docs/{name}", summary="One documentation page as Markdown", response_class=PlainTextResponse)
def doc(name: str) -> Response:
    if not _DOC_NAME.match(name):
        raise InputError("name", "a documentation page is named by lower-case letters, digits, - and _")
    path = docs_dir() / f"{name}.md"
    if not path.is_file():
        from .errors import problem

        return problem(404, f"no documentation page called {name!r}", "name")
    return PlainTextResponse(path.read_text(encoding="utf-8"), media_type="text/markdown; charset=utf-8")
