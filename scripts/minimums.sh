#!/usr/bin/env bash
# Run the fast tests against the declared minimum versions of every runtime dependency.
#
#   ./scripts/minimums.sh [pytest arguments...]
#
# Reads the ">=" lower bounds of [project.dependencies] in pyproject.toml, pins each to exactly that
# version (pip constraints), installs the project with its test extra into .venv-min and runs
# `pytest -m "not slow"`. A failure here means a declared minimum is not a true one.
set -euo pipefail
cd "$(dirname "$0")/.."

python3 -m venv --clear .venv-min
.venv-min/bin/python -m pip install -q --upgrade pip
.venv-min/bin/python - > .venv-min/constraints.txt <<'PY'
import re, tomllib
project = tomllib.load(open("pyproject.toml", "rb"))["project"]
# httpx too: Starlette's TestClient of the oldest FastAPI needs the httpx of its time.
deps = project["dependencies"] + [d for d in project["optional-dependencies"]["test"] if d.startswith("httpx")]
for dep in deps:
    match = re.match(r"^\s*([A-Za-z0-9_.-]+)(\[[^\]]*\])?\s*>=\s*([^,;\s]+)", dep)
    if match:
        print(f"{match.group(1)}=={match.group(3)}")
PY
echo "minimums.sh: pinned $(tr '\n' ' ' < .venv-min/constraints.txt)" >&2
.venv-min/bin/python -m pip install -q -c .venv-min/constraints.txt -e ".[test]"
exec .venv-min/bin/python -m pytest -m "not slow" -q -p no:cacheprovider "$@"
