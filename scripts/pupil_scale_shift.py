"""How far the pupil-scale rule moves the NL slopes (linear fidelity, paper scene otherwise).

    python scripts/pupil_scale_shift.py [--realizations 100] [--json]

For each (band, SCA, magnitude) below the slopes of dR/R, e1 and e2 are computed under the rules
``galsim`` (the default), ``header`` and ``official``, with the same centroid draws (same seed), and
the relative change of each slope against ``galsim`` is printed. This is what the pupil-scale term
of the model uncertainty (``solver``: header vs galsim) measures.
"""

from __future__ import annotations

import argparse
import json

from nlpsf import roman
from nlpsf.sim import experiment

POINTS = (("H158", 18, 18.3), ("F184", 1, 18.3), ("Y106", 7, 18.3), ("H158", 18, 21.0))
METRICS = ("dR_over_R", "de1", "de2")


def measure(realizations: int) -> list[dict]:
    rows = []
    for band, sca, magnitude in POINTS:
        values = {}
        for rule in roman.PUPIL_SCALE_RULES:
            config = experiment.SimulationConfig(band=band, sca=sca, realizations=realizations, method="linear", pupil_scale=rule)
            result = experiment.slopes(config, [magnitude])[0]
            values[rule] = {m: result.slope("bias", (m,)) for m in METRICS}
        row = {"band": band, "sca": sca, "magnitude": magnitude, "slopes": values, "relative_to_galsim": {}}
        for rule in ("header", "official"):
            row["relative_to_galsim"][rule] = {m: values[rule][m][0] / values["galsim"][m][0] - 1 for m in METRICS}
        rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--realizations", type=int, default=100)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    rows = measure(args.realizations)
    if args.json:
        print(json.dumps(rows, indent=2))
        return
    print("| band | SCA | m | metric | galsim slope | header vs galsim | official vs galsim | official vs header |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        s = row["slopes"]
        for m in METRICS:
            g, h, o = (s[r][m][0] for r in ("galsim", "header", "official"))
            err = s["galsim"][m][1]
            print(
                f"| {row['band']} | {row['sca']} | {row['magnitude']:g} | {m} | {g:.4g} ± {err:.2g} | "
                f"{100 * (h / g - 1):+.2f} % | {100 * (o / g - 1):+.2f} % | {100 * (o / h - 1):+.2f} % |"
            )


if __name__ == "__main__":
    main()
