#!/usr/bin/env bash
# Install everything the tests need on a fresh Debian machine and run the whole suite.
#
#   ./scripts/test.sh [pytest arguments...]
#
# Installs (if missing) Debian's Chromium for the browser tests, makes .venv with the project and
# its test, reference (GalSim), dask, pipeline (stcal) and roman (roman_datamodels, asdf) extras, checks ruff, then runs pytest on every test:
# library, GalSim cross-checks, service, schemathesis, headless-browser end-to-end and the
# container build (which sets up podman itself through ../shared/tools/container).
set -euo pipefail
cd "$(dirname "$0")/.."

if ! command -v chromium >/dev/null 2>&1; then
  echo "test.sh: installing Debian's chromium" >&2
  as_root=""
  [ "$(id -u)" -eq 0 ] || as_root="sudo"
  $as_root apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $as_root apt-get install -y -qq chromium >/dev/null
fi

python3 -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[test,reference,dask,pipeline,roman]"

.venv/bin/ruff check .
.venv/bin/ruff format --check .
exec .venv/bin/python -m pytest "$@"
