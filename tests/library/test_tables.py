"""The shipped slope tables: coverage, provenance, interpolation, the exact exposure/beta0 scaling."""

import json
import math

import numpy as np
import pytest

from nlpsf import roman
from nlpsf.sim import experiment
from nlpsf.slopes import tablebuild, tables


@pytest.fixture(scope="module")
def tableset():
    return tables.load_tables()


def fresh(table: tables.SlopeTable, magnitude: float, exptime: float | None = None, beta0: float | None = None):
    """A fresh simulation with the table's own settings (same centroids) at one magnitude."""
    s = table.settings
    config = experiment.SimulationConfig(
        band=table.band,
        sca=table.sca,
        realizations=s["realizations"],
        seed=s["seed"],
        oversampling=s["oversampling"],
        stamp=s["stamp"],
        exptime_s=exptime or s["exptime_s"],
        weight_cut_rho2=s["weight_cut_rho2"],
        method="linear",
        throughput=table.throughput,
        scene=experiment.scenes.SceneModel(position=table.position) if table.position else experiment.PAPER_SCENE,
    )
    return experiment.slopes(config, [magnitude], beta0=beta0 or s["beta0"])[0]


@pytest.fixture(scope="module")
def field_set():
    return tables.load_tables(str(tables.field_table_path()))


def test_every_band_and_sca_is_tabulated_from_saturation_to_beyond_26(tableset):
    assert tableset.bands == list(roman.BANDS)
    assert tableset.scas == list(range(1, 19))
    for table in tableset.tables.values():
        assert table.magnitudes[0] < table.saturation_magnitude - 1.0
        assert table.magnitudes[-1] >= 26.0
        assert np.all(np.diff(table.magnitudes) > 0)
        assert np.all(np.isfinite(table.columns["bias_size"]))
        assert np.all(table.columns["bias_size"] > 0)


def test_tables_carry_their_provenance(tableset):
    meta = tableset.meta
    assert meta["data_version"] == roman.DATA_VERSION
    for key in ("exptime_s", "beta0", "oversampling", "stamp", "realizations", "seed", "full_well_e", "weight_cut_rho2"):
        assert key in meta["settings"]
    assert meta["settings"]["exptime_s"] == 168.1 and meta["settings"]["beta0"] == 5e-7
    assert "code_version" in meta and "linear response" in meta["method"]
    # Built on the newest official per-SCA throughput, and every answer read from them says so.
    assert meta["settings"]["throughput"] == roman.DEFAULT_THROUGHPUT == "roman-2024"
    conditions = tables.curve("K213", 3, tables=tableset)["conditions"]
    assert conditions["throughput"] == "roman-2024"
    assert conditions["throughput_version"] == roman.THROUGHPUT_VERSIONS["roman-2024"]


def test_table_entries_are_the_simulation_they_claim(tableset):
    table = tableset.get("J129", 7)
    k = int(np.argmin(np.abs(table.magnitudes - 20.0)))
    result = fresh(table, float(table.magnitudes[k]))
    assert table.columns["bias_size"][k] == pytest.approx(result.bias["dR_over_R"].mean, rel=1e-9)
    assert table.columns["scatter_e2"][k] == pytest.approx(result.scatter["de2"]["value"], rel=1e-9)


def test_field_point_tables_cover_every_band_sca_and_corner(field_set, tableset):
    assert field_set.bands == list(roman.BANDS) and field_set.scas == list(range(1, 19)) and field_set.points == [1, 2, 3, 4]
    # Made with the centre tables' settings, on the same magnitude grid rule.
    assert field_set.meta["fingerprint"] == tableset.meta["fingerprint"]
    for sca in (1, 9, 18):
        for point in field_set.points:
            table = field_set.get("H158", sca, point)
            assert table.field_point == point and table.position == roman.field_points(sca)[point]
            assert field_set.at_point(point).get("H158", sca) is table


def test_field_point_table_entries_are_simulations_at_their_corner(field_set, tableset):
    table = field_set.get("J129", 7, 3)
    k = int(np.argmin(np.abs(table.magnitudes - 20.0)))
    result = fresh(table, float(table.magnitudes[k]))
    assert table.columns["bias_e1"][k] == pytest.approx(result.bias["de1"].mean, rel=1e-9)
    assert table.columns["scatter_size"][k] == pytest.approx(result.scatter["dR_over_R"]["value"], rel=1e-9)
    # The corner is not the centre: its e slopes differ by far more than their errors.
    centre = tableset.get("J129", 7)
    corner_e, corner_err, _ = table.slope("e", "bias", 20.0)
    centre_e, centre_err, _ = centre.slope("e", "bias", 20.0)
    assert abs(corner_e[0] - centre_e[0]) > 10 * math.hypot(corner_err[0], centre_err[0])


@pytest.mark.parametrize(
    ("band", "sca", "magnitude"), [("H158", 18, 18.31), ("Y106", 4, 19.83), ("F184", 11, 22.71), ("W146", 16, 19.66)]
)
def test_interpolated_slopes_agree_with_fresh_simulations_within_their_stated_error(tableset, band, sca, magnitude):
    table = tableset.get(band, sca)
    result = fresh(table, magnitude)
    for metric, name in (("size", "dR_over_R"), ("e1", "de1"), ("e2", "de2")):
        value, error, region = table.lookup(metric, "bias", magnitude)
        assert region[0] == 0
        assert abs(value[0] - result.bias[name].mean) <= error[0]
        value, error, _ = table.lookup(metric, "scatter", magnitude)
        assert abs(value[0] - result.scatter[name]["value"]) <= error[0]


def test_interpolation_error_is_below_the_statistical_error(tableset):
    # Where the stars are usable (fainter than saturation) the grid is fine enough that the cubic
    # interpolation adds less than the centroid-sampling error of the slopes themselves.
    # (The estimate itself is checked against fresh simulations between grid points above.)
    ratios = []
    for table in tableset.tables.values():
        usable = table.magnitudes >= table.saturation_magnitude
        for mode in tables.MODES:
            for metric in ("size", "e1", "e2"):
                name = f"{mode}_{metric}"
                ratios.append(np.max(table.columns[f"{name}_interp"][usable] / table.columns[f"{name}_err"][usable]))
    assert max(ratios) < 0.5


def test_other_exposures_are_an_exact_shift_of_the_magnitude_axis(tableset):
    table = tableset.get("H158", 18)
    result = fresh(table, 19.4, exptime=300.0)
    value, error, _ = table.slope("size", "bias", 19.4, exptime_s=300.0)
    assert abs(value[0] - result.bias["dR_over_R"].mean) <= error[0]
    # Doubling the exposure doubles the flux: the same slope 0.75 mag fainter.
    doubled = table.slope("size", "bias", 20.0 + 2.5 * math.log10(2), exptime_s=2 * 168.1)[0][0]
    assert doubled == pytest.approx(table.slope("size", "bias", 20.0)[0][0], rel=1e-12)


def test_other_beta0_follow_from_the_beta_flux_product(tableset):
    table = tableset.get("H158", 18)
    result = fresh(table, 19.7, beta0=2e-6)
    value, error, _ = table.slope("size", "bias", 19.7, beta0=2e-6)
    assert abs(value[0] - result.bias["dR_over_R"].mean) <= error[0]
    scatter, scatter_error, _ = table.slope("e1", "scatter", 19.7, beta0=2e-6)
    assert abs(scatter[0] - result.scatter["de1"]["value"]) <= scatter_error[0]


def test_full_well_moves_only_the_saturation_magnitude(tableset):
    table = tableset.get("Z087", 2)
    assert table.saturation(full_well_e=2.2e5) == pytest.approx(table.saturation() - 2.5 * math.log10(2), abs=1e-9)
    assert table.saturation(exptime_s=2 * 168.1) == pytest.approx(table.saturation() + 2.5 * math.log10(2), abs=1e-9)


def test_faint_extrapolation_is_proportional_to_flux(tableset):
    table = tableset.get("K213", 9)
    inside = table.lookup("size", "bias", 27.5)[0][0]
    beyond, _, region = table.lookup("size", "bias", 30.0)
    assert region[0] == 1
    assert beyond[0] == pytest.approx(inside * 10 ** (-0.4 * 2.5), rel=1e-3)


def test_brighter_than_the_grid_has_no_value(tableset):
    table = tableset.get("H158", 18)
    value, error, region = table.lookup("size", "bias", table.magnitudes[0] - 0.5)
    assert region[0] == -1 and math.isnan(value[0]) and math.isnan(error[0])


def test_power_law_fits_describe_the_paper_range(tableset):
    for fit in tables.powerlaw_fits(bands=["Y106", "J129", "H158", "F184"], scas=[18], tables=tableset):
        # The nonlinearity bends the curves near saturation: a power law is good to a few per cent.
        assert fit["max_relative_residual"] < 0.04
        # Slopes scale with the flux (-0.4) plus a small nonlinear steepening, as in the paper.
        assert -0.42 < fit["B"] < -0.399
    # The brightest band bends most.
    wide = tables.powerlaw_fit(tableset.get("W146", 18))
    assert wide["max_relative_residual"] > max(
        f["max_relative_residual"] for f in tables.powerlaw_fits(bands=["F184"], scas=[18])
    )


def test_table2_comparison_splits_the_change_into_throughput_and_optics(tableset):
    rows = tables.table2_comparison(tables=tableset)
    assert {(r["band"], r["mode"]) for r in rows} == {(b, m) for b in ("Y106", "J129", "H158", "F184") for m in tables.MODES}
    for r in rows:
        assert r["A_ratio"] == pytest.approx(r["throughput_ratio"] * r["optics_ratio"], rel=1e-12)
        assert abs(r["B_ours"] - r["B_paper"]) < 0.01
    markdown = tables.table2_markdown()
    assert markdown.count("\n") == 1 + len(rows)


def test_paper_data_is_shipped():
    data = tables.paper_data()
    assert data["table2_powerlaw"]["bias"]["H158"] == [4668, -0.4069]
    assert len(data["magnitudes"]) == 5


def test_build_is_resumable_and_merges(tmp_path):
    settings = tablebuild.TableSettings(realizations=4, faint_limit=19.5)
    seen = []
    first = tablebuild.build_tables(
        tmp_path, bands=["H158"], scas=[3, 4], settings=settings, progress=lambda d, t, m: seen.append(m)
    )
    assert len(first) == 2 and seen[0] == "starting"
    # Interrupted half way: one table lost, and a half-written temporary left behind.
    first[0].unlink()
    (tmp_path / "slopes_H158_SCA04.tmp").write_text("garbage")
    seen.clear()
    second = tablebuild.build_tables(
        tmp_path, bands=["H158"], scas=[3, 4], settings=settings, progress=lambda d, t, m: seen.append(m)
    )
    assert seen[0] == "resumed" and len(seen) == 2  # only the lost table was recomputed
    merged = tablebuild.merge_tables(second, tmp_path / "merged.ecsv")
    assert set(merged["sca"]) == {3, 4}
    loaded = tables.load_tables(str(tmp_path / "merged.ecsv"))
    assert loaded.get("H158", 3).magnitudes[-1] == pytest.approx(19.5)


def test_build_refuses_to_merge_tables_made_with_different_settings(tmp_path):
    a = tablebuild.build_tables(
        tmp_path / "a", bands=["Y106"], scas=[1], settings=tablebuild.TableSettings(realizations=3, faint_limit=19)
    )
    b = tablebuild.build_tables(
        tmp_path / "b", bands=["Y106"], scas=[2], settings=tablebuild.TableSettings(realizations=4, faint_limit=19)
    )
    with pytest.raises(ValueError, match="different settings"):
        tablebuild.merge_tables(a + b, tmp_path / "m.ecsv")


@pytest.mark.slow
def test_build_fans_out_over_dask(tmp_path):
    pytest.importorskip("dask.distributed")
    settings = tablebuild.TableSettings(realizations=3, faint_limit=19.0)
    paths = tablebuild.build_tables(tmp_path, bands=["F184"], scas=[5, 6], settings=settings, workers=2, dask_address="local")
    assert sorted(p.name for p in paths) == ["slopes_F184_SCA05.ecsv", "slopes_F184_SCA06.ecsv"]
    assert tablebuild.merge_tables(paths, tmp_path / "m.ecsv")["band"][0] == "F184"


#: The ECSVs the shipped runtime files were derived from: sources in the repository, not installed.
SOURCES = {"centre": "slopes.ecsv", "field": "field_slopes.ecsv.gz"}


def _source(which: str):
    from astropy.table import Table

    runtime = tables.shipped_table_path() if which == "centre" else tables.field_table_path()
    return runtime, Table.read(runtime.with_name(SOURCES[which]), format="ascii.ecsv")


@pytest.mark.parametrize("which", ["centre", "field"])
def test_the_runtime_file_holds_its_sources_rows_and_scipys_splines(which):
    """Every table of the shipped runtime file holds its source ECSV's rows (read by astropy) and, per
    slope column, the breakpoints and coefficients of the public CubicSpline built here from the
    ECSV's points (slope / flux in flux), bit for bit; and evaluating them gives that spline's values."""
    from scipy.interpolate import CubicSpline

    runtime, source = _source(which)
    read = tables.load_tables(str(runtime))
    assert read.meta["fingerprint"] == source.meta["fingerprint"] and read.meta["source"] == runtime.name
    keys = ["band", "sca"] + (["field_point"] if which == "field" else [])
    checked = 0
    for group in source.group_by(keys).groups:
        key = tuple(group[k][0] for k in keys)
        table = read.get(str(key[0]), int(key[1]), *(int(k) for k in key[2:]))
        group.sort("flux_electrons")
        flux = np.asarray(group["flux_electrons"], dtype=np.float64)
        np.testing.assert_array_equal(table.flux_electrons[::-1], flux)
        np.testing.assert_array_equal(table.magnitudes[::-1], group["magnitude"])
        for name in tables.SLOPE_COLUMNS:
            values = np.asarray(group[name], dtype=np.float64)
            np.testing.assert_array_equal(table.columns[name][::-1], values)
            for suffix in ("_err", "_interp"):
                np.testing.assert_array_equal(table.columns[name + suffix][::-1], group[name + suffix])
            truth = CubicSpline(flux, values / flux)
            breaks, coefficients = table.splines[name]
            assert np.array_equal(breaks, truth.x) and np.array_equal(coefficients, truth.c), (key, name)
            if checked % 37 == 0:
                probe = np.geomspace(flux[0], flux[-1], 301)
                _, evaluate, _, _ = table._interpolant(name)
                np.testing.assert_allclose(evaluate(probe), truth(probe), rtol=1e-12, atol=1e-300)
            checked += 1
    assert checked == len(read.tables) * len(tables.SLOPE_COLUMNS)


@pytest.mark.parametrize("which", ["centre", "field"])
def test_the_export_gives_the_source_ecsv_back_byte_for_byte(which, tmp_path):
    """``nlpsf tables export`` writes the runtime file as the ECSV it was derived from: the same rows,
    byte for byte, and the same header (types, units and metadata), so a user of the wheel, which
    ships the runtime file alone, gets the readable tables. The header's YAML is compared as read:
    astropy's writer wraps its lines differently from one version to another (6.1, the declared
    minimum, against the one that wrote the source); with the writing version the file is the same
    bytes."""
    import gzip

    from astropy.table import Table

    from nlpsf.cli import main

    runtime, _ = _source(which)
    out = tmp_path / SOURCES[which]
    assert main(["tables", "export", "--output", str(out), *(["--field"] if which == "field" else [])]) == 0
    source = runtime.with_name(SOURCES[which])
    texts = [gzip.decompress(p.read_bytes()) if which == "field" else p.read_bytes() for p in (out, source)]
    rows = [[line for line in text.splitlines() if not line.startswith(b"#")] for text in texts]
    assert rows[0] == rows[1]
    exported, original = (Table.read(p, format="ascii.ecsv") for p in (out, source))
    # As plain dicts: the order of keys the YAML reader hands back is no part of the metadata.
    assert json.loads(json.dumps(exported.meta)) == json.loads(json.dumps(original.meta))
    assert [(c.name, c.dtype, c.unit, c.description) for c in exported.itercols()] == [
        (c.name, c.dtype, c.unit, c.description) for c in original.itercols()
    ]


def test_a_table_file_is_read_through_its_runtime_file_or_its_ecsv(tmp_path):
    """A table file a user has (an ECSV and the runtime file written beside it) is read through the
    runtime file while its fingerprint matches the ECSV's, and from the ECSV when it does not: the
    same numbers either way, the splines then built from the ECSV."""
    import shutil

    runtime, _ = _source("centre")
    copy = tmp_path / "slopes.ecsv"
    shutil.copy(runtime.with_name("slopes.ecsv"), copy)
    shutil.copy(runtime, tables.companion_path(copy))
    fast = tables.load_tables(str(copy)).get("J129", 4)
    assert fast.splines
    stale = tmp_path / "stale" / "slopes.ecsv"  # another file (load_tables caches by path)
    stale.parent.mkdir()
    stale.write_text(copy.read_text().replace(tables.ecsv_fingerprint(copy), "feedfacefeedface", 1))
    shutil.copy(runtime, tables.companion_path(stale))
    loaded = tables.load_tables(str(stale))
    assert loaded.meta["fingerprint"] == "feedfacefeedface"
    slow = loaded.get("J129", 4)
    assert not slow.splines
    magnitudes = np.linspace(slow.magnitudes[0], slow.magnitudes[-1], 57)
    for metric in ("size", "e1", "e2"):
        np.testing.assert_array_equal(fast.slope(metric, "bias", magnitudes)[0], slow.slope(metric, "bias", magnitudes)[0])


def test_byte_shuffling_is_lossless():
    from nlpsf.slopes.tables.storage import shuffle_bytes, unshuffle_bytes

    values = np.random.default_rng(3).normal(size=(7, 5)) * 10.0 ** np.arange(5)
    values[2, 3] = np.nan
    for dtype in (np.float64, np.float32):
        packed = shuffle_bytes(values.astype(dtype))
        assert packed.dtype == np.uint8 and packed.shape == (np.dtype(dtype).itemsize, 7, 5)
        restored = unshuffle_bytes(packed, np.dtype(dtype).str)
        assert restored.dtype == dtype
        np.testing.assert_array_equal(restored, values.astype(dtype))
