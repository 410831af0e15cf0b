"""The README's examples run and print what the README shows (the user's first contact)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_spec = importlib.util.spec_from_file_location("check_docs", ROOT / "scripts" / "check_docs.py")
check_docs = importlib.util.module_from_spec(_spec)
sys.modules["check_docs"] = check_docs  # its dataclasses look their module up by name
_spec.loader.exec_module(check_docs)


def test_shown_output_matches_exactly_or_where_an_ellipsis_elides():
    assert check_docs.matches(("a 1", "b"), ["a 1", "b"])
    assert not check_docs.matches(("a 1", "b"), ["a 2", "b"])
    assert not check_docs.matches(("a 1",), ["a 1", "b"])  # an extra printed line is a difference
    assert check_docs.matches(("cost … s",), ["cost 0.31 s"])
    assert not check_docs.matches(("cost … s",), ["price 0.31 s"])
    assert check_docs.matches(("a", "…", "z"), ["a", "b", "c", "z"])
    assert check_docs.matches(("a", "…"), ["a"])


def test_console_blocks_are_read_with_their_continuations(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("```console\n$ echo a \\\n  b\na b\n$ true\n```\n```sh\n$ not run\n```\n")
    found = check_docs.examples(page)
    assert [(e.command, e.expected) for e in found] == [("echo a \\\n  b", ("a b",)), ("true", ())]


def test_every_readme_example_runs_and_prints_what_the_readme_shows():
    env = check_docs.environment()
    service = check_docs.Service(env)
    try:
        results = [(e, *check_docs.run(e, env, service)) for e in check_docs.examples(ROOT / "README.md")]
    finally:
        service.stop()
    assert len(results) >= 3
    failed = [f"README.md:{e.line}: {why}" for e, ok, why in results if not ok]
    assert not failed, "\n\n".join(failed)


def test_every_calibration_example_runs_and_prints_what_the_page_shows(tmp_path):
    # The kernel example writes its ECSV into the folder it runs in: a folder of its own, not the repository.
    env = check_docs.environment()
    examples = check_docs.examples(ROOT / "docs" / "calibration.md")
    results = [(e, *check_docs.run(e, env, None, cwd=tmp_path)) for e in examples]
    assert len(results) >= 1
    failed = [f"docs/calibration.md:{e.line}: {why}" for e, ok, why in results if not ok]
    assert not failed, "\n\n".join(failed)
