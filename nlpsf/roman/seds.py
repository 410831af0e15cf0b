"""Star spectra vendored in ``nlpsf/data/seds/``, selectable by name (``--sed k0v``).

One owner of the named, tabulated SEDs: which file each name reads, its source and its units.
``scene.SceneModel`` validates a name against :data:`NAMED` and reads the table through
:func:`table`; provenance and licence are in ``nlpsf/data/SOURCES.md`` and ``data/seds/LICENSE.md``.

``k0v``
    the K0V (solar metallicity) spectrum of the Pickles (1998, PASP 110, 863) UVKLIB library as
    STScI distributes it (``pickles_uk_31``), 400-2500 nm. The official Roman PSF products use a K0V
    star without naming the spectrum; STPSF's spectral-type lookup (poppy) would take the Phoenix or
    Castelli & Kurucz 2004 model at T_eff = 5250 K, log g = 4.5, [M/H] = 0 for it, which is not
    vendored here (docs in SOURCES.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np


@dataclass(frozen=True)
class NamedSED:
    """One vendored spectrum: its file in ``data/seds/`` and what it is."""

    name: str
    file: str
    description: str
    source: str


NAMED: dict[str, NamedSED] = {
    "k0v": NamedSED(
        "k0v",
        "pickles_uk_31.txt",
        "K0V, solar metallicity (Pickles 1998 UVKLIB ukk0v, STScI pickles_uk_31)",
        "Pickles 1998, PASP 110, 863; STScI TRDS grid/pickles (pickles_uk_31.fits)",
    ),
}

#: Angstrom per nanometre (the files tabulate wavelengths in angstrom, the scene in nm).
ANGSTROM_PER_NM = 10.0


def is_named(text: str) -> bool:
    return isinstance(text, str) and text.strip().lower() in NAMED


def path(name: str):
    return resources.files("nlpsf") / "data" / "seds" / NAMED[name].file


@lru_cache(maxsize=len(NAMED))
def table(name: str) -> tuple[tuple[float, ...], tuple[float, ...]]:
    """(wavelength [nm], f_lambda [erg s^-1 cm^-2 A^-1]) of a named SED, as its file tabulates it."""
    with path(name).open() as handle:
        rows = np.loadtxt(handle, comments="#", dtype=np.float64)
    return tuple(rows[:, 0] / ANGSTROM_PER_NM), tuple(rows[:, 1])
