"""Cost of each scene effect relative to the plain (paper's) simulation, measured in one run.

Work per configuration: a fresh request -- optics computed (the cache cleared), stamps rendered,
reference moments, and the slopes at one magnitude (``experiment.slopes``: bias and scatter) --
on H158 SCA 18, m = 18.3, beta0 = 5e-7, R centroid realizations, for both methods (Monte Carlo,
the paper's finite differences, and the linear response). Each effect is switched on alone at its
``nlpsf.sim.scene.NOMINAL`` value (brighter-fatter at a = 1e-7), then the Roman preset and everything
at once. Each configuration is timed ``--repeat`` times and the fastest kept (on a shared machine
the minimum is the least disturbed); ratios are to the plain scene timed in the same run.

Usage: python benchmarks/bench_scene.py [--realizations 100] [--repeat 5] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace

from nlpsf.sim import experiment, optics
from nlpsf.sim import scene as scenes


def configurations() -> dict[str, scenes.SceneModel]:
    plain = scenes.SceneModel()
    out = {"plain": plain}
    for name in scenes.EFFECTS:
        model = plain.with_nominal(name) if name != "brighter_fatter" else replace(plain, bfe_coefficient=1e-7)
        out[name] = model
    out["sed (6 wavelengths)"] = replace(out["sed"], n_wavelengths=6)
    out["ipc before"] = replace(out["ipc"], ipc_order="before")
    out["roman preset"] = scenes.preset("galsim-roman")
    out["everything"] = replace(
        scenes.preset("galsim-roman"),
        position=(4.0, 4.0),
        nl_coefficients=(1e-13, 1e-18),
        bfe_coefficient=1e-7,
        background_e=100.0,
    )
    return out


def time_one(model: scenes.SceneModel, method: str, realizations: int) -> float:
    optics.effective_psf.cache_clear()  # a fresh request pays for its optics
    config = experiment.SimulationConfig(realizations=realizations, method=method, scene=model)
    start = time.perf_counter()
    experiment.slopes(config, [18.3])
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--realizations", type=int, default=100)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    rows = []
    models = configurations()
    for method in ("monte_carlo", "linear"):
        times = {name: min(time_one(m, method, args.realizations) for _ in range(args.repeat)) for name, m in models.items()}
        for name, seconds in times.items():
            rows.append(
                {
                    "method": method,
                    "configuration": name,
                    "wavelengths": experiment.SimulationConfig(scene=models[name]).optics.n_wavelengths,
                    "seconds": seconds,
                    "relative_to_plain": seconds / times["plain"],
                }
            )
    result = {"machine": f"{os.cpu_count()} cores", "realizations": args.realizations, "repeat": args.repeat, "rows": rows}
    if args.json:
        print(json.dumps(result, indent=1))
        return
    print(f"H158 SCA 18, m = 18.3, {args.realizations} realizations, fastest of {args.repeat}, {result['machine']}")
    print(f"{'configuration':<22} {'wl':>3} {'monte_carlo s':>14} {'x plain':>8} {'linear s':>9} {'x plain':>8}")
    by = {(r["method"], r["configuration"]): r for r in rows}
    for name in models:
        mc, lin = by[("monte_carlo", name)], by[("linear", name)]
        print(
            f"{name:<22} {mc['wavelengths']:>3} {mc['seconds']:>14.2f} {mc['relative_to_plain']:>8.2f} "
            f"{lin['seconds']:>9.2f} {lin['relative_to_plain']:>8.2f}"
        )


if __name__ == "__main__":
    main()
