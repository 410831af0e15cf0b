"""Where a request's slopes come from: three providers of one question, ``covers(request)``.

- :class:`FieldGrid` -- the Roman default's shipped field grid (its scene, readout, exposure,
  beta0, full well, pupil rule and state, at any position of an SCA it holds);
- :class:`PaperTables` -- the paper's shipped tables, one store keyed by position: the SCA
  centre's and the four corner field points' (the paper's scene only, its pupil rule and state);
- :class:`Simulator` -- fresh simulations: covers every valid request.

``covers`` answers a :class:`Coverage` (what is read, at which fidelity) or a :class:`Refusal`: a
code, the request field that takes the answer off that provider, and why, in words. The solver's
plan is the first provider that covers (:func:`first_covering`); a batch, which answers at table
cost, asks the two table providers only and turns the refusal into :class:`NeedsSimulation`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import StrEnum

from nlpsf import roman
from nlpsf.checks import InputError

from . import tables

#: What a refusal to simulate says after its reason (a batch answers at table cost).
REFUSAL = "an answer at table cost does not run simulations"


class RefusalCode(StrEnum):
    """Why a provider does not cover a request."""

    FIDELITY = "fidelity"  # a simulating level was asked for
    ACCURACY = "accuracy"  # an accuracy target is met by measuring effects in fresh simulations
    NO_GRID = "no_grid"  # no field grid installed, or none for this (band, SCA)
    SCENE = "scene"  # another scene than the provider's
    EXPOSURE = "exposure"  # another exposure than the grid's
    READOUT = "readout"  # another ramp than the grid's
    SETTING = "setting"  # another beta0, full well, pupil rule or state than the grid's
    THROUGHPUT = "throughput"  # another photometry than the grid's
    PUPIL_SCALE = "pupil_scale"  # another pupil rule than the tables'
    LINEARISED = "linearised"  # another detector state than the tables'
    MAGNITUDE = "magnitude"  # brighter than a grid node's magnitudes (found while the answer reads them)


@dataclass(frozen=True)
class Refusal:
    """A provider's "no": its code, the request field at fault and why."""

    code: RefusalCode
    field: str
    why: str


@dataclass(frozen=True)
class Coverage:
    """A provider's "yes": which provider, at which fidelity, and what it reads."""

    provider: str
    fidelity: str
    #: The tables read (the SCA centre's, or a corner field point's); the paper tables' also for a grid or a simulation.
    tables: tables.TableSet | None = None
    #: The Roman default's field grid (:class:`FieldGrid` only).
    grid: object | None = None


class NeedsSimulation(InputError):
    """The request is valid, but its answer needs a fresh simulation: not at table cost."""

    def __init__(self, refusal: Refusal):
        self.refusal = refusal
        super().__init__(refusal.field, refusal.why)


def shipped_grid():
    """The Roman default's shipped field grid (``fieldgrid.FieldGrid``), None where none is installed."""
    from .fieldgrid import shipped_grid

    return shipped_grid()


#: The grid's settings a request must share, with the request field each is, in the order checked.
_GRID_SETTINGS = (
    ("exptime_s", "exptime"),
    ("beta0", "beta0"),
    ("full_well_e", "full_well"),
    ("pupil_scale", "pupil_scale"),
    ("linearise_at", "linearise_at"),
    ("scene", "scene"),
)


class FieldGrid:
    """The Roman default's shipped field grid: its scene unmodified at any position (none: the SCA's
    range over its nodes), its readout, exposure, beta0, full well, pupil rule and state, at the
    table level."""

    name = "field grid"

    def __init__(self, grid=None):
        self._grid = grid

    @property
    def grid(self):
        return self._grid if self._grid is not None else shipped_grid()

    def covers(self, request, fidelity: str) -> Coverage | Refusal:
        from nlpsf.request import presets

        if request.accuracy is not None:
            return Refusal(RefusalCode.ACCURACY, "accuracy", "an accuracy is measured by simulation")
        if fidelity != "table":
            return Refusal(RefusalCode.FIDELITY, "fidelity", f"fidelity {fidelity}")
        grid = self.grid
        if grid is None:
            return Refusal(RefusalCode.NO_GRID, "scene", "none installed")
        entry = grid.meta["tables"].get(f"{request.band}_{request.sca:02d}")
        if entry is None:
            return Refusal(RefusalCode.NO_GRID, "scene", f"the grid has no {request.band} SCA {request.sca}")
        own = presets.default_fill(request.band, request.sca)
        if not math.isclose(request.exptime, own.exptime, rel_tol=1e-9):
            return Refusal(RefusalCode.EXPOSURE, "exptime", "the readout differs from the default's")
        if not presets.is_default_scene(request.scene, own.background_e):
            return Refusal(RefusalCode.SCENE, "scene", "the scene differs from the default's")
        if request.ramp != own.ramp:
            return Refusal(RefusalCode.READOUT, "ramp", "the readout differs from the default's")
        settings = entry.get("settings", {})
        wanted = {
            "exptime_s": request.exptime, "beta0": request.beta0, "full_well_e": request.full_well,
            "pupil_scale": request.pupil_scale, "linearise_at": request.linearise_at, "scene": request.preset,
        }  # fmt: skip
        for name, field in _GRID_SETTINGS:
            held, value = settings.get(name), wanted[name]
            numeric = isinstance(value, float) and held is not None
            same = math.isclose(float(held), float(value), rel_tol=1e-6) if numeric else held == value
            if not same:
                return Refusal(RefusalCode.SETTING, field, f"the grid's {name} is {held!r}, the request's {value!r}")
        from .fieldgrid import grid_residual_model

        held_model = grid_residual_model(settings)
        if request.residual_nl is not None and request.residual_nl != held_model:
            why = f"the grid's residual_nl is {held_model!r}, the request's {request.residual_nl!r}"
            return Refusal(RefusalCode.SETTING, "residual_nl", why)
        if request.throughput not in (None, settings.get("throughput")):
            return Refusal(RefusalCode.THROUGHPUT, "throughput", f"the grid's throughput is {settings.get('throughput')!r}")
        return Coverage(self.name, "table", grid=grid)


class PaperTables:
    """The paper's shipped tables as one store keyed by position: the SCA centre's (``slopes.npz``)
    and each SCA's four corner field points' (``field_slopes.npz``), at the paper's scene, its pupil
    rule and the state beta0."""

    name = "paper tables"

    def at(self, position, sca: int) -> tables.TableSet | None:
        """The tables at ``position`` (None: the SCA centre): the centre's, a corner field point's,
        or None where the store holds no table there (or no field-point tables are installed)."""
        if position is None:
            return tables.load_tables()
        for point, corner in enumerate(roman.field_points(sca)):
            if point and _same_position(corner, position):
                corners = field_tables()
                return None if corners is None else corners.at_point(point)
        centre = tables.load_tables()
        held = centre.get(centre.bands[0], sca).position_pixels
        return centre if _same_position(held, position) else None

    def tables_for(self, scene, sca: int) -> tables.TableSet:
        """The tables a request reads (for its slopes, its saturation, its photometry): those at the
        scene's position where the store holds the paper's scene there, else the SCA centre's."""
        if scene is not None and scene.position is not None and replace(scene, position=None).no_effects:
            held = self.at(scene.position, sca)
            if held is not None:
                return held
        return tables.load_tables()

    def covers(self, request, scene, fidelity: str, tableset: tables.TableSet) -> Coverage | Refusal:
        """``scene``: the scene the answer is for (None: the paper's); ``tableset``: the tables it reads
        (:meth:`tables_for`'s, or the caller's)."""
        if fidelity != "table":
            return Refusal(RefusalCode.FIDELITY, "fidelity", f"fidelity {fidelity}")
        if scene is not None and not scene.no_effects and not _holds(scene, tableset, request.band, request.sca):
            return Refusal(RefusalCode.SCENE, "scene", "the tables hold the paper's scene only")
        table_rule = str(tableset.get(request.band, request.sca).settings["pupil_scale"])
        if request.pupil_scale is not None and request.pupil_scale != table_rule:
            return Refusal(RefusalCode.PUPIL_SCALE, "pupil_scale", f"the tables hold the {table_rule} pupil scale")
        if request.linearise_at != "beta0":
            return Refusal(RefusalCode.LINEARISED, "linearise_at", "the tables hold the slope at beta0")
        return Coverage(self.name, "table", tables=tableset)


class Simulator:
    """Fresh simulations (the linear response at the table level): every valid request."""

    name = "simulator"

    def covers(self, request, fidelity: str, tableset: tables.TableSet) -> Coverage:
        return Coverage(self.name, "linear" if fidelity == "table" else fidelity, tables=tableset)


def _same_position(a, b) -> bool:
    return all(abs(x - y) < 1e-6 for x, y in zip(a, b, strict=True))


def _holds(scene, tableset: tables.TableSet, band: str, sca: int) -> bool:
    """Whether the tables hold the scene: it differs from the paper's by its position alone, and the
    table of (band, SCA) was built at that position (a field-point table, or the centre's)."""
    if scene.position is None or not replace(scene, position=None).no_effects:
        return False
    return _same_position(tableset.get(band, sca).position_pixels, scene.position)


def field_tables() -> tables.TableSet | None:
    """The shipped field-point tables, None if this installation has none."""
    path = tables.field_table_path()
    return tables.load_tables(str(path)) if path.exists() else None
