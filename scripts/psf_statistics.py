"""nlpsf's PSF against the official Roman PSF statistics, and what the difference means for the slopes.

    python scripts/psf_statistics.py            # print the README table
    python scripts/psf_statistics.py --write    # also write nlpsf/data/optical_model_uncertainty.json
    python scripts/psf_statistics.py --sed blackbody:5270   # the 5270 K stand-in for the K0V

The shipped optical_model_uncertainty.json (the paper scene's optical-model part) was written with
``--sed blackbody:5270`` (its ``conditions.sed`` says so); the default is the official statistics'
own star, the vendored Pickles K0V.

1. For SCA 1 and 18 in every band, nlpsf's FWHM, N_eff and peak fraction under the official
   conditions (``nlpsf.sim.psfstats``: the K0V star over the band (``--sed``), 8 mas FWHM jitter, pixel-corner and
   pixel-centre centring, 64-pixel = 7.04" image) beside the official summary table.
2. The slopes' sensitivity to the PSF's width, measured: the linear-response bias slopes at m = 20
   (table settings: achromatic, 100 realizations) for nlpsf's PSF and for it blurred by a Gaussian
   of ``--blur`` times the official FWHM (a ~5-10 % change of N_eff, the size of the gaps),
   against the change in N_eff (geometric mean over the two centrings) that the blur causes.
   d slope / d ln N_eff times ln(N_eff official / N_eff nlpsf) is the slope change that making
   nlpsf's PSF as wide as the official one would cause: the optical-model uncertainty of each
   slope, relative to the size slope for size, and for e1 and e2 together relative to the modulus
   of the ellipticity slope |c_e| = hypot(c_e1, c_e2) (the components pass through zero across
   the focal plane, so a relative error of each would mean nothing). The official statistics say
   nothing about the PSF's ellipticity, so for e1 and e2 this bounds only the part of the model
   difference that shows in the width; the aberration patterns themselves (Cycle 9 vs post-CDR)
   are not compared.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

from nlpsf import __version__, roman
from nlpsf.sim import experiment, moments, optics, psfstats, render

OUTPUT = Path(__file__).resolve().parent.parent / "nlpsf" / "data" / "optical_model_uncertainty.json"
METRICS = {"size": "dR_over_R", "e1": "de1", "e2": "de2"}
SED_TEXT = {
    "K0V": "K0V: Pickles 1998 (nlpsf.roman.seds k0v)",
    psfstats.K0V_STANDIN: f"blackbody {psfstats.K0V_TEMPERATURE_K:g} K (K0V)",  # the shipped file's wording
    "flat": "flat f_nu",
}


def native_n_eff(psf: optics.EffectivePSF) -> float:
    """Geometric mean over corner and centre centring of 1 / sum p^2 on native pixels."""
    images = render.draw(psf, render.Grid(1, 40), np.array([[0.0, 0.0], [0.5, 0.5]]))
    return float(math.sqrt(np.prod(1.0 / np.sum(images**2, axis=(1, 2)))))


def slopes_and_width(band: str, sca: int, blur_fwhm: float, realizations: int) -> tuple[dict[str, float], float]:
    config = experiment.SimulationConfig(band=band, sca=sca, realizations=realizations, method="linear")
    grid = config.grid
    psf = optics.effective_psf(config.optics, round(grid.field_arcsec(), 9))
    if blur_fwhm > 0:
        psf = psfstats._gaussian_blur(psf, blur_fwhm)
    offsets = render.draw_offsets(np.random.default_rng(config.seed), config.realizations, config.oversampling)
    stamps = render.draw(psf, grid, offsets)
    scene = experiment.Scene(config, psf, offsets, stamps, moments.fit(stamps, config.moment_settings), 0.0)
    result = experiment.slopes(config, [20.0], beta0=5e-7, scene=scene)[0]
    return {m: float(result.bias[name].mean) for m, name in METRICS.items()}, native_n_eff(psf)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--write", action="store_true", help=f"write {OUTPUT.name}")
    parser.add_argument(
        "--blur", type=float, default=0.3, help="FWHM of the probing Gaussian blur, in units of the official FWHM (default 0.3)"
    )
    parser.add_argument("--realizations", type=int, default=100)
    parser.add_argument(
        "--sed", default="K0V", choices=psfstats.SEDS, help="the star of the official conditions (default K0V: Pickles 1998)"
    )
    args = parser.parse_args(argv)
    start = time.perf_counter()
    official = psfstats.official_statistics()
    lines = [
        '| band | SCA | FWHM nlpsf / official (") | N_eff corner nlpsf / official | N_eff centre nlpsf / official '
        "| peak corner nlpsf / official | peak centre nlpsf / official | size slope | e slopes |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    per_band: dict[str, dict] = {}
    for band in roman.BANDS:
        entry = per_band.setdefault(band, {"size": 0.0, "e": 0.0, "scas": {}})
        for sca in (1, 18):
            lines.append(_compare_point(band, sca, official, args, entry))
            print(f"{band} SCA {sca} done ({time.perf_counter() - start:.0f} s)", file=sys.stderr)
    print("\n".join(lines))
    print()
    print("Per-band optical-model uncertainty of the slopes (largest over SCA 1 and 18):")
    for band, entry in per_band.items():
        print(f"  {band}: size {100 * entry['size']:.1f} %, e {100 * entry['e']:.1f} % of |c_e|")
    if args.write:
        OUTPUT.write_text(json.dumps(_payload(args, per_band), indent=1, sort_keys=True) + "\n")
        print(f"wrote {OUTPUT}", file=sys.stderr)
    return 0


def _compare_point(band: str, sca: int, official: dict, args: argparse.Namespace, entry: dict) -> str:
    """nlpsf's PSF statistics at (band, SCA) against the official ones, and the slope change its width
    gap causes; ``entry`` (the band's worst changes, per SCA) is updated; the table's row is returned."""
    ours = psfstats.psf_statistics(band, sca, sed=args.sed)
    theirs = {c: official[(sca, band, c)] for c in psfstats.CENTRINGS}
    log_width_gap = 0.5 * sum(math.log(theirs[c].n_eff_pixels / ours[c].n_eff_pixels) for c in psfstats.CENTRINGS)
    base, n0 = slopes_and_width(band, sca, 0.0, args.realizations)
    blurred, n1 = slopes_and_width(band, sca, args.blur * theirs["corner"].fwhm_arcsec, args.realizations)
    # Linear in the width gap: the slope change the blur causes per unit ln N_eff, times the gap.
    step = log_width_gap / math.log(n1 / n0)
    delta = {m: (blurred[m] - base[m]) * step for m in METRICS}
    # Ellipticity slopes can pass through zero across SCAs: measure their change against the
    # modulus of the e slope, |c_e| = hypot(c_e1, c_e2), not against each small component.
    modulus = math.hypot(base["e1"], base["e2"])
    change = {"size": delta["size"] / abs(base["size"]), "e": math.hypot(delta["e1"], delta["e2"]) / modulus}
    for metric in change:
        entry[metric] = max(entry[metric], abs(change[metric]))
    entry["scas"][str(sca)] = {
        "fwhm_ratio": ours["corner"].fwhm_arcsec / theirs["corner"].fwhm_arcsec,
        "n_eff_ratio": {c: ours[c].n_eff_pixels / theirs[c].n_eff_pixels for c in psfstats.CENTRINGS},
        "peak_ratio": {c: ours[c].peak_fraction / theirs[c].peak_fraction for c in psfstats.CENTRINGS},
        "slope_change_to_official_width": change,
    }
    return (
        f"| {band} | {sca} | {ours['corner'].fwhm_arcsec:.3f} / {theirs['corner'].fwhm_arcsec:.3f} "
        + "".join(f"| {ours[c].n_eff_pixels:.2f} / {theirs[c].n_eff_pixels:.2f} " for c in ("corner", "center"))
        + "".join(f"| {ours[c].peak_fraction:.3f} / {theirs[c].peak_fraction:.3f} " for c in ("corner", "center"))
        + f"| {100 * change['size']:+.1f} % | {100 * change['e']:.1f} % "
        + "|"
    )


def _payload(args: argparse.Namespace, per_band: dict) -> dict:
    """The shipped file's content."""
    return {
        "description": (
            "Relative uncertainty of the NL bias slopes from nlpsf's optical model (GalSim Cycle-9 Zernikes, pupil "
            "masks) against the official post-CDR PSFs: the slope change that widening or narrowing nlpsf's PSF "
            "to the official N_eff would cause (measured sensitivity d ln|slope| / d ln N_eff times the N_eff gap), "
            "largest over SCA 1 and 18. 'size': relative to the size slope; 'e': the change of (c_e1, c_e2) relative to "
            "|c_e| = hypot(c_e1, c_e2). For e1 and e2 this covers only the width part of the model difference."
        ),
        "source": "roman-technical-information 1.5.0 SummaryPSFstats_{center,corner}.ecsv (2024-06-03)",
        "conditions": {
            "sed": SED_TEXT[args.sed],
            "jitter_fwhm_arcsec": psfstats.OFFICIAL_JITTER_FWHM_ARCSEC,
            "image_pixels": psfstats.OFFICIAL_IMAGE_PIXELS,
            "probe_blur_fwhm_over_official_fwhm": args.blur,
            "slope_magnitude": 20.0,
            "realizations": args.realizations,
            "throughput": roman.DEFAULT_THROUGHPUT,
            "data_version": roman.DATA_VERSION,
            "code_version": __version__,
        },
        "per_band": per_band,
    }


if __name__ == "__main__":
    raise SystemExit(main())
