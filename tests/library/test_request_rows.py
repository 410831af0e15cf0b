"""A batch CSV's structure, read once for the CLI and the page: what a spreadsheet writes is read as
meant, and what would lose or swap a value is refused, naming the line."""

from __future__ import annotations

import csv
import io

import pytest

from nlpsf.checks import InputError
from nlpsf.request.rows import request_rows


def _written(rows: list[list[str]], **dialect) -> str:
    """``rows`` as Python's csv writer writes them (the reference for what a spreadsheet writes)."""
    out = io.StringIO()
    csv.writer(out, **dialect).writerows(rows)
    return out.getvalue()


def test_rows_are_the_cells_a_csv_writer_wrote_under_their_header():
    written = _written(
        [["band", "magnitude", "tolerance", "position"], ["H158", "18.3", "1e-3", "1,2"], ["J129", "", "1e-4", ""]]
    )
    assert request_rows(written) == [
        {"band": "H158", "magnitude": "18.3", "tolerance": "1e-3", "position": "1,2"},
        {"band": "J129", "magnitude": "", "tolerance": "1e-4", "position": ""},
    ]


def test_a_spreadsheets_byte_order_mark_padding_comments_and_blank_lines_are_not_data():
    plain = request_rows("band,magnitude,tolerance\nH158,18.3,1e-3\n")
    excel = "\ufeffband,magnitude,tolerance,,\r\n\r\n# a note\r\nH158,18.3,1e-3,,\r\n"
    assert request_rows(excel) == plain
    assert request_rows("band,magnitude,tolerance\nH158\n") == [{"band": "H158", "magnitude": "", "tolerance": ""}]


@pytest.mark.parametrize(
    ("text", "named"),
    [
        ("band,band,magnitude\nH158,J129,18\n", "band more than once"),
        ("band,magnitude\nH158,18\nH158,18,1e-3\n", "line 3 has 3 cells"),
        ("band,magnitude,,\nH158,18,,7\n", "line 2 has 4 cells"),
        ("band;magnitude;tolerance\nH158;18;1e-3\n", "separated by ';'"),
        ("band,,magnitude\nH158,,18\n", "empty column name"),
        ('band,magnitude\n"H158,18\n', "not CSV"),
        ("", "empty"),
        ("# nothing\n\n", "empty"),
        ("band,magnitude\n", "no requests"),
    ],
)
def test_a_file_that_would_lose_or_swap_a_value_is_refused_naming_where(text, named):
    with pytest.raises(InputError) as refused:
        request_rows(text)
    assert refused.value.argument == "csv" and named in refused.value.reason
