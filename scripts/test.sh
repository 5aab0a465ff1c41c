#!/usr/bin/env bash
# README command 2 (and CI): set up, then run the test suite on the real drivers.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
exec .venv/bin/python -m pytest -q "$@"
