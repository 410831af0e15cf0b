"""The shipped Roman field grid (docs/field.md): what it holds, and its slopes against a fresh
simulation of the Roman default at a position that is no node, with the same centroid draws."""

import numpy as np
import pytest

from nlpsf import defaults
from nlpsf.sim import experiment
from nlpsf.slopes import fieldgrid, gridfile, tablebuild
from nlpsf.slopes.fieldgrid import grid_residual_model

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


def _format_2_values(content: bytes) -> dict[str, np.ndarray]:
    """Every ``{key}/values`` of a nlpsf-field-grid-2 file, decoded here (not by ``fieldgrid``)."""
    import io
    import json

    with np.load(io.BytesIO(content)) as data:
        meta = json.loads(data["meta"].tobytes().decode())
        assert meta["format"] == "nlpsf-field-grid-2"
        out = {}
        for name in (n for n in data.files if n.endswith("/values")):
            planes = data[name]  # (itemsize, columns, n, n, M) bytes
            raw = np.ascontiguousarray(np.moveaxis(planes, 0, -1)).view(meta["shuffled"][name]["dtype"])[..., 0]
            out[name] = np.moveaxis(raw, 0, -1)
    return out


def test_the_shipped_errors_are_stated_rounded_up_and_its_slopes_as_built():
    """Against the float32 file the shipped one was converted from (``scripts/ship_field_grid.py
    --resave`` records its git blob): every slope bit for bit, every error at or above its float32
    value by less than 2**-10 of it (0.1 %), none flushed to zero or infinite."""
    import subprocess

    from ..servers import ROOT

    source = GRID.meta["provenance"].get("converted_from")
    if source is None:
        pytest.skip("the shipped grid was written in this format, not converted")
    blob = subprocess.run(["git", "cat-file", "blob", source["git_blob"]], capture_output=True, cwd=ROOT, check=False)
    if blob.returncode != 0:
        pytest.skip(f"the file converted from (git blob {source['git_blob']}) is not in this checkout's history")
    before = _format_2_values(blob.stdout)
    columns = GRID.meta["columns"]
    is_error = np.array([c.endswith(("_err", "_interp")) for c in columns])
    assert sorted(before) == sorted(f"{k}/values" for k in GRID.meta["tables"])
    worst = 0.0
    for name, written in before.items():
        stated = GRID.arrays[name]
        assert stated.dtype == np.float32 and stated.shape == written.shape
        assert stated[..., ~is_error].tobytes() == written[..., ~is_error].tobytes(), name
        w, s = written[..., is_error].astype(np.float64), stated[..., is_error].astype(np.float64)
        finite = np.isfinite(w)
        assert np.array_equal(finite, np.isfinite(s)) and np.all(s[finite] >= w[finite]) and np.all(s[finite] > 0), name
        worst = max(worst, float(np.max(s[finite] / w[finite] - 1)))
    assert worst < 2.0**-10


def test_the_shipped_errors_are_positive_wherever_a_slope_is_stated():
    # The statistical errors are positive; the interpolation estimates (a row left out and predicted
    # from the others) are finite and not negative: one can be exactly zero where the spline reproduces
    # the row (K213 SCA 12 node 41, m = 27.25 in the 2026-12-04 build, the flux law's faint end).
    assert GRID.meta["format"] == gridfile.FORMAT
    columns = GRID.meta["columns"]
    is_error = np.array([c.endswith(("_err", "_interp")) for c in columns])
    is_statistical = np.array([c.endswith("_err") for c in columns])
    for key in sorted(GRID.meta["tables"]):
        values = GRID.arrays[f"{key}/values"]
        stated = np.isfinite(values[..., ~is_error]).all(axis=-1)
        assert np.all(np.isfinite(values[stated][:, is_error])), key
        assert np.all(values[stated][:, is_statistical] > 0), key
        assert np.all(values[stated][:, is_error & ~is_statistical] >= 0), key


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
    # The residual model the grid's nodes were built with (a grid built before the setting: the earlier one).
    model = grid_residual_model(GRID.conditions(band, sca)["settings"])
    fresh = experiment.slopes(config, magnitudes, beta0=settings.beta0, linearise_at=settings.linearise_at, residual_nl=model)
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


@pytest.mark.parametrize(("band", "sca"), [("W146", 6), ("H158", 18), ("R062", 3)])
def test_every_node_reads_as_its_own_cubic_spline(band, sca):
    """The grid evaluates all nodes at once (tables.splines.evaluate_stacked_cubics); each node's
    value must be scipy's CubicSpline of that node's own table (column / flux in flux, as
    nlpsf.slopes.tables reads a table), bit for bit, and NaN outside the node's magnitude range. The truth
    is built here from the file's arrays."""
    key = GRID.key(band, sca)
    flux = GRID.arrays[f"{key}/flux"]
    magnitudes = GRID.arrays[f"{key}/magnitude"]
    column = "bias_e1"
    index = GRID.meta["columns"].index(column)
    values = GRID.arrays[f"{key}/values"][..., index].astype(np.float64)
    draws = np.random.default_rng(7).uniform(np.nanmin(magnitudes) - 0.5, np.nanmax(magnitudes) + 0.5, 64)
    got = GRID.node_values(band, sca, column, draws)
    n = flux.shape[0]
    for j in range(n):
        for i in range(n):
            spline, (low, high), (top, top_m) = _node_spline(flux[j, i], magnitudes[j, i], values[j, i])
            target = top * 10 ** (-0.4 * (draws - top_m))
            inside = (target >= low * (1 - 1e-12)) & (target <= high * (1 + 1e-12))
            expected = np.where(inside, spline(np.clip(target, low, high)) * target, np.nan)
            assert inside.any() and (~inside).any()
            np.testing.assert_array_equal(got[j, i], expected)


def _node_spline(flux: np.ndarray, magnitudes: np.ndarray, values: np.ndarray):
    """The truth of one node, built here from the file's arrays: scipy's CubicSpline of its column /
    flux in flux (as ``nlpsf.slopes.tables`` reads a table), its flux range, and its brightest row's
    (flux, magnitude) that a magnitude's flux is reckoned from."""
    from scipy.interpolate import CubicSpline

    ok = np.isfinite(flux) & np.isfinite(values)
    order = np.argsort(flux[ok])
    f, q = flux[ok][order], (values[ok] / flux[ok])[order]
    brightest = int(np.nanargmax(flux))
    return CubicSpline(f, q), (f[0], f[-1]), (float(flux[brightest]), float(magnitudes[brightest]))


@pytest.mark.parametrize(("band", "sca"), [("W146", 6), ("H158", 18)])
def test_every_node_at_its_own_magnitudes_reads_as_its_own_cubic_spline(band, sca):
    """A magnitude solve reads every node at its own few magnitudes at once (``columns_at_nodes`` of
    n x n x k magnitudes): each value must be scipy's CubicSpline of that node's own table at that
    node's flux for that magnitude (from its brightest row, a scalar power), bit for bit, as one node
    read alone gives it."""
    key = GRID.key(band, sca)
    flux = GRID.arrays[f"{key}/flux"]
    magnitudes = GRID.arrays[f"{key}/magnitude"]
    columns = ("bias_size", "bias_e2_err")
    n, k = flux.shape[0], 3
    asked = np.random.default_rng(11).uniform(np.nanmin(magnitudes) - 0.3, np.nanmax(magnitudes) + 0.3, (n, n, k))
    got = GRID.columns_at_nodes(band, sca, columns, asked)
    assert all(g.shape == (n, n, k) for g in got)
    for c, column in enumerate(columns):
        values = GRID.arrays[f"{key}/values"][..., GRID.meta["columns"].index(column)].astype(np.float64)
        for j in range(n):
            for i in range(n):
                spline, (low, high), (top, top_m) = _node_spline(flux[j, i], magnitudes[j, i], values[j, i])
                target = np.array([top * 10 ** (-0.4 * (float(m) - top_m)) for m in asked[j, i]])  # scalar powers
                inside = (target >= low * (1 - 1e-12)) & (target <= high * (1 + 1e-12))
                expected = np.where(inside, spline(np.clip(target, low, high)) * target, np.nan)
                np.testing.assert_array_equal(got[c][j, i], expected)


def test_a_column_the_grid_does_not_hold_is_refused_whatever_was_read_before():
    from nlpsf.checks import InputError

    grid = fieldgrid.shipped_grid()
    for _ in range(2):  # before and after the held column is kept
        with pytest.raises(InputError, match="no column 'bias_nothing'"):
            grid.columns_node_values("H158", 7, ["bias_size", "bias_nothing"], 20.25)
        grid.columns_node_values("H158", 7, ["bias_size"], 20.25)
    with pytest.raises(InputError, match="no field grid for H158 SCA 19"):
        grid.node_values("H158", 19, "bias_size", 20.25)
