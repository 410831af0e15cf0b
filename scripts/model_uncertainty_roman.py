"""What the Roman default cannot know, part by part from the sources' stated uncertainties: its model uncertainty.

    python scripts/model_uncertainty_roman.py                 # print the tables
    python scripts/model_uncertainty_roman.py --write         # also write nlpsf/data/roman_model_uncertainty.json
    python scripts/model_uncertainty_roman.py --bands H158 --scas 18   # a subset (printed, not written)
    python scripts/model_uncertainty_roman.py --report        # docs/validation.md's tables from the shipped file

First, per band, the joint fit of nlpsf's optics to the official PSF statistics of SCA 1 and 18
(``roman_uncertainty_measure.fit_optics``). Then for every band at each SCA in ``--scas`` (the SCA centre),
m = 18.5, 20 and 22, both modes, the parts of ``nlpsf.solve.roman_uncertainty`` are measured inside
the full default scene (``tablebuild.TableSettings.roman``, HLWAS likelihood ramp, slopes at the
"corrected" state) with the linear response and the same 50 centroid draws for every variant
(``roman_uncertainty_measure.measure_point``): the optics' two sensitivities (combined with the band's fit
here), jitter and diffusion at one standard deviation, the diffusion profile, brighter-fatter, the
NL's shape, and the SED range's two ends. About 12 slope runs per (band, SCA).

Shipped per band, mode and metric: per SCA each part's signed value per magnitude (``by_magnitude``:
[m, value, statistical error]), its worst |value|, the SED range ([m, 3500 K end, 10000 K end]),
the optics' sensitivities ([m, per arcsec^2, per ln s], for other pupil rules), the combination per
magnitude; ``worst``: the worst over the SCAs; per band the optics fit.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from nlpsf import __version__, roman
from nlpsf.request import presets as roman_default
from nlpsf.solve import roman_uncertainty as ru
from nlpsf.solve import roman_uncertainty_measure as measure

OUTPUT = Path(__file__).resolve().parent.parent / "nlpsf" / "data" / ru.FILE
SCAS = tuple(range(1, 19))
MAGNITUDES = (18.5, 20.0, 22.0)
REALIZATIONS = 50
SEED = 1


def code_version() -> str:
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True, cwd=OUTPUT.parent
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        commit = "unknown"
    return f"{__version__} ({commit})"


def summarise_sca(point: dict, fit: dict, mode: str, metric: str) -> dict:
    changes = point["changes"]
    parts: dict = {}
    sensitivity = []
    optics_rows = []
    for (m, sv, ev), (_, ss, es) in zip(changes["optics_v"][mode][metric], changes["optics_s"][mode][metric], strict=True):
        if sv is None or ss is None:
            optics_rows.append([m, None, None])
            sensitivity.append([m, None, None])
            continue
        value, offset = ru.optics_value(fit, np.array([sv, ss]))
        # The statistical error of the sensitivities carried through the same rule (small).
        error = math.hypot(ev * abs(fit["theta"][0]), es * abs(fit["theta"][1]))
        optics_rows.append([m, math.copysign(float(value), float(offset)), error])
        sensitivity.append([m, sv, ss])
    for name in ru.PART_NAMES:
        rows = optics_rows if name == "optics" else changes[name][mode][metric]
        values = [r[1] for r in rows if r[1] is not None]
        parts[name] = {"by_magnitude": rows, "value": max(values, key=abs) if values else None}
        if name in point["errors"]:
            parts[name]["why"] = point["errors"][name]
    cool, hot = changes["sed_cool"][mode][metric], changes["sed_hot"][mode][metric]
    ranges = {"sed": {"ends": list(ru.SED_RANGE), "by_magnitude": [[a[0], a[1], b[1]] for a, b in zip(cool, hot, strict=True)]}}
    combined = []
    for index, magnitude in enumerate(point["magnitudes"]):
        values = {n: p["by_magnitude"][index][1] for n, p in parts.items()}
        combined.append([magnitude, ru.combine(values)])
    return {"parts": parts, "ranges": ranges, "optics_sensitivity": sensitivity, "combined_by_magnitude": combined}


def worst_over(entries: list[dict]) -> dict:
    """Per part and magnitude the largest |value| over SCAs (signed values kept); the ranges' ends
    the most extreme; the optics' sensitivities of the SCA with the largest optics part."""
    out: dict = {"parts": {}, "ranges": {}, "combined_by_magnitude": []}
    for name in ru.PART_NAMES:
        rows: dict[float, list] = {}
        for entry in entries:
            for row in entry["parts"][name]["by_magnitude"]:
                if row[1] is not None and (row[0] not in rows or abs(row[1]) > abs(rows[row[0]][1])):
                    rows[row[0]] = row
        ordered = [rows[m] for m in sorted(rows)]
        values = [r[1] for r in ordered]
        out["parts"][name] = {"by_magnitude": ordered, "value": max(values, key=abs) if values else None}
    for name in ru.RANGES:
        by: dict[float, list] = {}
        for entry in entries:
            for m, lo, hi in entry["ranges"][name]["by_magnitude"]:
                if lo is None or hi is None:
                    continue
                old = by.setdefault(m, [m, lo, hi])
                old[1], old[2] = min(old[1], lo, hi), max(old[2], lo, hi)
        out["ranges"][name] = {"ends": entries[0]["ranges"][name]["ends"], "by_magnitude": [by[m] for m in sorted(by)]}
    largest = max(entries, key=lambda e: abs(e["parts"]["optics"]["value"] or 0.0))
    out["optics_sensitivity"] = largest["optics_sensitivity"]
    for magnitude in sorted({r[0] for e in entries for r in e["combined_by_magnitude"]}):
        out["combined_by_magnitude"].append(
            [magnitude, max(r[1] for e in entries for r in e["combined_by_magnitude"] if r[0] == magnitude)]
        )
    return out


def summarise(points: list[dict], fits: dict) -> dict:
    out: dict = {}
    for band in dict.fromkeys(p["band"] for p in points):
        for mode in ru.MODES:
            for metric in ru.METRICS:
                per_sca = {str(p["sca"]): summarise_sca(p, fits[band], mode, metric) for p in points if p["band"] == band}
                out.setdefault(band, {}).setdefault(mode, {})[metric] = {
                    "per_sca": per_sca,
                    "worst": worst_over(list(per_sca.values())),
                }
    return out


#: An e1 / e2 slope is "near zero" below this fraction of |c_e| (the issue's targets exclude it).
NEAR_ZERO = 0.3
TARGETS = {"size": 0.10, "e1": 0.30, "e2": 0.30, "e": 0.30}


def report(data: dict) -> str:
    """Markdown for docs/validation.md from a shipped file: per band and mode, each part's worst
    |value| over the SCAs and magnitudes, the SED range, and the combined uncertainty against the
    targets, e1 and e2 restated against their own slope (|c_e| / |c_ei| from the default's slopes)."""
    lines = ["**The optics fit** (per band, SCA 1 and 18 jointly):", ""]
    lines += ["| band | v (mas²) | ln s | σ_v (mas²) | σ_ln s | scatter | worst residual |", "|---|---|---|---|---|---|---|"]
    for band, fit in data["optics_fit"].items():
        worst = max(fit["data"], key=lambda r: abs(r["residual_log"]))
        lines.append(
            f"| {band} | {1e6 * fit['theta'][0]:+.0f} | {fit['theta'][1]:+.4f} | {1e6 * fit['sigma'][0]:.0f} | "
            f"{fit['sigma'][1]:.4f} | {100 * fit['intrinsic_scatter_log']:.2f} % | {100 * worst['residual_log']:+.1f} % "
            f"({worst['statistic']}, {worst['centring']}, SCA {worst['sca']}) |"
        )
    lines.append("")
    for mode in ru.MODES:
        lines += [
            f"**{mode}**: each part's worst |value| over the measured SCAs and m = 18.5, 20, 22 (size, e: of their own "
            "slope; e1, e2: of |c_e|), the SED range's extreme ends, and the combined uncertainty's range over the points "
            "(e1, e2 against their own slope, points where |c_ei| < 0.3 |c_e| left out as near zero):",
            "",
            "| band | metric | " + " | ".join(ru.PART_NAMES) + " | SED range | combined (range) | target met at | largest part |",
            "|---|---|" + "---|" * (len(ru.PART_NAMES) + 4),
        ]
        for band, per_mode in data["per_band"].items():
            for metric in ru.METRICS:
                entry = per_mode[mode][metric]
                cells = []
                for name in ru.PART_NAMES:
                    v = entry["worst"]["parts"][name]["value"]
                    cells.append("—" if v is None else f"{100 * abs(v):.1f} %")
                sed = entry["worst"]["ranges"]["sed"]["by_magnitude"]
                sed_cell = f"{100 * min(r[1] for r in sed):+.1f} … {100 * max(r[2] for r in sed):+.1f} %" if sed else "—"
                combined, met, total, dominant = [], 0, 0, {}
                for sca, own in entry["per_sca"].items():
                    base = data["base_slopes"][f"{band} {sca}"]
                    for index, (m, value) in enumerate(own["combined_by_magnitude"]):
                        slopes = (base.get(f"{m:g}") or {}).get(mode)
                        if slopes is None:
                            continue
                        scale = 1.0
                        if metric in ("e1", "e2"):
                            if abs(slopes[metric]) < NEAR_ZERO * abs(slopes["e"]):
                                continue
                            scale = abs(slopes["e"]) / abs(slopes[metric])
                        combined.append(value * scale)
                        total += 1
                        met += value * scale <= TARGETS[metric]
                        parts = {n: abs(p["by_magnitude"][index][1] or 0.0) for n, p in own["parts"].items()}
                        top = max(parts, key=parts.get)
                        dominant[top] = dominant.get(top, 0) + 1
                span = f"{100 * min(combined):.1f}–{100 * max(combined):.1f} %" if combined else "—"
                top = max(dominant, key=dominant.get) if dominant else "—"
                lines.append(f"| {band} | {metric} | {' | '.join(cells)} | {sed_cell} | {span} | {met} of {total} | {top} |")
        lines.append("")
    return "\n".join(lines)


def combined_points(data: dict, band: str, mode: str, metric: str, scas=None) -> list[float]:
    """The combined relative uncertainty at every measured (SCA, magnitude) of a file, e1 / e2
    against their own slope (near-zero points left out), over ``scas`` (None: all)."""
    out = []
    for sca, own in data["per_band"][band][mode][metric]["per_sca"].items():
        if scas is not None and int(sca) not in scas:
            continue
        base = data["base_slopes"][f"{band} {sca}"]
        for m, value in own["combined_by_magnitude"]:
            slopes = (base.get(f"{m:g}") or base.get(str(m)) or {}).get(mode)
            if slopes is None:
                continue
            scale = 1.0
            if metric in ("e1", "e2"):
                if abs(slopes[metric]) < NEAR_ZERO * abs(slopes["e"]):
                    continue
                scale = abs(slopes["e"]) / abs(slopes[metric])
            out.append(value * scale)
    return out


def compare(old: dict, new: dict, scas=(1, 9, 18)) -> str:
    """Markdown: the combined uncertainty's range and the points meeting the target, an earlier
    file against this one, at the SCAs both measured."""
    lines = [
        "| band | mode | metric | before: range (met) | now: range (met) |",
        "|---|---|---|---|---|",
    ]
    for band in new["per_band"]:
        for mode in ru.MODES:
            for metric in ru.METRICS:
                cells = []
                for data in (old, new):
                    values = combined_points(data, band, mode, metric, scas)
                    met = sum(v <= TARGETS[metric] for v in values)
                    cells.append(f"{100 * min(values):.1f}–{100 * max(values):.1f} % ({met} of {len(values)})" if values else "—")
                lines.append(f"| {band} | {mode} | {metric} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help=f"write {OUTPUT.relative_to(OUTPUT.parents[2])}")
    parser.add_argument("--bands", default=",".join(roman.BANDS))
    parser.add_argument("--scas", default=",".join(map(str, SCAS)))
    parser.add_argument("--report", action="store_true", help="print the docs' tables from the shipped file, measure nothing")
    parser.add_argument("--save-points", default=None, help="also write every point's raw measurement here (JSON)")
    parser.add_argument("--compare", default=None, help="with --report: an earlier file, compared at SCA 1, 9 and 18")
    args = parser.parse_args(argv)
    if args.report:
        data = json.loads(OUTPUT.read_text())
        print(report(data) if args.compare is None else compare(json.loads(Path(args.compare).read_text()), data))
        return 0
    bands = args.bands.split(",")
    scas = [int(s) for s in args.scas.split(",")]
    start = time.perf_counter()
    fits, points = _measure_points(bands, scas, start)
    summary = summarise(points, fits)
    elapsed = time.perf_counter() - start
    if args.save_points:
        Path(args.save_points).write_text(json.dumps({"points": points, "fits": fits}, default=_finite))
    payload = _payload(points, fits, summary, _conditions(scas, elapsed))
    print(report(json.loads(json.dumps(_rounded(payload), default=_finite))))
    print(f"\n{len(points)} points in {elapsed:.0f} s")
    if args.write:
        payload = {**_rounded(payload), "per_band": _rounded(payload["per_band"], PART_DIGITS)}
        OUTPUT.write_text(json.dumps(payload, sort_keys=True, separators=(",", ":"), default=_finite) + "\n")
        print(f"wrote {OUTPUT}")
    return 0


def _measure_points(bands: list[str], scas: list[int], start: float) -> tuple[dict, list[dict]]:
    """The joint optics fit per band, then every (band, SCA) point's measurement, with progress."""
    fits = {band: measure.fit_optics(band) for band in bands}
    print(f"optics fits in {time.perf_counter() - start:.0f} s", file=sys.stderr)
    points = []
    for band in bands:
        for sca in scas:
            point = measure.measure_point(band, sca, MAGNITUDES, REALIZATIONS, SEED)
            points.append(point)
            elapsed = time.perf_counter() - start
            print(f"{band} SCA {sca:2d} {elapsed:6.1f} s {point['errors'] or ''}", file=sys.stderr, flush=True)
    return fits, points


def _conditions(scas: list[int], elapsed: float) -> dict:
    """What the file's numbers were measured under: versions, the default's values, each part's probe."""
    return {
        "code_version": code_version(),
        "data_version": roman.DATA_VERSION,
        "measured_utc": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "elapsed_s": round(elapsed, 1),
        "script": "scripts/model_uncertainty_roman.py",
        "scene": "the Roman default (nlpsf.request.presets, TableSettings.roman().config), SCA centre",
        "default_values": roman_default.conditions(),
        "method": "linear response, slopes at the corrected state, the same centroid draws for every variant",
        "residual_nl": roman_default.RESIDUAL_NL,
        "realizations": REALIZATIONS,
        "seed": SEED,
        "scas": scas,
        "magnitudes": list(MAGNITUDES),
        "jitter": {
            "nominal_arcsec": ru.JITTER_ARCSEC,
            "sigma_arcsec": ru.JITTER_SIGMA_ARCSEC,
            "requirement_arcsec": ru.JITTER_REQUIREMENT_ARCSEC,
            "exceeded_fraction": ru.JITTER_EXCEEDED_FRACTION,
            "probe_arcsec": ru.JITTER_PROBE_ARCSEC,
        },
        "charge_diffusion": {"nominal_px": ru.DIFFUSION_PX, **ru.diffusion_uncertainty()},
        "sed_range": list(ru.SED_RANGE),
        "bfe": {
            "published_per_e": ru.BFE_COEFFICIENT_PUBLISHED,
            "ipc_smoothing": ru.BFE_IPC_SMOOTHING,
            "used_per_e": ru.BFE_COEFFICIENT,
            "source": "Freudenburg et al. 2020, PASP 132, 074504 (arXiv:2003.05978), SCA 20829, not IPC-deconvolved",
        },
        "nl_shape_coefficients": list(ru.NL_SHAPE_COEFFICIENTS),
        "optics": {
            "blur_probe_arcsec2": ru.OPTICS_BLUR_PROBE_ARCSEC2,
            "pupil_probe": ru.OPTICS_PUPIL_PROBE,
            "scas": list(ru.OPTICS_SCAS),
            "sed": ru.OFFICIAL_SED,
            "rounding": ru.OFFICIAL_ROUNDING,
        },
    }


def _payload(points: list[dict], fits: dict, summary: dict, conditions: dict) -> dict:
    """The shipped file's content (before rounding)."""
    return {
        "description": (
            "The Roman default's model uncertainty by part (nlpsf.solve.roman_uncertainty): each part's signed relative "
            "value (a standard uncertainty, or a left-out shift) of the NL slope inside the full default scene, per band, "
            "mode, metric, SCA and magnitude (by_magnitude rows: [m, value, statistical error]); value: its worst over the "
            "magnitudes; ranges: what varies from star to star ([m, end 1, end 2]); optics_sensitivity: [m, d/dv per "
            "arcsec^2, d/d ln s]; combined_by_magnitude: the combination rule; worst: the worst over the measured SCAs; "
            "optics_fit: the joint fit per band. size and e: relative to their own slope; e1 and e2: the component's "
            "change relative to |c_e| = hypot(c_e1, c_e2)."
        ),
        "combination": ru.COMBINATION,
        "parts": [{"name": p.name, "kind": p.kind, "measured_as": p.measured_as, "source": p.source} for p in ru.PARTS],
        "ranges": list(ru.RANGES),
        "conditions": conditions,
        "optics_fit": fits,
        "pupil_log_scale": {f"{p['band']} {p['sca']}": p["pupil_log_scale"] for p in points},
        "per_band": summary,
        # The default's own slopes at each point (the parts above are relative to them).
        "base_slopes": {f"{p['band']} {p['sca']}": p["base"] for p in points},
    }


#: Significant digits of the parts, ranges and sensitivities in the file: a part is a fraction of a
#: slope known to ~1e-3 of itself (its statistical error, its sensitivity's linearity), so 4 digits
#: hold everything measured (and keep the wheel within its budget); the rest keeps 6.
PART_DIGITS = 4


def _rounded(value, digits: int = 6):
    """Floats to ``digits`` significant digits: a smaller file, the same numbers to the precision
    they are measured to."""
    if isinstance(value, float):
        return float(f"{value:.{digits}g}") if math.isfinite(value) else value
    if isinstance(value, dict):
        return {k: _rounded(v, digits) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_rounded(v, digits) for v in value]
    return value


def _finite(value):
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, np.floating):
        return float(value)
    raise TypeError(type(value))


if __name__ == "__main__":
    raise SystemExit(main())
