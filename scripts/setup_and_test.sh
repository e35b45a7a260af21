#!/usr/bin/env bash
# Install everything into .venv/ and run the default test suite (slow tests deselected).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
# valgrind for the memcheck tests of tests/test_reliability.py (they skip without it)
if ! command -v valgrind >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
    { apt-get update -qq && apt-get install -y -qq valgrind; } \
        || echo "valgrind could not be installed: the memcheck tests will be skipped" >&2
fi
. .venv/bin/activate
python -m pytest -q "$@"
