#!/usr/bin/env bash
# Refresh requirements/lock.txt: install the newest versions pyproject.toml allows into a
# scratch environment and record every package's exact version. Run the tests on it
# (scripts/test_latest.sh) before committing the new lock.
set -euo pipefail
cd "$(dirname "$0")/.."
venv=$(mktemp -d)/venv
LEARNEST_LOCK=none LEARNEST_VENV="$venv" bash scripts/setup.sh
{
    echo "# Exact versions of every package the project installs (runtime, test and build tools),"
    echo "# used by scripts/setup.sh as pip constraints. Refresh: bash scripts/lock.sh"
    echo "# Python $("$venv/bin/python" -c 'import platform; print(platform.python_version())'), Linux $(uname -m); torch is the CPU build."
    "$venv/bin/python" -m pip freeze --all 2>/dev/null | grep -viE "^(-e|#)|learnest" | sed 's/+cpu//' | sort -f
} > requirements/lock.txt
rm -rf "$(dirname "$venv")"
git diff --stat requirements/lock.txt
