#!/usr/bin/env bash
# README command 1: set up, then run the built-in default scenario (procedural scenes only).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
exec .venv/bin/lsbench run scenarios/default.toml "$@"
