"""The shipped romanisim MA tables are romanisim's own.

Independent check: romanisim's ``parameters.read_pattern`` and ``read_time`` read from the installed
romanisim package (a test-only check; romanisim is not a dependency of nlpsf, and the test is skipped
when it is not installed). The shipped JSON files were converted from romanisim 0.15.0's wheel.
"""

import json

import pytest

from nlpsf.sim import ramps

ROMANISIM_TABLES = tuple(range(3, 18))


def _romanisim_parameters():
    """romanisim's parameters module (romanisim.models.parameters since 0.13; romanisim.parameters before)."""
    pytest.importorskip("romanisim", reason="romanisim not installed (test-only check)")
    try:
        from romanisim.models import parameters
    except ImportError:
        from romanisim import parameters
    return parameters


def _shipped(number: int) -> dict:
    return json.loads((ramps.shipped_table_dir() / f"romanisim-{number}.json").read_text())


def test_the_hlwas_table_is_romanisims_default_and_fits_its_exposure():
    table = ramps.load_ma_table("C2A_IMG_HLWAS")
    assert table.name == "romanisim-4"
    assert table.n_resultants == 9 and table.n_reads == 44
    # romanisim's exposure time for table 4 is its last read: 44 reads of 3.16247 s.
    assert table.duration_s == pytest.approx(44 * 3.16247, rel=1e-12)
    assert _shipped(4)["ma_table_number"] == 4


@pytest.mark.parametrize("number", ROMANISIM_TABLES)
def test_shipped_tables_equal_romanisims(number):
    parameters = _romanisim_parameters()
    if number not in parameters.read_pattern:
        pytest.fail(f"romanisim {getattr(parameters, '__version__', '')} has no MA table {number}")
    table = ramps.load_ma_table(f"romanisim-{number}")
    expected = tuple(tuple(r) for r in parameters.read_pattern[number])
    assert table.resultants == expected
    assert table.frame_time_s == parameters.read_time


def test_the_installed_romanisim_default_table_is_the_one_shipped_as_its_default():
    parameters = _romanisim_parameters()
    number = parameters.default_parameters_dictionary["exposure"]["ma_table_number"]
    assert number == 4
    assert ramps.load_ma_table("C2A_IMG_HLWAS").resultants == tuple(tuple(r) for r in parameters.read_pattern[number])
