#!/usr/bin/env bash
# Create .venv/ in the repository and install learnest_codegen with everything it needs.
# torch is pinned to the local CPU build (any other spec pulls GBs of CUDA wheels); l4casadi is
# built from source against that torch, which needs scikit-build, cmake and ninja first.
set -euo pipefail
cd "$(dirname "$0")/.."
PYTHON=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
. .venv/bin/activate
python -m pip install -q --upgrade pip
python -m pip install -q "torch==2.13.0"
python -m pip install -q scikit-build cmake ninja setuptools wheel
python -c "import l4casadi" 2>/dev/null || \
    CMAKE_POLICY_VERSION_MINIMUM=3.5 python -m pip install -q l4casadi --no-build-isolation
python -m pip install -q -e ".[test]" --no-build-isolation
