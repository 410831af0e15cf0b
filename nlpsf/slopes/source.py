"""c(m), the slope a solve reads at its request's conditions: from the shipped tables (the paper's
scene, rescaled exactly in exposure and beta0), from the Roman default's field grid, or from fresh
simulations (a scene, a ramp the tables do not map, another pupil rule or detector state)."""

from __future__ import annotations

import gc
import math
from dataclasses import replace

from nlpsf import defaults
from nlpsf.checks import SimulationError
from nlpsf.flags import FlagCode
from nlpsf.request.resolve import SolveRequest
from nlpsf.sim import levels, ramps

from . import tables
from .providers import REFUSAL, NeedsSimulation, Refusal, RefusalCode

#: Centroids one prepared scene holds at most in a linear-response simulation; more are simulated as
#: independent batches of this size (seeds seed, seed + 1, ...) and pooled (``experiment.pooled``).
#: Where pixels lose resultants an answer can need thousands, ~0.6 MB each on the HLWAS ramp.
BATCH_REALIZATIONS = 800


class Slopes:
    """c(m) at the request's conditions, from the tables or from fresh simulations."""

    def __init__(
        self,
        band: str,
        sca: int,
        metric: str,
        mode: str,
        beta0: float,
        exptime: float,
        fidelity: str,
        tableset,
        ramp: ramps.Ramp | None = None,
        full_well: float = defaults.FULL_WELL_E,
        throughput: str | None = None,
        scene=None,
        pupil_scale: str | None = None,
        linearise_at: str = "beta0",
        grid=None,
        realizations: int | None = None,
        residual_nl: str | None = None,
        simulate: bool = True,
    ):
        self.band, self.sca, self.metric, self.mode = band, sca, metric, mode
        self.linearise_at = linearise_at  # the detector state of the fresh simulations' slopes
        self.residual_nl = residual_nl  # how a calibration error acts there (experiment.correction)
        #: The Roman default's field grid where it covers the request (``providers.FieldGrid``), else None.
        self.grid = grid
        #: Magnitudes brighter than the grid covers (outside a node's magnitude grid): simulated instead.
        self.grid_misses: list[float] = []
        #: Whether a magnitude the grid does not hold may be simulated (a batch's answer: no, refused).
        self.simulate = simulate
        self.pupil_scale = pupil_scale  # of the fresh simulations (None: the tables' own)
        self.beta0, self.exptime, self.fidelity = beta0, exptime, fidelity
        self.ramp, self.full_well = ramp, full_well
        self.scene_model = scene  # nlpsf.sim.scene.SceneModel of the simulated levels (None: the paper's)
        self.table = tableset.get(band, sca)
        #: Centroids of the fresh simulations (the plan's, else the tables' own).
        self.realizations = int(realizations or self.table.settings["realizations"])
        #: Magnitudes the table was relabelled by for another throughput's photometry (0: none).
        self.relabel_shift = 0.0
        if throughput is not None:
            self.table, self.relabel_shift = tables.with_throughput(self.table, throughput)
        self._cache: dict[float, tuple[float, float]] = {}
        self._scene = None  # experiment.Scene of the fresh simulations, prepared once per request
        #: The simulated star's peak fraction where the answer's limits are its own (else the tables').
        self.own_peak_fraction: float | None = None
        self._results: dict[float, object] = {}  # experiment.SlopeResult of each simulated magnitude
        #: Each batch of centroids simulated, by (magnitude, its configuration): shared with the Slopes
        #: that asks for more centroids of the same request (:meth:`reuse_batches`).
        self._batches: dict[tuple, object] = {}
        #: beta_eff / beta0 where the ramp maps exactly onto the tables (OLS), else None.
        self.ramp_factor = ramp.quadratic_factor(exptime) if ramp is not None and ramp.fit == "ols" else None
        #: How the ramp's slopes were obtained in this request ("table", "simulation").
        self.ramp_bases: set[str] = set()
        #: :meth:`modulus_over_component` read from the field grid, by magnitude.
        self._grid_moduli: dict[float, float | None] = {}
        #: (magnitude, slope, |error|) of the field grid at this node, read with the SCA's other nodes.
        self._read_with_others: tuple[float, float, float] | None = None

    @classmethod
    def for_request(cls, request: SolveRequest, the_plan) -> Slopes:
        """The slopes of ``request`` as ``the_plan`` (``solver.SolvePlan``) says they are read."""
        return cls(
            request.band,
            request.sca,
            request.metric,
            request.mode,
            request.beta0,
            request.exptime,
            the_plan.fidelity,
            the_plan.tables,
            request.ramp,
            request.full_well,
            throughput=request.throughput,
            scene=the_plan.scene,
            pupil_scale=request.pupil_scale,
            linearise_at=request.linearise_at,
            grid=the_plan.grid,
            realizations=the_plan.realizations,
            residual_nl=request.residual_model,
            simulate=the_plan.simulate,
        )

    @property
    def prepared(self):
        """The prepared simulation (``experiment.Scene``) of this request, None where none ran."""
        return self._scene

    @property
    def table_beta0(self) -> float:
        """The beta0 the tables are read at: beta_eff for a ramp that maps exactly."""
        return self.beta0 * (self.ramp_factor or 1.0)

    def range(self) -> tuple[float, float]:
        return self.table.grid_range(self.exptime, self.table_beta0)

    def exact_from(self) -> float:
        """Faintest-side limit of the exact ramp mapping: brighter than this, the brightest pixel's
        last resultant passes the full well and drops out of its fit."""
        last = self.ramp.table.duration_s / self.exptime
        return self.table.saturation(self.exptime, self.full_well) - 2.5 * math.log10(1.0 / last)

    def from_table(self, magnitude: float) -> tuple[float, float, int]:
        value, error, region = self.table.slope(self.metric, self.mode, magnitude, self.exptime, self.table_beta0)
        scale = self.ramp_factor or 1.0  # d/d beta = c_2 d/d beta_eff
        return float(value[0]) * scale, float(error[0]) * scale, int(region[0])

    def at(self, magnitude: float) -> tuple[float, float, int]:
        """(slope, uncertainty, region): region -1 brighter than the grid, 0 in it, +1 fainter."""
        if self.grid is not None:
            return self._from_grid(magnitude)
        if self.ramp is not None:
            return self._ramp_at(magnitude)
        value, error, region = self.from_table(magnitude)
        if self.fidelity == "table" or region < 0:
            return value, error, region
        return (*self._simulated(magnitude), region)

    def read_with_others(self, magnitude: float, slope: float, error: float) -> None:
        """The field grid's (slope, |error|) at ``magnitude`` at this node (the scene's position is one
        of the grid's nodes), as ``sca_nodes`` read it with the SCA's other nodes: :meth:`at` answers
        that magnitude with it instead of reading the grid again (the same slope; the error to the
        last bits). Ignored unless finite: :meth:`at` then reads the grid as ever."""
        if self.grid is not None and math.isfinite(slope) and math.isfinite(error):
            self._read_with_others = (magnitude, slope, error)

    def _from_grid(self, magnitude: float) -> tuple[float, float, int]:
        """The Roman default's slope from its field grid at the scene's position; a magnitude brighter
        than a node's grid is simulated (and noted). Fainter than the grid's faint end (m = 28 in the
        shipped file), the linear regime's flux law from there (region +1), as the paper's tables
        extrapolate: H158 SCA 18 at (1000, 3000), size, m = 30: 0.3639932 against 0.3639921 simulated."""
        faint = self.grid.magnitude_range(self.band, self.sca)[1]
        known = self._read_with_others
        if known is not None and magnitude == known[0]:
            self.ramp_bases.add("grid")
            return known[1], known[2], 1 if magnitude > faint else 0
        if magnitude > faint:
            value, error = grid_slope(self.grid, self.band, self.sca, self.scene_model.position, self.metric, self.mode, faint)
            scale = 10 ** (-0.4 * (magnitude - faint))
            self.ramp_bases.add("grid")
            return value * scale, abs(error) * scale, 1
        value, error = grid_slope(self.grid, self.band, self.sca, self.scene_model.position, self.metric, self.mode, magnitude)
        if math.isfinite(value) and math.isfinite(error):
            self.ramp_bases.add("grid")
            return value, abs(error), 0
        self.grid_misses.append(magnitude)
        return (*self._simulated(magnitude), 0)

    def _ramp_at(self, magnitude: float) -> tuple[float, float, int]:
        exact = self.fidelity == "table" and self.ramp_factor is not None and magnitude >= self.exact_from()
        if exact:
            self.ramp_bases.add("table")
            return self.from_table(magnitude)
        self.ramp_bases.add("simulation")
        hi = self.table.grid_range(self.exptime, self.beta0)[1]
        return (*self._simulated(magnitude), 1 if magnitude > hi else 0)

    def _simulated(self, magnitude: float) -> tuple[float, float]:
        key = round(magnitude, 9)
        if key not in self._cache:
            self._cache[key] = self._simulate(magnitude)
        return self._cache[key]

    def _config(self):
        """The fresh simulations' configuration (magnitude-independent)."""
        from nlpsf.sim import experiment  # the simulator: only fresh-simulation levels need it

        # A ramp that the tables do not map exactly is simulated with the linear response.
        level = levels.simulation_settings("linear" if self.fidelity == "table" else self.fidelity)
        batched = level.method == "linear" and self.realizations > BATCH_REALIZATIONS
        return experiment.SimulationConfig.from_table(
            self.table.settings,
            band=self.band,
            sca=self.sca,
            exptime_s=self.exptime,
            throughput=self.table.throughput,
            method=level.method,
            n_wavelengths=level.n_wavelengths,
            realizations=BATCH_REALIZATIONS if batched else self.realizations,
            **({} if self.pupil_scale is None else {"pupil_scale": self.pupil_scale}),
            **({} if self.ramp is None else {"ramp": self.ramp, "full_well_e": self.full_well}),
            **({} if self.scene_model is None else {"scene": self.scene_model}),
        )

    def prepare(self):
        """The prepared simulation (``experiment.Scene``) of this request, made once (magnitude-independent)."""
        from nlpsf.sim import experiment

        config = self._config()
        if self._scene is None or self._scene.config != config:
            self._scene = experiment.prepare(config)
        return self._scene

    def own_final_frame_saturation(self) -> tuple[float, float]:
        """(magnitude, peak fraction): the star of the simulated scene whose brightest pixel, on top
        of the scene's background, reaches the request's full well at the end of the exposure --
        the prepared scene's own peak (``Scene.star_peak_fraction``, over every sub-pixel centroid),
        by the rule the tables and the field grid are built with (``tablebuild.saturation_magnitude``)."""
        from dataclasses import replace

        from . import tablebuild

        scene = self.prepare()
        peak = float(scene.star_peak_fraction)
        self.own_peak_fraction = peak
        return tablebuild.saturation_magnitude(peak, replace(scene.config, full_well_e=self.full_well)), peak

    def own_peak_electrons(self, magnitude: float) -> float | None:
        """The simulated star's brightest pixel before the NL [e-] at ``magnitude`` (no background),
        where the answer's limits are its own (:meth:`own_final_frame_saturation`), else None."""
        if self.own_peak_fraction is None:
            return None
        config = self._scene.config
        return float(config.electrons(magnitude)) * self.own_peak_fraction * config.oversampling**2

    def _simulate(self, magnitude: float) -> tuple[float, float]:
        if not self.simulate:  # a batch answers at table cost: refused here, before any work
            raise NeedsSimulation(
                Refusal(
                    RefusalCode.MAGNITUDE,
                    "magnitude",
                    f"the slope at m={magnitude:.4g} is outside what the tables and the Roman default's field grid hold "
                    f"(a magnitude brighter than a node's grid), so it would be simulated: {REFUSAL}",
                )
            )
        from nlpsf.sim import experiment

        scene = self.prepare()
        config = scene.config
        batches = [self._batch(magnitude, config, scene)]
        for k, size in enumerate(self._more_batches(config.realizations), start=1):
            batches.append(self._batch(magnitude, replace(config, realizations=size, seed=config.seed + k)))
        result = experiment.pooled(batches)
        self._results[round(magnitude, 9)] = result
        value, error = result.slope(self.mode, defaults.METRIC_COLUMNS[self.metric])
        if value is None:
            raise SimulationError(f"the simulation at m={magnitude:g} failed: {'; '.join(result.flags)}")
        return value, error

    def _batch(self, magnitude: float, config, scene=None):
        """One batch's slopes at ``magnitude`` (``scene``: its prepared scene, else prepared here),
        simulated once for this request however many times its centroids are counted again."""
        from nlpsf.sim import experiment

        key = (round(magnitude, 9), config)
        if key not in self._batches:
            ask = {"beta0": self.beta0, "linearise_at": self.linearise_at, "residual_nl": self.residual_nl}
            self._batches[key] = experiment.slopes(config, [magnitude], scene=scene, **ask)[0]
            if scene is None:
                # A batch's prepared scene holds reference cycles: freed now, not after several batches
                # have piled up (H158, 6,400 centroids: 0.85 GB at the peak instead of 2.5 GB).
                gc.collect()
        return self._batches[key]

    def reuse_batches(self, earlier: Slopes) -> None:
        """Take the batches ``earlier`` (the same request with fewer centroids) simulated: the
        batches of 800 both count are not simulated again."""
        self._batches = earlier._batches

    def _more_batches(self, first: int) -> list[int]:
        """The sizes of the batches after the first (of ``first`` centroids) that make up the request's
        centroids (:data:`BATCH_REALIZATIONS` each, the last the remainder)."""
        left = self.realizations - first
        return [min(BATCH_REALIZATIONS, left - start) for start in range(0, max(left, 0), BATCH_REALIZATIONS)]

    #: Flags of a simulated slope that say how far it can be trusted; the answer carries them
    #: (the simulation's other flags, saturation and validity, the solver states in its own terms).
    SLOPE_QUALITY = (FlagCode.JUMPY_FINITE_DIFFERENCE,)

    def slope_quality_flags(self) -> list:
        """The slope-quality flags (:data:`SLOPE_QUALITY`) of the magnitudes simulated for this
        answer, one per code (the first magnitude's)."""
        seen: dict = {}
        for result in self._results.values():
            for flag in result.flags:
                code = getattr(flag, "code", None)
                if code in self.SLOPE_QUALITY and code not in seen:
                    seen[code] = flag
        return list(seen.values())

    def modulus_over_component(self, magnitude: float) -> float | None:
        """|c_e| / |c_ei| = hypot(c_e1, c_e2) / |c_ei| of this answer's own slopes at ``magnitude``
        (an e1 / e2 answer; 1 otherwise): from the field grid at the position, or from the simulation
        that gave the slope there. None where the answer's slope there came from the tables (the
        caller then reads the tables' ratio)."""
        if self.metric not in ("e1", "e2"):
            return 1.0
        if self.grid is not None and magnitude in self._grid_moduli:
            return self._grid_moduli[magnitude]  # the model part and the component flags both ask at the answer's
        pair = None
        if self.grid is not None:
            position = self.scene_model.position
            pair = [float(v) for v in self.grid.values(self.band, self.sca, position, ("e1", "e2"), self.mode, magnitude)]
            pair = pair if all(math.isfinite(v) for v in pair) else None
        from_grid = pair is not None
        result = self._results.get(round(magnitude, 9))
        if pair is None and result is not None:
            pair = [result.slope(self.mode, defaults.METRIC_COLUMNS[m])[0] for m in ("e1", "e2")]
            pair = pair if all(v is not None and math.isfinite(v) for v in pair) else None
        if pair is None:
            return None
        component = abs(pair[0] if self.metric == "e1" else pair[1])
        ratio = math.hypot(*pair) / component if component > 0 else None
        if from_grid:
            self._grid_moduli[magnitude] = ratio  # the grid's numbers: the same at every call
        return ratio


def grid_slope(grid, band: str, sca: int, position, metric: str, mode: str, magnitude: float) -> tuple[float, float]:
    """(slope, standard error) of a field grid (``fieldgrid.FieldGrid.slope``) at a position and magnitude."""
    value, error = grid.slope(band, sca, position, metric, mode, magnitude)
    return float(value), float(error)
