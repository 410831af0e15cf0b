"""What the page needs from the server beyond the resource endpoints: the calculator's plots, the
limits a refusal quotes, requirement presets with their sources, a CSV batch, and the user guide.

The page draws; every number it draws comes from here or from the resource endpoints. The plots'
endpoints take POST /solve's body, so what they draw is that request's scene, position and readout;
the curves are the library's (``nlpsf.solve.curves``: the solver's own slope source and
relation at each magnitude), so the relation T = |c(m)| p β₀ (× 1/√n for a scatter average) has one
owner, the library, and the answer's point lies on its curve.
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

from nlpsf.checks import InputError
from nlpsf.request.resolve import SolveRequest
from nlpsf.request.rows import request_rows
from nlpsf.slopes import tables
from nlpsf.solve import curves as requirement_curves
from nlpsf.solve import relation

from . import job_parts, models, solve_api
from .errors import SafeJSONResponse, json_safe

# The page's own endpoints: outside the versioned public schema (/openapi.json), which they would
# otherwise have to follow (typed models, units on every field); docs/page.md lists them.
router = APIRouter(prefix="/api/v1/page", tags=["page"], include_in_schema=False)

Positive = Annotated[float, Query(allow_inf_nan=False, gt=0)]
At = Annotated[
    list[float] | None,
    Query(max_length=8, description="magnitudes (AB mag) added to the grid exactly: the answer's, for its point and the legend"),
]
Overlay = Annotated[
    bool, Query(description="also the paper's idealised scene's curves (and its published points where they apply)")
]


def _request(body: models.SolveRequest) -> SolveRequest:
    """The library's typed request for a solve body: the one POST /solve builds (job_parts.solve_request)."""
    return job_parts.solve_request(job_parts.solve_body(body.model_dump(), body.model_fields_set))


def _no_curve(body: models.SolveRequest) -> str | None:
    if body.over_field is not None:
        return "an answer over the field is the worst of its points; each point has its own curve (solve at a position)"
    return None


@router.post("/limits", summary="The limits of a solve request: saturation for its readout, the brightest magnitude answered")
def limits_endpoint(body: models.SolveRequest) -> SafeJSONResponse:
    # The request's own scene, position and readout (the solver's rules, nlpsf.solve.curves).
    return SafeJSONResponse(json_safe(requirement_curves.limits(_request(body))))


@router.post("/requirement", summary="The calculator's two plots for a solve request: p(m) around its T, c(m), limits")
def requirement(body: models.SolveRequest, at: At = None, overlay: Overlay = False) -> SafeJSONResponse:
    """The body is POST /solve's: the curves are that request's (its scene, position and readout),
    each value the solver's own at its magnitude (nlpsf.solve.curves)."""
    request = _request(body)
    why = _no_curve(body)
    curves = requirement_curves.curves(request, at=at or (), refuse=why)
    paper = requirement_curves.paper_overlay(request, curves.tolerance, at=at or ()) if overlay else None
    published = requirement_curves.published(request, curves.tolerance)
    return SafeJSONResponse(
        json_safe(
            {
                "source": "the solver's own slopes and relation at each magnitude (nlpsf.solve.curves)",
                "curves": curves.to_dict(),
                "paper": None if paper is None else paper.to_dict(),
                "published": published,
            }
        )
    )


@router.post("/slopes", summary="Slope vs magnitude for every band, for a solve request's scene, position and readout")
def slopes(body: models.SolveRequest, at: At = None) -> SafeJSONResponse:
    """The body is POST /solve's (its band is replaced by each band in turn): each band's c(m) as the
    solver reads it for that request."""
    why = _no_curve(body)
    out = []
    # Slopes need no tolerance: every band's request asks for its tolerance at precision 1 (whatever
    # two of three the calculator's form holds), at the answer's magnitude where one is given.
    asked = {"precision": 1.0, "tolerance": None, "shear_m": None, "shear_c": None, "size_ratio": None}
    asked["magnitude"] = (at or [body.magnitude or 20.0])[0]
    for band in tables.load_tables().bands:
        banded = body.model_copy(update={"band": band, **asked})
        request = _request(banded)
        curve = requirement_curves.curves(request, at=at or (), step=SLOPES_STEP_MAG, refuse=why).to_dict()
        out.append(
            {
                "band": band,
                "magnitude": curve["magnitude"],
                "slope": curve["slope_abs"],
                "statistical": curve["slope_statistical"],
                "fidelity_relative_uncertainty": curve["method_relative"],
                "signed": curve["signed"],
                "saturation_magnitude": curve["limits"].get("saturation_magnitude"),
                "final_frame_saturation_magnitude": curve["limits"].get("final_frame_saturation_magnitude"),
                "where": curve["where"],
                "gaps": curve["gaps"],
                "needs_simulation": curve["needs_simulation"],
                "conditions": curve["conditions"],
            }
        )
    source = "the solver's own slopes for the request, per band; absolute values"
    return SafeJSONResponse(json_safe({"source": source, "curves": out}))


#: The slopes plot's magnitude spacing (eight bands at once; the calculator's plots use the library's 0.1 mag).
SLOPES_STEP_MAG = 0.25


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
            # Whether a background left blank is the preset's sky over the exposure (else no sky).
            "sky": roman_default.policy(name).sky,
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
        number = _number(text[:-1].strip(), float)
        return number / 100.0 if isinstance(number, float) else text
    return _number(text, int if name in _INTEGER_COLUMNS else float)


def _number(text: str, kind: type) -> Any:
    """The cell as a finite number, else its text: the solve request names the field it cannot read,
    and the answer's echo of the row shows what was sent ("nan", "inf"), not a JSON null."""
    try:
        number = kind(text)
    except ValueError:
        return text
    return number if math.isfinite(number) else text


def _with_position(row: dict[str, Any]) -> dict[str, Any]:
    """A row's "position" cell ("X Y" or "X;Y") as its scene's position, on the row's preset."""
    if "position" not in row:
        return row
    row = dict(row)
    text = str(row.pop("position"))
    parts = text.replace(";", " ").split()
    numbers = [_number(p, float) for p in parts]
    # Not numbers (or NaN, infinity): the text, so that the solve request names scene.position and
    # what it expects, and the echo shows what was sent.
    position: Any = numbers if all(isinstance(n, float) for n in numbers) else text
    scene = row.get("scene")
    row["scene"] = {"position": position, **({"preset": scene} if isinstance(scene, str) and scene else {})}
    return row


def parse_batch_csv(text: str) -> list[dict[str, Any]]:
    """The CSV's request rows (``request_rows``: its structure checked), each cell read as the page
    sends it (empty cells left out, numbers as numbers, a position as the row's scene's)."""
    return [_with_position({name: _cell(name, cell) for name, cell in row.items() if cell}) for row in request_rows(text)]


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


# ---- the full tables as the page downloads them: units, provenance, what each column is ---------------

#: What each column of the shipped tables is, with its unit (a slope column's companions: ``_err``, ``_interp``).
TABLE_COLUMNS: dict[str, str] = {
    "band": "Roman band (no unit)",
    "sca": "detector, SCA number (no unit)",
    "field_point": "field point of the SCA (0 centre, 1-4 corners; no unit), field-point tables only",
    "magnitude": "star magnitude, AB mag in the band, at the tables' exposure",
    "flux_electrons": "the star's electrons over the tables' exposure [e-]",
    "peak_electrons": "the star's brightest pixel before the NL [e- per native pixel: the fine pixel's charge x oversampling^2]",
    "saturated": "peak_electrons above the full well (true/false)",
    "failed_realizations": "centroid realizations whose moments failed (count)",
}
_SLOPE_WORDS = {
    "bias": "bias slope d(metric)/d beta at beta0 [e-: the dimensionless metric per unit beta in 1/e-]",
    "scatter": "scatter slope sigma(metric)/sigma_beta [e-: per unit sigma_beta in 1/e-]",
}
_METRIC_WORDS = {"size": "size dR/R", "e1": "ellipticity e1", "e2": "ellipticity e2"}
_COMPANIONS = {
    "_err": "1-sigma statistical error of {} over the centroid realizations [same unit]",
    "_interp": "estimated error of reading {} between the tabulated magnitudes [same unit]: each point left out and "
    "interpolated back from the others with the cubic spline of slope / flux in flux the tables are read with, the "
    "difference divided by 16 (a cubic spline's error falls as the spacing^4; nlpsf.tablebuild.interpolation_error_estimate)",
}


def _table_column_words(name: str) -> str:
    if name in TABLE_COLUMNS:
        return TABLE_COLUMNS[name]
    for suffix, words in _COMPANIONS.items():
        if name.endswith(suffix):
            return words.format(name[: -len(suffix)])
    mode, _, metric = name.partition("_")
    return f"{_METRIC_WORDS.get(metric, metric)} {_SLOPE_WORDS.get(mode, mode)}"


@router.get("/tables.csv", summary="The shipped slope tables as CSV, with units, provenance and what each column is")
def tables_csv() -> Response:
    shipped = tables.load_tables()
    rows = tables.table_rows()
    columns = list(rows[0])
    meta = shipped.meta
    settings = meta.get("settings", {})
    out = io.StringIO()
    out.write("# nlpsf slope tables: the paper's idealised scene (detector centre, one wavelength, quadratic NL, final frame)\n")
    out.write(
        f"# provenance: file {meta.get('source')}, fingerprint {meta.get('fingerprint')}, code {meta.get('code_version')}; "
        f"optical data: {meta.get('data_version')}; method: {meta.get('method')}\n"
    )
    conditions = ", ".join(f"{k} {v}" for k, v in settings.items())
    out.write(f"# conditions: {conditions} (exptime_s in s, beta0 in 1/e-, full_well_e in e-)\n")
    out.write("# columns:\n")
    for name in columns:
        out.write(f"#   {name}: {_table_column_words(name)}\n")
    writer = csv.DictWriter(out, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows({k: "" if isinstance(v, float) and not math.isfinite(v) else v for k, v in row.items()} for row in rows)
    headers = {"Content-Disposition": 'attachment; filename="nlpsf-tables-all.csv"'}
    return PlainTextResponse(out.getvalue(), media_type="text/csv", headers=headers)


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
