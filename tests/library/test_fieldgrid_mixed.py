"""A field-grid file with grids of different sizes per (band, SCA) (``fieldgrid.merge_grids``): the
shipped file holds W146 on 5 x 5 nodes and the other bands on 3 x 3 (docs/field.md)."""

from __future__ import annotations

import numpy as np
import pytest
from astropy.table import Table

from nlpsf.slopes import fieldgrid, gridfile, tablebuild

CHEAP = tablebuild.TableSettings(realizations=2, faint_limit=18.0, magnitude_step=0.5)


@pytest.fixture(scope="module")
def grids(tmp_path_factory):
    directory = tmp_path_factory.mktemp("mixed")
    three = tablebuild.build_tables(directory / "g3", bands=["F184"], scas=[4, 5], settings=CHEAP, grid=3)
    five = tablebuild.build_tables(directory / "g5", bands=["F184"], scas=[5], settings=CHEAP, grid=5)
    base = fieldgrid.FieldGrid.load(tablebuild.merge_field_grid(three, directory / "base.npz", provenance={"built": "3"}))
    update = fieldgrid.FieldGrid.load(tablebuild.merge_field_grid(five, directory / "update.npz", provenance={"built": "5"}))
    merged = fieldgrid.merge_grids(base, update).save(directory / "merged.npz")
    return base, fieldgrid.FieldGrid.load(merged), three, five


@pytest.mark.slow
def test_each_entry_is_read_on_its_own_grid(grids):
    base, merged, _, five = grids
    assert merged.meta["tables"]["F184_04"]["grid"] == 3 and merged.meta["tables"]["F184_05"]["grid"] == 5
    assert merged.arrays["F184_05/values"].shape[:2] == (5, 5)
    # The entry not replaced is the base's, bit for bit, and keeps the base's provenance.
    for part in gridfile.ARRAY_PARTS:
        np.testing.assert_array_equal(merged.arrays[f"F184_04/{part}"], base.arrays[f"F184_04/{part}"])
    assert merged.conditions("F184", 4)["provenance"]["built"] == "3"
    assert merged.conditions("F184", 5)["provenance"]["built"] == "5"
    assert merged.meta["provenance"]["replaced_entries"] == ["F184_05"]
    # At each of the 25 nodes the 5 x 5 entry returns that node's own table (float32 storage).
    for path in five:
        table = Table.read(path, format="ascii.ecsv")
        row = len(table) // 2
        magnitude = float(table["magnitude"][row])
        value, _ = merged.slope("F184", 5, tuple(table.meta["position"]), "size", "bias", magnitude)
        assert float(value) == pytest.approx(float(table["bias_size"][row]), rel=3e-7)


@pytest.mark.slow
def test_the_denser_grid_shares_the_coarser_grids_nodes(grids):
    """A 5 x 5 build's every other node is the 3 x 3 node at the same position, bit for bit (the
    same settings and draws): densifying reuses, and checks, the coarser grid."""
    base, merged, _, _ = grids
    np.testing.assert_array_equal(merged.arrays["F184_05/values"][::2, ::2], base.arrays["F184_05/values"])
    np.testing.assert_array_equal(merged.arrays["F184_05/positions"][::2, ::2], base.arrays["F184_05/positions"])


def test_merging_refuses_grids_of_other_columns():
    meta = {"format": gridfile.FORMAT, "columns": ["bias_size", "bias_e1"], "value_dtype": "float32", "tables": {}}
    base = fieldgrid.FieldGrid(meta, {})
    with pytest.raises(fieldgrid.InputError):
        fieldgrid.merge_grids(base, fieldgrid.FieldGrid({**meta, "columns": ["bias_size"]}, {}))
    with pytest.raises(fieldgrid.InputError):
        fieldgrid.merge_grids(base, fieldgrid.FieldGrid({**meta, "value_dtype": "float64"}, {}))
