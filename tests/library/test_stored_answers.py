"""Answers stay what they were: a few hundred answers stored by ``scripts/stored_answers.py`` (the
commit named in the file: after the field grid's rebuild of 2026-12-04 with the per-resultant residual),
answered again. This guards a refactoring, not the physics (the physics is checked against GalSim, stcal and
the analytic cases elsewhere): the paper's scene bit for bit, the Roman default within 1e-12
relative (where evaluating every node at once may change the last bits), the same flag codes and
the same refusals (the field each names). Words are not compared (messages, descriptions: any text
with a space), so that the catalogue may reword them; identifiers are."""

from __future__ import annotations

import gzip
import json
import math
from functools import cache
from pathlib import Path

import pytest

from nlpsf import InputError, SolveRequest, answer
from nlpsf.solve.solver import solve_over_field

STORED = Path(__file__).resolve().parent.parent / "data" / "stored_answers.json.gz"
#: Relative tolerance of the Roman default's numbers (vectorised evaluation); the paper's are exact.
DEFAULT_RTOL = 1e-12


@cache
def stored() -> dict:
    with gzip.open(STORED, "rt") as handle:
        return json.load(handle)


def differences(old, new, rtol: float, where: str = "") -> list[str]:
    """Where ``new`` differs from ``old``: numbers beyond ``rtol`` (0: exactly), identifiers and the
    structure unequal; text in words (a string with a space) is not compared."""
    if isinstance(old, str) and " " in old and isinstance(new, str):
        return []
    if isinstance(old, bool) or old is None or isinstance(old, str):
        return [] if old == new else [f"{where}: {old!r} -> {new!r}"]
    if isinstance(old, (int, float)):
        if not isinstance(new, (int, float)) or isinstance(new, bool):
            return [f"{where}: {old!r} -> {new!r}"]
        if math.isnan(old) and math.isnan(new):
            return []
        same = old == new if rtol == 0 else math.isclose(old, new, rel_tol=rtol, abs_tol=0.0)
        return [] if same else [f"{where}: {old!r} -> {new!r}"]
    if isinstance(old, dict):
        if not isinstance(new, dict) or set(old) != set(new):
            return [f"{where}: keys {sorted(old)} -> {sorted(new) if isinstance(new, dict) else new!r}"]
        return [d for k in old for d in differences(old[k], new[k], rtol, f"{where}.{k}")]
    if isinstance(old, list):
        if not isinstance(new, list) or len(old) != len(new):
            return [f"{where}: {len(old)} items -> {new!r}"]
        return [d for i, (a, b) in enumerate(zip(old, new, strict=True)) for d in differences(a, b, rtol, f"{where}[{i}]")]
    return [f"{where}: cannot compare {old!r}"]


#: Answers simulated afresh (issue 28: a Roman-default answer at a position between the saturation
#: limits), by the flag code they carry: not compared. Each costs about a CPU-second, and what this guards
#: is the path from a request to the shipped slopes; the fresh simulation is checked against GalSim,
#: stcal and the brute force elsewhere.
SIMULATED_AFRESH = frozenset({"default_between_limits"})


def simulated_afresh(out: dict) -> bool:
    return bool(SIMULATED_AFRESH & set(out.get("flag_codes") or []))


def answered(body: dict) -> dict:
    try:
        out = answer(SolveRequest.from_json(body)).to_dict()
    except InputError as error:
        return {"error": {"argument": error.argument, "reason": error.reason}}
    out.pop("elapsed_s")
    return json.loads(json.dumps(out))  # as stored: tuples as lists


def refusal_by_field(out: dict) -> dict:
    """A refusal compared by the field at fault: its English reason may be reworded (the flag
    catalogue's rule), and a reworded reason is no change of answer."""
    if "error" in out:
        return {"error": {"argument": out["error"]["argument"]}}
    return out


def _is_paper(body: dict) -> bool:
    scene = body.get("scene")
    return scene == "paper" or (isinstance(scene, dict) and scene.get("preset") == "paper")


KINDS = ("paper", "paper_corner", "default", "default_at", "extra")


@pytest.mark.parametrize("kind", KINDS)
def test_stored_answers_are_answered_again_alike(kind):
    entries = [e for e in stored()["answers"] if e["kind"] == kind]
    assert entries
    failures = []
    for entry in entries:
        rtol = 0.0 if _is_paper(entry["body"]) else DEFAULT_RTOL
        if simulated_afresh(entry["answer"]):
            continue
        found = differences(refusal_by_field(entry["answer"]), refusal_by_field(answered(entry["body"])), rtol)
        if found:
            failures.append(f"{entry['body']}: {found[:3]}")
    assert not failures, f"{len(failures)} of {len(entries)} differ ({_blas()}); first: {failures[:3]}"


def _blas() -> str:
    """The BLAS kernels this process runs (tests/conftest.py pins OpenBLAS's to those the answers were stored with)."""
    from threadpoolctl import threadpool_info

    found = [f"{i.get('internal_api')} {i.get('version')} {i.get('architecture')}" for i in threadpool_info()]
    return ", ".join(found) or "no BLAS found"


def test_the_stored_set_holds_every_kind_and_some_refusals():
    entries = stored()["answers"]
    assert len(entries) >= 300
    assert {e["kind"] for e in entries} == set(KINDS)
    assert any("error" in e["answer"] for e in entries)


def test_stored_answers_over_the_field_are_answered_again_alike():
    for entry in stored()["over_field"]:
        body = dict(entry["body"])
        rtol = 0.0 if body.get("scene") == "paper" else DEFAULT_RTOL
        scas, scene = body.pop("scas"), body.pop("scene", None)
        out = solve_over_field(body.pop("band"), scas=scas, scene=scene, **body).to_dict()
        out.pop("elapsed_s")
        found = differences(entry["answer"], json.loads(json.dumps(out)), rtol)
        assert not found, (entry["body"], found[:3])
