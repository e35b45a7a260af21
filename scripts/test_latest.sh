#!/usr/bin/env bash
# The default test suite on the newest versions pyproject.toml allows (no lock), in .venv-latest/:
# the check that the ranges in pyproject.toml still hold. Arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
LEARNEST_LOCK=none LEARNEST_VENV=.venv-latest bash scripts/setup.sh
.venv-latest/bin/python -m pip freeze 2>/dev/null | grep -iE "^(casadi|numpy|scipy|filterpy|l4casadi|torch)=="
.venv-latest/bin/python -m pytest -q -n auto "$@"
