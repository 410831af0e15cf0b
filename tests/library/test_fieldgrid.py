"""Field-grid tables (``nlpsf.slopes.fieldgrid``, ``tablebuild.build_tables(grid=n)``): interpolation across
the SCA, the packed float32 file, resuming, and the interpolation error against fresh simulations."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.table import Table

from nlpsf.checks import InputError
from nlpsf.sim import experiment
from nlpsf.slopes import fieldgrid, gridfile, tablebuild

#: A cheap table build (the paper's scene at each node, few centroids, a short magnitude grid):
#: these tests are about the grid machinery, not the slopes' statistics.
CHEAP = tablebuild.TableSettings(realizations=3, faint_limit=19.0, magnitude_step=0.5)


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    directory = tmp_path_factory.mktemp("grid")
    messages: list[str] = []
    paths = tablebuild.build_tables(
        directory, bands=["H158"], scas=[18], settings=CHEAP, grid=3, progress=lambda d, t, m: messages.append(m)
    )
    return directory, paths, messages


def test_grid_nodes_span_the_sca_and_include_its_centre():
    axis = fieldgrid.grid_axis(3)
    assert axis[0] == 1.0 and axis[-1] == 4088.0 and axis[1] == pytest.approx(2044.5)
    assert len(fieldgrid.grid_positions(5)) == 25
    with pytest.raises(InputError):
        fieldgrid.check_grid(4)


@pytest.mark.parametrize("scheme", fieldgrid.SCHEMES)
def test_interpolation_at_a_node_is_the_node_value(scheme):
    rng = np.random.default_rng(1)
    values = rng.normal(size=(5, 5, 3))
    for i, j, position in fieldgrid.grid_positions(5):
        np.testing.assert_allclose(fieldgrid.interpolate(values, position, scheme), values[j, i], rtol=1e-12, atol=1e-12)


def test_schemes_are_exact_for_the_polynomials_they_span():
    """Bilinear reproduces a bilinear field, Lagrange on 3 x 3 a biquadratic one (analytic cases)."""
    axis = fieldgrid.grid_axis(3)
    x, y = np.meshgrid(axis, axis)  # [j, i]
    bilinear = 2.0 + 3e-4 * x - 1e-4 * y + 5e-8 * x * y
    biquadratic = bilinear + 7e-8 * x**2 - 2e-8 * y**2 + 1e-11 * x**2 * y**2
    for position in [(37.0, 3999.0), (1500.5, 2222.0), (4000.0, 12.0)]:
        px, py = position
        expected_bilinear = 2.0 + 3e-4 * px - 1e-4 * py + 5e-8 * px * py
        expected = expected_bilinear + 7e-8 * px**2 - 2e-8 * py**2 + 1e-11 * px**2 * py**2
        assert fieldgrid.interpolate(bilinear, position, "bilinear") == pytest.approx(expected_bilinear, rel=1e-12)
        assert fieldgrid.interpolate(biquadratic, position, "lagrange") == pytest.approx(expected, rel=1e-12)


def test_positions_off_the_sca_are_refused():
    with pytest.raises(InputError):
        fieldgrid.weights(3, (0.0, 100.0))
    with pytest.raises(InputError):
        fieldgrid.weights(3, (100.0, 100.0), scheme="cubic")


def test_the_packed_file_at_a_node_equals_the_node_table(built, tmp_path):
    _, paths, _ = built
    packed = tablebuild.merge_field_grid(paths, tmp_path / "grid.npz")
    grid = fieldgrid.FieldGrid.load(packed)
    assert grid.keys() == ["H158_18"]
    for path in paths:
        table = Table.read(path, format="ascii.ecsv")
        i, j = table.meta["grid_node"][1:]
        for row in (2, len(table) - 2):
            magnitude = float(table["magnitude"][row])
            for column in ("bias_size", "bias_e1", "scatter_e2"):
                exact = float(table[column][row])
                nodes = grid.node_values("H158", 18, column, magnitude)
                # float32 storage: 6e-8 relative; the spline through the nodes returns the node itself.
                assert nodes[j, i] == pytest.approx(exact, rel=3e-7)
                for scheme in fieldgrid.SCHEMES:
                    at = grid.column_value("H158", 18, tuple(table.meta["position"]), magnitude, column, scheme)
                    assert at == pytest.approx(exact, rel=3e-7)


def test_a_rebuild_skips_the_finished_tables_and_redoes_a_missing_one(built):
    directory, paths, messages = built
    assert len(paths) == 9 and messages[0] == "starting"
    before = {p.name: p.stat().st_mtime_ns for p in paths}
    again: list[str] = []
    tablebuild.build_tables(
        directory, bands=["H158"], scas=[18], settings=CHEAP, grid=3, progress=lambda d, t, m: again.append(m)
    )
    assert again == ["resumed"]  # nothing recomputed
    assert {p.name: p.stat().st_mtime_ns for p in paths} == before
    missing = sorted(paths)[4]
    missing.unlink()
    redo: list[str] = []
    tablebuild.build_tables(directory, bands=["H158"], scas=[18], settings=CHEAP, grid=3, progress=lambda d, t, m: redo.append(m))
    assert redo[0] == "resumed" and len(redo) == 2 and "node" in redo[1]
    assert missing.exists()


def test_the_candidate_roman_scene_combines_ramp_ipc_and_background():
    settings = tablebuild.TableSettings.roman(realizations=2)
    config = settings.config("H158", 18, position=(100.0, 3900.0))
    on = config.scene.effects_on()
    assert all(on[k] for k in ("position", "sed", "jitter", "charge_diffusion", "ipc", "background"))
    assert config.ramp is not None and config.ramp.fit == "optimal" and config.pupil_scale == "official"
    assert config.exptime_s == pytest.approx(config.ramp.table.duration_s)
    # The paper tables keep their fingerprint (the new settings enter only when not at default).
    assert settings.fingerprint() != tablebuild.TableSettings(realizations=2).fingerprint()


#: Worst |relative error| of the 3 x 3 Lagrange interpolation measured by
#: scripts/field_interpolation_error.py (H158, W146, F184 x SCA 1, 9, 18, 4 random positions each,
#: m = 17-22 where no resultant saturates, 32 centroids; docs/field.md): 0.015 %, 1.02 %, 2.44 %, rounded up.
MEASURED_BOUND = {"dR_over_R": 2e-4, "de1": 1.1e-2, "de2": 2.5e-2}


def test_interpolated_slopes_match_a_fresh_simulation_off_the_grid():
    """The 3 x 3 grid of the Roman scene, interpolated to an off-grid position, against a fresh
    simulation there with the same centroid draws (so the difference is the interpolation's)."""
    settings = tablebuild.TableSettings.roman(realizations=8)
    magnitude = [20.0]

    def slopes_at(position):
        result = experiment.slopes(settings.config("H158", 9, position=position), magnitude, beta0=settings.beta0)[0]
        return np.array([result.bias[m].mean for m in MEASURED_BOUND])

    nodes = np.array([[slopes_at((float(x), float(y))) for x in fieldgrid.grid_axis(3)] for y in fieldgrid.grid_axis(3)])
    position = (3311.0, 757.0)
    fresh = slopes_at(position)
    interpolated = fieldgrid.interpolate(nodes, position, "lagrange")
    for k, metric in enumerate(MEASURED_BOUND):
        assert abs(interpolated[k] / fresh[k] - 1) <= MEASURED_BOUND[metric], metric


def test_the_cli_builds_and_packs_a_field_grid(tmp_path, capsys):
    from nlpsf.cli import main

    argv = ["tables", "build", "--band", "H158", "--sca", "18", "--realizations", "2", "--faint-limit", "18.5"]
    argv += ["--step", "0.5", "--quiet", "--output", str(tmp_path / "nodes")]
    assert main([*argv, "--grid", "4"]) == 2
    assert "grid" in capsys.readouterr().err
    assert main([*argv, "--grid", "3", "--merge-to", str(tmp_path / "grid.npz")]) == 0
    grid = fieldgrid.FieldGrid.load(tmp_path / "grid.npz")
    assert grid.meta["tables"]["H158_18"]["grid"] == 3 and grid.meta["value_dtype"] == "float32"
    assert len(list((tmp_path / "nodes").glob("*_G3_*.ecsv"))) == 9


def _malloc_trim_threshold():
    import os

    return os.environ.get("MALLOC_TRIM_THRESHOLD_")


def test_local_dask_workers_keep_glibcs_dynamic_mmap_threshold(monkeypatch):
    """dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 in its workers, which made a Roman-scene table
    cost 3 x the CPU there (docs/field.md); ``cluster.dask_client`` unsets it for a local cluster."""
    pytest.importorskip("dask.distributed")
    from nlpsf.sim import cluster

    monkeypatch.delenv("MALLOC_TRIM_THRESHOLD_", raising=False)
    with cluster.dask_client("local", workers=1) as client:
        assert set(client.run(_malloc_trim_threshold).values()) == {None}


def _write_format_2(path, arrays: dict, columns: list[str]) -> None:
    """A nlpsf-field-grid-2 file written here, not by ``fieldgrid``: every array float, its bytes
    regrouped by significance (the values' columns first), the metadata as JSON bytes."""
    import json

    stored, shuffled = {}, {}
    for name, array in arrays.items():
        columns_first = name.endswith("/values")
        a = np.ascontiguousarray(np.moveaxis(array, -1, 0) if columns_first else array)
        stored[name] = np.ascontiguousarray(np.moveaxis(a.view(np.uint8).reshape(*a.shape, a.itemsize), -1, 0))
        shuffled[name] = {"dtype": array.dtype.str, "columns_first": columns_first}
    meta = {"format": "nlpsf-field-grid-2", "columns": columns, "tables": {}, "value_dtype": "float32", "shuffled": shuffled}
    stored["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    np.savez_compressed(path, **stored)


def test_a_format_2_file_rewritten_keeps_its_slopes_and_only_rounds_its_errors_up(tmp_path):
    """Errors over the shipped file's span (1e-9 to 1e3 in slope units, 39 binades, wider than
    float16's 30) and slopes to 1e5, with NaN padding and an exact zero: read back from the -3 file,
    every slope is the float32 written, bit for bit, and every error at or above the one written,
    by less than 2**-10 of it (float16's mantissa), never flushed to zero nor made infinite."""
    columns = gridfile._slope_columns()
    is_error = np.array([c.endswith(("_err", "_interp")) for c in columns])
    rng = np.random.default_rng(17)
    shape = (5, 5, 40, len(columns))
    values = np.where(
        is_error, 10 ** rng.uniform(-9, 3, size=shape), rng.choice([-1, 1], size=shape) * 10 ** rng.uniform(-6, 5, size=shape)
    ).astype(np.float32)
    values[:, :, -3:] = np.nan  # a shorter magnitude grid at every node
    values[0, 0, 0, is_error] = 0.0
    values[1, 0, 0, is_error] = np.float32(1.4787224e-09)  # the shipped file's smallest error
    values[2, 0, 0, is_error] = np.float32(6.1e-18)  # a rebuild's: 67 binades below its largest
    arrays = {"H158_01/values": values, "H158_01/flux": rng.uniform(1, 2, size=shape[:3])}
    arrays["H158_01/positions"] = np.ones((5, 5, 2))
    _write_format_2(tmp_path / "two.npz", arrays, columns)

    read = fieldgrid.FieldGrid.load(tmp_path / "two.npz")
    three = read.save(tmp_path / "three.npz")
    back = fieldgrid.FieldGrid.load(three).arrays
    assert back["H158_01/values"].dtype == np.float32 and back["H158_01/values"].shape == shape
    for name in ("H158_01/flux", "H158_01/positions"):
        assert back[name].tobytes() == arrays[name].tobytes()
    slopes_written, slopes_read = values[..., ~is_error], back["H158_01/values"][..., ~is_error]
    assert slopes_read.tobytes() == slopes_written.tobytes()  # bit for bit, NaNs included
    written = values[..., is_error].astype(np.float64)
    stated = back["H158_01/values"][..., is_error].astype(np.float64)
    finite = np.isfinite(written)
    assert np.array_equal(finite, np.isfinite(stated))
    assert np.all(stated[finite] >= written[finite])
    positive = finite & (written > 0)
    assert np.all(stated[positive] > 0) and np.all(stated[finite & (written == 0)] == 0)
    growth = stated[positive] / written[positive] - 1
    assert growth.max() < 2.0**-10 and growth.max() > 2.0**-11  # the bound is reached, not loose
    assert three.stat().st_size < 0.75 * (tmp_path / "two.npz").stat().st_size
    # Re-saving a -3 file changes nothing more (its errors are on the code's grid already).
    again = fieldgrid.FieldGrid.load(fieldgrid.FieldGrid(fieldgrid.FieldGrid.load(three).meta, back).save(tmp_path / "again.npz"))
    assert again.arrays["H158_01/values"].tobytes() == back["H158_01/values"].tobytes()


def test_packing_refuses_errors_it_cannot_state_and_keeps_the_tiny_ones_exactly():
    with pytest.raises(InputError):
        gridfile.pack_errors(np.array([1.0, np.inf], dtype=np.float32))
    with pytest.raises(InputError):
        gridfile.pack_errors(np.array([1.0, -1e-3], dtype=np.float32))
    # 1 + 2**-23 (one float32 step above 1) is stated as 1 + 2**-10, the next code up.
    codes, offset, outliers = gridfile.pack_errors(np.array([1.0, np.nextafter(np.float32(1), np.float32(2))], dtype=np.float32))
    assert gridfile.unpack_errors(codes, offset, outliers).tolist() == [1.0, 1.0 + 2.0**-10] and outliers.size == 0
    # 70 binades: more than the codes' 63 below the largest; the error below them is kept as it is.
    errors = np.array([2.0**-66 * 1.2345, 3.0, 10.0, 0.0, np.nan], dtype=np.float32)
    codes, offset, outliers = gridfile.pack_errors(errors)
    back = gridfile.unpack_errors(codes, offset, outliers)
    assert outliers.tolist() == [errors[0]] and back[0] == errors[0] and back[1:3].tolist() == [3.0, 10.0]
    assert back[3] == 0.0 and np.isnan(back[4])
