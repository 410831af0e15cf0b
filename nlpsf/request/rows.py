"""Solve requests as rows of a CSV (the CLI's ``solve --batch`` file, the page's batch upload): the
file's structure is checked here, once, for both; each cell stays text for the caller's request to read.

A spreadsheet's CSV is read as it is usually written: a UTF-8 byte-order mark (Excel's "CSV UTF-8")
is not part of the first column's name, blank lines and ``#`` comment lines are skipped, and empty
columns after the last named one are ignored. What would silently lose or swap a value is refused,
naming the line: a column named twice, a cell beyond the named columns, a file separated by ``;``.
"""

from __future__ import annotations

import csv
import io

from nlpsf.checks import InputError

#: The argument every refusal of the file's structure names.
ARGUMENT = "csv"


def request_rows(text: str) -> list[dict[str, str]]:
    """Every request row of the CSV ``text`` as {column: cell text ("" where empty or missing)},
    in the header's order. Raises ``InputError`` (argument ``csv``) where the file's structure is
    not one request a row under one header of distinct names."""
    reader = csv.reader(io.StringIO(text.removeprefix("\ufeff")), strict=True)
    header: list[str] | None = None
    rows: list[dict[str, str]] = []
    try:
        for cells in reader:
            if not any(cell.strip() for cell in cells) or cells[0].lstrip().startswith("#"):
                continue
            if header is None:
                header = _header(cells)
                continue
            if any(cell.strip() for cell in cells[len(header) :]):
                raise InputError(
                    ARGUMENT,
                    f"line {reader.line_num} has {len(cells)} cells where the header names {len(header)} columns "
                    f"({', '.join(header)}): a cell beyond them would be lost (quote a cell that holds a comma)",
                )
            rows.append({name: (cells[k] if k < len(cells) else "").strip() for k, name in enumerate(header)})
    except csv.Error as error:
        raise InputError(ARGUMENT, f"line {reader.line_num} is not CSV: {error}") from None
    if header is None:
        raise InputError(ARGUMENT, "the CSV is empty: give a header row (e.g. band,tolerance,magnitude) and one row per request")
    if not rows:
        raise InputError(ARGUMENT, "the CSV has a header but no requests")
    return rows


def _header(cells: list[str]) -> list[str]:
    """The header row's column names: trailing empty ones (a spreadsheet's padding) dropped."""
    names = [cell.strip() for cell in cells]
    while names and not names[-1]:
        names.pop()
    if len(names) == 1 and ";" in names[0]:
        raise InputError(
            ARGUMENT,
            f"the header row {names[0]!r} is separated by ';': give comma-separated values (numbers with a decimal point)",
        )
    if any(not name for name in names):
        raise InputError(ARGUMENT, "the header row has an empty column name")
    twice = sorted({name for name in names if names.count(name) > 1})
    if twice:
        raise InputError(ARGUMENT, f"the header names {', '.join(twice)} more than once: which value is meant?")
    return names
