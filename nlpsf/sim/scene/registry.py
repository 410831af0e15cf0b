"""The scene effects' registry: one entry per effect (its fields, the values that switch it off, its
nominal Roman value and that value's source, optical or detector, whether it breaks the tables'
beta x flux rescaling, what it combines with), GalSim's Roman constants, the limits a request may
give, and the shipped measurement of what the paper's scene leaves out.

Adding an effect: one :data:`REGISTRY` entry here, its field and check in ``model``, its kernel in
``kernels`` and its test.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

#: GalSim 2.8.5 ``galsim/roman/__init__.py`` ``ipc_kernel`` before its normalisation (rows are y,
#: columns x, as a GalSim Image's array); :data:`ROMAN_IPC_KERNEL` divides it by its sum as GalSim does.
_ROMAN_IPC_RAW = (
    (0.001269938, 0.015399776, 0.001199862),
    (0.013800177, 1.0, 0.015600367),
    (0.001270391, 0.016129619, 0.001200137),
)
ROMAN_IPC_KERNEL: tuple[tuple[float, ...], ...] = tuple(
    tuple(v / float(np.sum(_ROMAN_IPC_RAW)) for v in row) for row in _ROMAN_IPC_RAW
)
#: GalSim's Roman constants (``galsim.roman.jitter_rms``, ``charge_diffusion``).
ROMAN_JITTER_ARCSEC = 0.014
ROMAN_CHARGE_DIFFUSION_PX = 0.1

IPC_ORDERS = ("after", "before")
SED_UNITS = ("flambda", "fnu")
#: Limits a request may give (anything beyond is not a Roman scene).
MAX_JITTER_ARCSEC = 1.0
MAX_DIFFUSION_PX = 3.0
MAX_BACKGROUND_E = 1e5
MAX_BFE = 1e-4
MAX_NL_ORDER = 8
#: Largest nearest-neighbour IPC coupling alpha.
MAX_IPC_ALPHA = 0.2
#: Default relative accuracy the number of wavelengths is chosen for (see :func:`choose_wavelengths`).
WAVELENGTH_ACCURACY = 1e-2
#: Empirical factor between the relative error of the NL slopes from one wavelength and the band's
#: photon-weighted var / lambda^2 (measured on H158, W146 and R062 in
#: ``tests/library/test_scene.py::test_wavelength_count_meets_its_stated_accuracy``).
SLOPE_BINNING_FACTOR = 4.0


@dataclass(frozen=True)
class SceneEffect:
    """One scene effect: the one entry the presets, the impact report, the solver and the API read.

    ``fields``: the ``SceneModel`` fields that set it (copied together when a solve simulates it);
    ``off``: the values that switch it off; ``nominal``: the Roman value the impact report and the
    shipped model uncertainty try when a scene leaves it off (a None value: no default), with its
    ``source``; ``kind``: "optical" (acts on the PSF before the pixels) or "detector"; ``breaks_beta_q``:
    it adds a flux dependence of its own (the tables' beta x flux rescaling then does not hold);
    ``combines_with``: what it can be simulated together with; ``is_on``: whether a scene has it.
    """

    name: str
    fields: tuple[str, ...]
    off: dict
    nominal: dict
    source: str
    kind: str
    breaks_beta_q: bool
    combines_with: str
    is_on: Callable[[Any], bool]  # of a SceneModel (model.py, which imports this module)
    #: Part of the "galsim-roman" preset (at its nominal value).
    in_roman_preset: bool = False


_EVERY = "every other effect, and a ramp"
#: The scene effects, in the order they act (the impact report's contract uses this order).
#: Adding an effect: one entry here, its kernel (``detector_chain`` or the optics) and its test.
REGISTRY: dict[str, SceneEffect] = {
    e.name: e
    for e in (
        SceneEffect(
            "position", ("position",), {"position": None}, {"position": (4.0, 4.0)},
            "a corner of the SCA (pixel 4, 4)", "optical", False, _EVERY, lambda s: s.position is not None, False,
        ),
        SceneEffect(
            "sed", ("sed", "sed_table", "sed_units", "n_wavelengths"), {"sed": None, "sed_table": None, "n_wavelengths": None},
            {"sed": "flat"}, "flat f_nu (the AB reference)", "optical", False, _EVERY, lambda s: s.sed is not None, True,
        ),
        SceneEffect(
            "jitter", ("jitter_arcsec",), {"jitter_arcsec": 0.0}, {"jitter_arcsec": ROMAN_JITTER_ARCSEC},
            "galsim.roman.jitter_rms", "optical", False, _EVERY, lambda s: s.jitter_arcsec > 0, True,
        ),
        SceneEffect(
            "charge_diffusion", ("charge_diffusion_px",), {"charge_diffusion_px": 0.0},
            {"charge_diffusion_px": ROMAN_CHARGE_DIFFUSION_PX}, "galsim.roman.charge_diffusion", "optical", False, _EVERY,
            lambda s: s.charge_diffusion_px > 0, True,
        ),
        SceneEffect(
            "ipc", ("ipc", "ipc_label", "ipc_order"), {"ipc": None, "ipc_label": None},
            {"ipc": ROMAN_IPC_KERNEL, "ipc_label": "roman"}, "galsim.roman.ipc_kernel", "detector", False, _EVERY,
            lambda s: s.ipc is not None, True,
        ),
        SceneEffect(
            "nl_polynomial", ("nl_coefficients",), {"nl_coefficients": ()}, {"nl_coefficients": (1e-13, 1e-18)},
            "b3, b4 each 0.1 % of the signal at 1e5 e- (the residual level quoted in issue 8)", "detector", True, _EVERY,
            lambda s: any(c != 0 for c in s.nl_coefficients),
        ),
        SceneEffect(
            "brighter_fatter", ("bfe_coefficient",), {"bfe_coefficient": 0.0}, {"bfe_coefficient": None},
            "no default: give a coefficient to measure it", "detector", True,
            "every other effect; not a ramp (ramps.RAMP_REFUSES)", lambda s: s.bfe_coefficient != 0,
        ),
        SceneEffect(
            "background", ("background_e",), {"background_e": 0.0}, {"background_e": 100.0},
            "100 e- per pixel, of the order of Roman's sky over 168 s", "detector", True, _EVERY,
            lambda s: s.background_e > 0,
        ),
    )
}  # fmt: skip
#: Names of the effects, in the order they act.
EFFECTS: tuple[str, ...] = tuple(REGISTRY)
#: Representative values the impact report tries for an effect the scene leaves off, with their
#: sources as ``note`` (read from :data:`REGISTRY`).
NOMINAL: dict[str, dict] = {name: {**e.nominal, "note": e.source} for name, e in REGISTRY.items()}


#: Where :func:`shipped_model_uncertainty` reads the shipped measurement.
MODEL_UNCERTAINTY_FILE = "scene_model_uncertainty.json"


@lru_cache(maxsize=1)
def shipped_model_uncertainty() -> dict:
    """What the paper's scene leaves out, measured by ``scripts/model_uncertainty.py`` (worst
    |impact| of each effect at its :data:`NOMINAL` value over SCA 1 and 18, two magnitudes; see
    the file's ``description``). The solver's answers without ``accuracy`` read their model part here."""
    path = Path(str(resources.files("nlpsf") / "data" / MODEL_UNCERTAINTY_FILE))
    return json.loads(path.read_text())
