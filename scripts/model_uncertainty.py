"""What the paper's scene leaves out, measured once and shipped: the model part of a table answer.

    python scripts/model_uncertainty.py            # print the summary
    python scripts/model_uncertainty.py --write    # also write nlpsf/data/scene_model_uncertainty.json

A table answer is exact for the paper's idealised scene (SCA centre, one wavelength, quadratic NL,
no other detector or pointing effect). For every band, at SCA 1, 9 and 18, at m = saturation + 0.5 and
m = 21, in both modes, ``nlpsf.solve.impact.model_point`` measures (linear response, the same centroids
with and without) what each effect of the Roman scene changes in the slopes when it is switched on
at its nominal value (``nlpsf.sim.scene.NOMINAL``: the worst corner of the SCA against its centre, a
flat-f_nu SED, jitter 0.014", charge diffusion 0.1 px, GalSim's IPC kernel after the NL, b3/b4 NL
residuals, a 100 e- background; brighter-fatter has no default and is not measured), and the
pupil-mask scale rule (galsim, used, against header).

Shipped per band, mode and metric: each effect's worst |impact| over those points, their quadrature
sum (``effects_sum``) and plain sum (``effects_bound``), and the pupil rule's worst |impact|; the same
per measured SCA (``per_sca``), which the solver uses for that SCA (other SCAs get the worst over all
measured ones). ``size`` and ``e`` are relative to their own slope, ``e1`` and ``e2`` the component's
change relative to |c_e| (the solver scales them by |c_e| / |c_ei| at the answer's magnitude). Every
point's signed values are kept under ``points`` so that a test can re-measure one. ~1-3 s per point
on one core (mostly the optics of the SED and the corners): 96 points, 3-5 minutes.

Why the plain sum. The effects are not independent errors that might partly cancel: a Roman star
goes through all of them at once, and at a given point their signs are fixed and often the same
(W146 SCA 18, e2 bias: position, SED, jitter, diffusion and IPC all negative). A full Roman scene
at a corner of W146 SCA 18 moved the e2 slope by 1.4 times the quadrature sum
(``tests/library/test_model_part.py``); the plain sum of the worst impacts bounds it to first order.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import sys
import time
from pathlib import Path

from nlpsf import __version__, defaults, roman
from nlpsf.sim import scene as scenes
from nlpsf.slopes import tables
from nlpsf.solve import impact

OUTPUT = Path(__file__).resolve().parent.parent / "nlpsf" / "data" / "scene_model_uncertainty.json"
#: SCA 18 (the paper's), SCA 1 (small e slopes at its centre) and SCA 9 (between).
SCAS = (1, 9, 18)
FAINT_MAGNITUDE = 21.0
SATURATION_OFFSET = 0.5
REALIZATIONS = 50
SEED = 1


def magnitudes(band: str, sca: int) -> list[float]:
    """Near the brightest usable star (saturation + 0.5, table conditions) and a faint one."""
    saturation = tables.load_tables().get(band, sca).saturation(defaults.EXPTIME_S, defaults.FULL_WELL_E)
    return [round(saturation + SATURATION_OFFSET, 3), FAINT_MAGNITUDE]


def worst(points: list[dict], metric: str) -> dict:
    """Each effect's worst |impact| on ``metric`` over ``points``, where, their quadrature sum, and
    the pupil rule's worst |impact|."""
    entry: dict = {"effects": {}, "worst_at": {}, "pupil_scale": 0.0, "not_measured": []}
    for point in points:
        at = {"sca": point["sca"], "magnitude": point["magnitude"]}
        for name, values in point["effects"].items():
            if values is None or values[metric] is None:
                if name not in entry["not_measured"]:
                    entry["not_measured"].append(name)
                continue
            if abs(values[metric]) >= entry["effects"].get(name, -1.0):
                entry["effects"][name], entry["worst_at"][name] = abs(values[metric]), at
        pupil = point["pupil_scale"][metric]
        if pupil is not None and abs(pupil) >= entry["pupil_scale"]:
            entry["pupil_scale"], entry["worst_at"]["pupil_scale"] = abs(pupil), at
    entry["effects_sum"] = math.sqrt(math.fsum(v**2 for v in entry["effects"].values()))  # any order, same sum
    # Every Roman star has all of them at once, with signs fixed by the optics (often alike): the
    # bound the solver uses is their plain sum (see the module docstring).
    entry["effects_bound"] = math.fsum(entry["effects"].values())
    return entry


def summarise(points: list[dict]) -> dict:
    """Per band, mode and metric: the worst over every point, and per measured SCA its own worst
    (``per_sca``), which the solver prefers for that SCA."""
    out: dict = {}
    for band in dict.fromkeys(p["band"] for p in points):
        for mode in dict.fromkeys(p["mode"] for p in points):
            chosen = [p for p in points if p["band"] == band and p["mode"] == mode]
            per_metric = out.setdefault(band, {}).setdefault(mode, {})
            for metric in impact.MODEL_METRICS:
                entry = worst(chosen, metric)
                entry["per_sca"] = {
                    str(sca): worst([p for p in chosen if p["sca"] == sca], metric)
                    for sca in dict.fromkeys(p["sca"] for p in chosen)
                }
                per_metric[metric] = entry
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help=f"write {OUTPUT.relative_to(OUTPUT.parents[2])}")
    parser.add_argument("--bands", default=",".join(defaults.BANDS))
    args = parser.parse_args(argv)
    start = time.perf_counter()
    points = []
    for band in args.bands.split(","):
        for sca in SCAS:
            for magnitude in magnitudes(band, sca):
                for mode in defaults.MODES:
                    points.append(impact.model_point(band, sca, magnitude, mode, realizations=REALIZATIONS, seed=SEED))
                    print(
                        f"{band} SCA {sca:2d} m={magnitude:6.3f} {mode:7s} {time.perf_counter() - start:6.1f} s", file=sys.stderr
                    )
    summary = summarise(points)
    elapsed = time.perf_counter() - start
    for band, per_mode in summary.items():
        for mode, per_metric in per_mode.items():
            for sca in SCAS:
                parts = {m: e["per_sca"][str(sca)] for m, e in per_metric.items()}
                cells = "  ".join(
                    f"{m} {100 * e['effects_sum']:5.1f} % (pupil {100 * e['pupil_scale']:4.1f} %)" for m, e in parts.items()
                )
                print(f"{band} {mode:7s} SCA {sca:2d}  {cells}")
    print(f"{len(points)} points in {elapsed:.0f} s")
    if args.write:
        payload = {
            "description": (
                "What the paper's scene (tables) leaves out: per band, mode and metric, each scene effect's worst "
                "|relative change of the NL slope| when switched on at its nominal Roman value, over SCA "
                f"{', '.join(map(str, SCAS))} at m = saturation + {SATURATION_OFFSET} and m = {FAINT_MAGNITUDE:g} "
                "(linear response, the same centroids with and without), their quadrature sum (effects_sum) and plain "
                "sum (effects_bound, what the solver adds: a Roman star has them all at once), and the pupil-mask "
                "scale rule (header vs galsim); per_sca: the same for each measured SCA. size and e: relative to "
                "their own slope; e1 and e2: the component's change relative to |c_e| = hypot(c_e1, c_e2). "
                "position: the worst corner field point of the SCA against its centre."
            ),
            "conditions": {
                "code_version": __version__,
                "data_version": roman.DATA_VERSION,
                "measured_utc": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
                "elapsed_s": round(elapsed, 1),
                "script": "scripts/model_uncertainty.py",
                "method": "linear response at beta0 (nlpsf.solve.impact.model_point)",
                "realizations": REALIZATIONS,
                "seed": SEED,
                "beta0": defaults.BETA0,
                "exptime_s": defaults.EXPTIME_S,
                "full_well_e": defaults.FULL_WELL_E,
                "scas": list(SCAS),
                "magnitudes": f"saturation + {SATURATION_OFFSET} (table conditions) and {FAINT_MAGNITUDE}",
                "measured_at": {name: entry["note"] for name, entry in scenes.NOMINAL.items()},
                "pupil_scale": "header rule against galsim (the one used)",
            },
            "per_band": summary,
            "points": points,
        }
        OUTPUT.write_text(json.dumps(payload, indent=1, sort_keys=True) + "\n")
        print(f"wrote {OUTPUT}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
