#!/usr/bin/env bash
# Install everything (the Debian tools the tests use, then the locked Python environment in
# .venv/) and run the default test suite (slow tests deselected) on every core.
# Arguments go to pytest, e.g. `bash scripts/setup_and_test.sh -m slow`.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_tools.sh
bash scripts/setup.sh
. .venv/bin/activate
python -m pytest -q -n auto "$@"  # one worker per core (pytest-xdist)
