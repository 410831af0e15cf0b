# ruff: noqa: E501, RUF005
"""Before/after check of ``--scene paper``: today's answers must stay bit for bit.

Run once on the code before the Roman default became the default (``--phase before``: the requests
as they were written then, no scene option), and once after (``--phase after``: the same requests
with ``--scene paper`` / ``"scene": "paper"`` added), then ``--compare``. Outputs are byte strings:
a CLI's stdout, an API response body. Keys an answer gained on purpose (``IGNORED_KEYS``, e.g.
the scene's name in the conditions) are removed from JSON before the comparison, and the report
names them; nothing else is normalised (timings excepted: ``elapsed_s`` is wall time).

    python scripts/paper_scene_bitcheck.py --phase before --out /tmp/bitcheck
    python scripts/paper_scene_bitcheck.py --phase after --out /tmp/bitcheck
    python scripts/paper_scene_bitcheck.py --compare --out /tmp/bitcheck
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: Keys that differ between runs of the same code (wall time) and keys added on purpose.
VOLATILE_KEYS = ("elapsed_s", "measured_utc", "created", "started", "finished", "id", "Location")
IGNORED_KEYS = ("scene_name", "scene_preset", "linearise_at")

BATCH_CSV = "band,magnitude,tolerance,precision,metric\nH158,18.3,1e-4,,size\nJ129,,1e-4,0.01,e1\nF184,20,,0.02,e\n"

#: (name, CLI arguments). The "after" phase appends ``--scene paper``.
# fmt: off
CLI: list[tuple[str, list[str]]] = [
    ("solve_readme_table", ["solve", "--band", "H158", "--magnitude", "18.3", "--tolerance", "1e-4"]),
    ("solve_readme_magnitude", ["solve", "--band", "H158", "--precision", "0.01", "--tolerance", "1e-4"]),
    ("solve_json", ["solve", "--band", "H158", "--magnitude", "18.3", "--tolerance", "1e-4", "--json"]),
    ("solve_mag_json", ["solve", "--band", "Y106", "--precision", "0.01", "--tolerance", "1e-4", "--json"]),
    ("solve_scatter_e1", ["solve", "--band", "J129", "--metric", "e1", "--mode", "scatter", "--stars", "10"]
     + ["--magnitude", "19", "--precision", "0.01", "--json"]),
    ("solve_shear", ["solve", "--band", "H158", "--shear-m", "1e-3", "--size-ratio", "1.5", "--magnitude", "19"]),
    ("solve_sca7_e", ["solve", "--band", "F184", "--sca", "7", "--metric", "e", "--magnitude", "20", "--precision", "0.02", "--json"]),
    ("solve_over_field", ["solve", "--band", "H158", "--over-field", "--magnitude", "19", "--tolerance", "1e-4", "--json"]),
    ("solve_ramp_ols", ["solve", "--band", "H158", "--ma-table", "romanisim-110", "--magnitude", "19", "--tolerance", "1e-4", "--json"]),
    (
        "solve_ramp_optimal",
        ["solve", "--band", "H158", "--ramp", "8", "--ramp-fit", "optimal", "--magnitude", "19.5", "--tolerance", "1e-4", "--json"],
    ),
    ("solve_scene_jitter", ["solve", "--band", "H158", "--jitter", "0.014", "--magnitude", "19", "--tolerance", "1e-4", "--json"]),
    ("solve_position", ["solve", "--band", "Y106", "--position", "1000,3000", "--magnitude", "19", "--tolerance", "1e-4"]),
    ("solve_batch", ["solve", "--batch", "{batch}"]),
    ("simulate", ["simulate", "--band", "H158", "--magnitude", "19", "--realizations", "12", "--json"]),
    ("slopes", ["slopes", "--band", "J129", "--magnitude", "18.3", "--magnitude", "21", "--realizations", "12", "--json"]),
    ("slopes_table", ["slopes", "--band", "F184", "--magnitude", "19", "--realizations", "8", "--method", "linear"]),
]
# fmt: on

#: (name, method, path, JSON body). The "after" phase adds ``"scene": "paper"`` to solve bodies.
API: list[tuple[str, str, str, dict | None]] = [
    ("api_solve", "POST", "/api/v1/solve", {"band": "H158", "magnitude": 18.3, "tolerance": 1e-4}),
    ("api_solve_mag", "POST", "/api/v1/solve", {"band": "J129", "precision": 0.01, "tolerance": 1e-4, "metric": "e2"}),
    (
        "api_solve_ramp",
        "POST",
        "/api/v1/solve",
        {"band": "H158", "magnitude": 19, "tolerance": 1e-4, "ma_table": "romanisim-110"},
    ),
    ("api_batch", "POST", "/api/v1/solve/batch", {"requests": [{"band": "H158", "magnitude": 19, "tolerance": 1e-4}]}),
]


def _run_cli(args: list[str], env: dict) -> bytes:
    done = subprocess.run([sys.executable, "-m", "nlpsf", *args], capture_output=True, env=env, timeout=900)
    return done.stdout + b"\n--- rc " + str(done.returncode).encode() + b"\n" + done.stderr[-2000:]


def _api_outputs(phase: str) -> dict[str, bytes]:
    from fastapi.testclient import TestClient
    from nlpsf.web.main import create_app
    from nlpsf.web.settings import Settings

    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        settings = Settings(db_path=str(Path(tmp) / "jobs.sqlite3"), job_workers=1, solve_wait_s=600)
        with TestClient(create_app(settings)) as client:
            for name, method, path, body in API:
                body = json.loads(json.dumps(body))
                if phase == "after":
                    if path == "/api/v1/solve":
                        body["scene"] = "paper"
                    elif path == "/api/v1/solve/batch":
                        for item in body["requests"]:
                            item["scene"] = "paper"
                response = client.request(method, path, json=body)
                out[name] = str(response.status_code).encode() + b"\n" + response.content
    return out


def run_phase(phase: str, out: Path) -> None:
    directory = out / phase
    directory.mkdir(parents=True, exist_ok=True)
    batch = directory / "batch.csv"
    batch.write_text(BATCH_CSV)
    env = {**os.environ, "PYTHONHASHSEED": "0"}
    for name, args in CLI:
        args = [a.replace("{batch}", str(batch)) for a in args]
        if phase == "after":
            args = [*args, "--scene", "paper"]
        start = time.perf_counter()
        (directory / f"{name}.out").write_bytes(_run_cli(args, env))
        print(f"{phase} {name}: {time.perf_counter() - start:.1f} s", flush=True)
    for name, body in _api_outputs(phase).items():
        (directory / f"{name}.out").write_bytes(body)
        print(f"{phase} {name}", flush=True)


def _strip(value, ignored: set[str], seen: set[str]):
    if isinstance(value, dict):
        kept = {}
        for k, v in value.items():
            if k in VOLATILE_KEYS:
                continue
            if "effects_on" in value and k == "name" and v in (None, "paper"):
                seen.add("scene.name")  # a scene's conditions now name the paper's scene
                continue
            if k == "scene_description" and isinstance(v, str) and v.startswith("paper: "):
                seen.add("scene_description")
                v = v.removeprefix("paper: ")
            if k in ignored:
                seen.add(k)
                continue
            kept[k] = _strip(v, ignored, seen)
        return kept
    if isinstance(value, list):
        return [_strip(v, ignored, seen) for v in value]
    return value


def _normalised(text: bytes, seen: set[str]) -> bytes:
    """JSON bodies without the volatile and the intentionally added keys; other text as it is."""
    head, _, rest = text.partition(b"\n") if text[:3].isdigit() else (b"", b"", text)
    body, sep, tail = rest.partition(b"\n--- rc ")
    try:
        parsed = json.loads(body)
    except ValueError:
        return text
    return head + json.dumps(_strip(parsed, set(IGNORED_KEYS), seen), sort_keys=True).encode() + sep + tail


def compare(out: Path) -> int:
    failures = 0
    seen: set[str] = set()
    for path in sorted((out / "before").glob("*.out")):
        after = out / "after" / path.name
        if not after.exists():
            print(f"MISSING {path.name}")
            failures += 1
            continue
        a, b = path.read_bytes(), after.read_bytes()
        identical = a == b
        same = identical or _normalised(a, seen) == _normalised(b, seen)
        print(f"{'identical' if identical else 'same' if same else 'DIFFERENT'} {path.name}")
        failures += not same
    print(f"{failures} different; keys added on purpose and ignored: {', '.join(sorted(seen)) or 'none'}")
    return 1 if failures else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--phase", choices=("before", "after"))
    parser.add_argument("--compare", action="store_true")
    parser.add_argument("--out", type=Path, default=Path("/tmp/nlpsf-bitcheck"))
    args = parser.parse_args()
    if args.phase:
        run_phase(args.phase, args.out)
    return compare(args.out) if args.compare else 0


if __name__ == "__main__":
    sys.exit(main())
