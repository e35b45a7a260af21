#!/usr/bin/env bash
# Create a virtual environment in the repository and install learnest_codegen with everything it
# needs, at the exact versions of requirements/lock.txt (pip constraints), so that every machine
# tests the same stack.
#
#   LEARNEST_LOCK   the constraints file (default requirements/lock.txt); "none": the newest
#                   versions pyproject.toml allows (scripts/test_latest.sh, scripts/lock.sh)
#   LEARNEST_VENV   the environment's folder (default .venv)
#
# torch is the local CPU build 2.13.0 (any other spec pulls GBs of CUDA wheels); l4casadi is
# built from source against that torch, which needs scikit-build, cmake and ninja first.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
VENV=${LEARNEST_VENV:-.venv}
LOCK=${LEARNEST_LOCK:-requirements/lock.txt}
if [ "$LOCK" = none ]; then PIN=(); else PIN=(-c "$LOCK"); fi
[ -x "$VENV/bin/python" ] || "$PYTHON" -m venv "$VENV"
. "$VENV/bin/activate"
pip() { python -m pip install -q --disable-pip-version-check "${PIN[@]}" "$@" 2>&1 \
        | { grep -v "^WARNING: Location" || true; }; return "${PIPESTATUS[0]}"; }
pip --upgrade pip
pip "torch==2.13.0"
pip scikit-build cmake ninja setuptools wheel
python -c "import l4casadi" 2>/dev/null || CMAKE_POLICY_VERSION_MINIMUM=3.5 pip l4casadi --no-build-isolation
pip -e ".[test]" --no-build-isolation
python - <<'PY'
import importlib.metadata as m
print("installed:", ", ".join(f"{p} {m.version(p)}" for p in
      ("torch", "casadi", "l4casadi", "numpy", "scipy", "filterpy")))
PY
