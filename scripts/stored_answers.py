"""Store answers of the calculator as they are, to check a refactoring against: a few hundred random
requests (the paper's tables, its field-point tables at the corners, the Roman default without and
with a position, over the field), each answer's ``to_dict()`` without its timing.

The requests are drawn here from a fixed seed and read through the public API only (``nlpsf.SolveRequest.from_json``
and ``nlpsf.answer``, as the service reads a body), so the same script stores the answers of any
version of the code. ``tests/library/test_stored_answers.py`` answers them again and compares.

Usage: python scripts/stored_answers.py --write    (writes tests/data/stored_answers.json.gz)
"""

from __future__ import annotations

import argparse
import gzip
import json
import random
import subprocess
from pathlib import Path

OUT = Path(__file__).resolve().parent.parent / "tests" / "data" / "stored_answers.json.gz"
BANDS = ("R062", "Z087", "Y106", "J129", "H158", "F184", "W146", "K213")
METRICS = ("size", "e1", "e2", "e")
#: The corner field points of every SCA (``roman.field_points`` 1-4), where the paper's field-point tables are.
CORNERS = ((4.0, 4.0), (4092.0 - 8.0, 4.0), (4.0, 4092.0 - 8.0), (4084.0, 4084.0))
#: How many of each kind.
BASE = 120


def base_requests(seed: int = 2025, count: int = BASE) -> list[dict]:
    """Random requests (band, SCA, metric, mode, two of the three) -- the same ones the benchmark
    (``benchmarks/bench_default.py``) times."""
    draw = random.Random(seed)
    out = []
    for _ in range(count):
        body = {
            "band": draw.choice(BANDS),
            "sca": draw.randint(1, 18),
            "metric": draw.choice(METRICS),
            "mode": draw.choice(("bias", "scatter")),
        }
        solved = draw.choice(("precision", "tolerance", "magnitude"))
        if solved != "precision":
            body["precision"] = 10 ** draw.uniform(-3.0, -1.0)
        if solved != "tolerance":
            body["tolerance"] = 10 ** draw.uniform(-5.0, -2.5)
        if solved != "magnitude":
            body["magnitude"] = round(draw.uniform(15.0, 26.0), 3)
        body["position"] = [round(draw.uniform(1.0, 4088.0), 1), round(draw.uniform(1.0, 4088.0), 1)]
        out.append(body)
    return out


def bodies() -> list[tuple[str, dict]]:
    """(kind, API body) of every stored answer."""
    out: list[tuple[str, dict]] = []
    draw = random.Random(7)
    for body in base_requests():
        position = body.pop("position")
        out.append(("paper", {**body, "scene": "paper"}))
        out.append(("default", dict(body)))
        out.append(("default_at", {**body, "scene": {"position": position}}))
        if draw.random() < 0.25:
            out.append(("paper_corner", {**body, "scene": {"preset": "paper", "position": list(draw.choice(CORNERS))}}))
    # conditions off the tables' own: exposure and beta0 rescaled, averaging, shear budgets, a throughput
    extra = [
        {"band": "H158", "precision": 0.01, "magnitude": 20.0, "exptime": 300.0, "scene": "paper"},
        {"band": "J129", "tolerance": 1e-4, "magnitude": 19.0, "beta0": 8e-7, "scene": "paper"},
        {"band": "F184", "mode": "scatter", "stars": 25, "precision": 0.05, "tolerance": 3e-5, "scene": "paper"},
        {"band": "Y106", "metric": "size", "shear_m": 1e-3, "size_ratio": 1.5, "precision": 0.02, "scene": "paper"},
        {"band": "H158", "metric": "e1", "shear_c": 1e-4, "size_ratio": 1.2, "magnitude": 19.5},
        {"band": "W146", "metric": "e", "size_ratio": 2.0, "precision": 0.01, "magnitude": 21.0},
        {"band": "K213", "precision": 0.01, "magnitude": 20.0, "throughput": "official", "scene": "paper"},
        {"band": "H158", "precision": 0.01, "tolerance": 1e-4, "full_well": 9e4, "scene": "paper"},
        {"band": "H158", "precision": 0.001, "tolerance": 1e-3, "scene": "paper"},
        {"band": "Z087", "precision": 0.2, "tolerance": 1e-6},
        {"band": "R062", "precision": 0.001, "tolerance": 1e-2, "scene": {"position": [2000, 2000]}},
        {"band": "H158", "precision": 0.01, "magnitude": 30.0},
        {"band": "H158", "precision": 0.01, "magnitude": 30.0, "scene": {"position": [100, 3000]}},
    ]
    out += [("extra", body) for body in extra]
    return out


def over_field() -> list[dict]:
    """Requests answered as the worst over the field (``solve_over_field``)."""
    return [
        {"band": "H158", "scas": [18, 3], "precision": 0.01, "tolerance": 1e-4, "scene": "paper"},
        {"band": "J129", "scas": [7], "tolerance": 1e-4, "magnitude": 19.0, "scene": "paper"},
        {"band": "W146", "scas": [1, 9], "precision": 0.01, "magnitude": 20.0},
        {"band": "F184", "scas": [12], "metric": "e2", "precision": 0.02, "tolerance": 3e-5},
    ]


def _solve_over_field():
    try:
        from nlpsf.solve.solver import solve_over_field
    except ImportError:  # the layout before the subpackages
        from nlpsf.solver import solve_over_field
    return solve_over_field


def answer_of(body: dict) -> dict:
    """The answer's ``to_dict()`` without its timing, or the ``InputError`` it raises (field, reason)."""
    from nlpsf import InputError, SolveRequest, answer

    try:
        out = answer(SolveRequest.from_json(body)).to_dict()
    except InputError as error:
        return {"error": {"argument": error.argument, "reason": error.reason}}
    out.pop("elapsed_s", None)
    return out


def over_field_answer(body: dict) -> dict:
    body = dict(body)
    scas, scene = body.pop("scas"), body.pop("scene", None)
    out = _solve_over_field()(body.pop("band"), scas=scas, scene=scene, **body).to_dict()
    out.pop("elapsed_s", None)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--write", action="store_true", help=f"write {OUT.name}")
    parser.add_argument("--commit", help="the commit the answers are of (default: this checkout's HEAD)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    git = ["git", "rev-parse", "--short", "HEAD"]
    commit = args.commit or subprocess.run(git, capture_output=True, text=True, cwd=OUT.parent).stdout.strip()
    stored = {"commit": commit, "answers": [], "over_field": []}
    for kind, body in bodies():
        stored["answers"].append({"kind": kind, "body": body, "answer": answer_of(body)})
    for body in over_field():
        stored["over_field"].append({"body": body, "answer": over_field_answer(body)})
    text = json.dumps(stored, sort_keys=True, allow_nan=True)
    print(f"{len(stored['answers'])} answers, {len(stored['over_field'])} over the field; {len(text) / 1e6:.2f} MB of JSON")
    if args.write:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with gzip.open(args.out, "wt", compresslevel=9) as handle:
            handle.write(text)
        print(f"wrote {args.out} ({args.out.stat().st_size / 1e3:.0f} kB)")


if __name__ == "__main__":
    main()
