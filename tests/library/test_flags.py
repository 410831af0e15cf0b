"""Flags are codes with a message: every code has one template, messages are built from it, and a
flag survives pickling (jobs, dask) and serialisation with its code."""

import ast
import pickle
import re
import string
from pathlib import Path

import pytest

from nlpsf import flags, solve
from nlpsf.flags import CATALOGUE, Flag, FlagCode


def test_every_code_has_a_template_quoting_exactly_its_values():
    assert set(CATALOGUE) == set(FlagCode)
    for code, spec in CATALOGUE.items():
        fields = {name for _, name, _, _ in string.Formatter().parse(spec.template) if name}
        assert fields == set(spec.quotes), code
        assert spec.meaning.endswith("."), code


def test_a_flag_is_its_message_with_code_and_values():
    flag = flags.make(FlagCode.STAR_SATURATED, magnitude=16.5, m_sat=17.98)
    assert isinstance(flag, str) and flag.code is FlagCode.STAR_SATURATED
    assert "m=16.5" in flag and "m=17.98" in flag  # the numbers quoted, formatted by the template
    assert flag.values == {"magnitude": 16.5, "m_sat": 17.98}
    again = pickle.loads(pickle.dumps(flag))
    assert again == flag and again.code is flag.code and again.values == flag.values
    assert flags.codes([flag, "a plain string"]) == ["star_saturated", None]
    assert flag.to_dict()["code"] == "star_saturated"


def test_a_number_that_is_not_finite_reads_as_a_word():
    # JSON has no infinity: a precision no slope limits is null in the answer, and its flag says
    # "unbounded", not Python's "inf" (which a reader may take for a bug); NaN says "undefined".
    flag = flags.make(FlagCode.STAR_SATURATED, magnitude=float("inf"), m_sat=float("nan"))
    assert "m=unbounded" in flag and "m=undefined" in flag and flag.values["m_sat"] != flag.values["m_sat"]
    # An answer whose least demanding node needs no precision (its e2 slope consistent with zero):
    from nlpsf import SolveRequest, answer

    solution = answer(SolveRequest.from_json({"band": "J129", "magnitude": 30, "tolerance": 1e-4, "metric": "e2"}))
    assert solution.conditions["sca_range"]["least_demanding"]["precision"] is None
    words = " ".join(solution.flags)
    assert "unbounded" in words and not re.search(r"\b(inf|nan)\b", words, re.IGNORECASE)


def test_a_flag_needs_every_value_its_message_quotes():
    with pytest.raises(TypeError, match="m_sat"):
        Flag(FlagCode.STAR_SATURATED, magnitude=16.5)


def test_catalogue_lists_every_code():
    assert {entry["code"] for entry in flags.catalogue()} == {c.value for c in FlagCode}


def _quoted_text(path: Path) -> list[str]:
    """The string literals a test file holds, without its docstrings (which describe, and may quote)."""
    tree = ast.parse(path.read_text())
    docstrings = {id(node.value) for node in ast.walk(tree) if isinstance(node, ast.Expr)}
    return [
        node.value
        for node in ast.walk(tree)
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docstrings
    ]


def test_tests_assert_codes_not_english():
    # The messages are the catalogue's to reword: no library or service test quotes any stretch of
    # their prose (more than 15 characters between the values a template quotes).
    tests = Path(__file__).resolve().parents[1]
    prose = {
        piece.strip()
        for spec in CATALOGUE.values()
        for part in re.split(r"\{[^}]*\}", spec.template)
        for piece in re.split(r"[:;,()]", part)
        if len(piece.strip()) > 15
    }
    assert len(prose) > 2 * len(CATALOGUE)  # the split found the messages' words
    for path in tests.rglob("test_*.py"):
        if path.name == "test_flags.py" or path.parent.name == "e2e":
            continue  # the page's browser tests read what the page shows
        for text in _quoted_text(path):
            quoted = [p for p in prose if p in text]
            assert not quoted, (path.name, quoted)


def test_an_answers_flags_cannot_change_another_answers():
    """A plan's flags are shared by the answers made from it (the SCA range keeps its first node's
    plan, a node's field-grid flag is made once): their values are read-only, so editing one
    answer's flag cannot reach the next answer's."""
    first = solve("H158", magnitude=18.3, tolerance=1e-4)
    for flag in first.flags:
        if isinstance(flag, Flag):
            with pytest.raises(TypeError):
                flag.values["x"] = -1.0  # type: ignore[index]
    again = solve("H158", magnitude=18.3, tolerance=1e-4)
    assert [f.to_dict() for f in again.flags] == [f.to_dict() for f in first.flags]
    assert pickle.loads(pickle.dumps(first.flags)) == first.flags
