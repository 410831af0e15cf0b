"""The shipped Roman field grid (docs/field.md): what it holds, and its slopes against a fresh
simulation of the Roman default at a position that is no node, with the same centroid draws."""

import numpy as np
import pytest

from nlpsf import defaults, experiment, fieldgrid, tablebuild

GRID = fieldgrid.shipped_grid()
pytestmark = pytest.mark.skipif(GRID is None, reason="no shipped field grid in this checkout")
#: The issue's targets for an interpolated slope where no resultant saturates (e: where the slope is
#: not near zero, |slope| >= 10 % of the median over the SCA's nodes; docs/field.md).
TARGET = {"size": 0.01, "e1": 0.03, "e2": 0.03}
METRICS = {"size": "dR_over_R", "e1": "de1", "e2": "de2"}


#: The grid size of each band in the shipped file: R062, Z087, Y106, W146 and K213 on 5 x 5 nodes,
#: where 3 x 3 missed the e targets (docs/field.md), the other bands on 3 x 3.
GRID_SIZE = {"R062": 5, "Z087": 5, "Y106": 5, "W146": 5, "K213": 5}


def test_the_shipped_grid_holds_float32_nodes_and_says_how_it_was_built():
    assert GRID.coverage(), "the file covers no (band, SCA)"
    provenance = GRID.meta["provenance"]
    assert len(provenance["code_commit"]) == 40 and provenance["cpu_s"] > 0
    for band, sca in GRID.coverage():
        key = GRID.key(band, sca)
        assert GRID.arrays[f"{key}/values"].dtype == np.float32
        n = GRID_SIZE.get(band, 3)
        assert GRID.arrays[f"{key}/values"].shape[:2] == (n, n)
        conditions = GRID.conditions(band, sca)
        assert conditions["settings"]["scene"] == "roman" and conditions["settings"]["linearise_at"] == "corrected"
        assert conditions["settings"]["realizations"] == 100 and conditions["grid"] == n
        assert len(conditions["provenance"]["code_commit"]) == 40
        brightest, faintest = GRID.magnitude_range(band, sca)
        # The grid starts 1.5 mag (rounded down to its step) brighter than the ramp's limit at every node.
        assert faintest == defaults.TABLE_FAINT_LIMIT
        assert brightest <= GRID.saturation_magnitudes(band, sca).min() - 1.5 + 0.125
        centre = (2044.5, 2044.5)
        assert GRID.final_frame_saturation_magnitude(band, sca, centre) > GRID.saturation_magnitude(band, sca, centre) + 3
    covered = set(GRID.coverage())
    assert all(GRID.covers(b, s) == ((b, s) in covered) for b in defaults.BANDS for s in range(1, defaults.N_SCA + 1))


def test_the_reader_returns_none_without_the_file(monkeypatch, tmp_path):
    monkeypatch.setattr(fieldgrid, "shipped_grid_path", lambda: tmp_path / "absent.npz")
    fieldgrid.shipped_grid.cache_clear()
    try:
        assert fieldgrid.shipped_grid() is None
    finally:
        fieldgrid.shipped_grid.cache_clear()


def test_the_shipped_grid_matches_a_fresh_simulation_off_the_nodes():
    band, sca = ("H158", 9) if GRID.covers("H158", 9) else GRID.coverage()[0]
    position = (3311.0, 757.0)
    m_sat = GRID.final_frame_saturation_magnitude(band, sca, position)
    magnitudes = [20.0, 22.0]
    settings = tablebuild.TableSettings.roman()
    config = settings.config(band, sca, position=position)
    fresh = experiment.slopes(config, magnitudes, beta0=settings.beta0, linearise_at=settings.linearise_at)
    assert m_sat < magnitudes[0]  # fainter than where any resultant saturates
    for magnitude, result in zip(magnitudes, fresh, strict=True):
        assert result.extras["ramp"]["fitted_on_fewer"] == 0  # no resultant saturates here
        for metric, name in METRICS.items():
            value, error = GRID.slope(band, sca, position, metric, "bias", magnitude)
            scale = np.median(np.abs(GRID.node_values(band, sca, f"bias_{metric}", magnitude)))
            truth = result.bias[name].mean
            if abs(truth) < 0.1 * scale:
                continue  # near zero: a relative error says nothing
            assert abs(value / truth - 1) <= TARGET[metric], (metric, magnitude, value, truth)
            assert error > 0
