#!/usr/bin/env bash
# Install everything into .venv/ and run the default test suite (slow tests deselected).
set -euo pipefail
cd "$(dirname "$0")/.."
# Cross toolchain and emulator for tests/test_cortex_m.py (the Cortex-M4F example); the test
# skips without them. Installed only when missing and when apt-get exists (CI runs as root).
if ! { command -v arm-none-eabi-gcc && command -v qemu-system-arm; } >/dev/null 2>&1 \
        && command -v apt-get >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
    { $SUDO apt-get update -q \
        && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q --no-install-recommends \
            gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm make; } \
        || echo "WARNING: installing the Cortex-M toolchain failed; tests/test_cortex_m.py will skip" >&2
fi
bash scripts/setup.sh
# valgrind for the memcheck tests of tests/test_reliability.py (they skip without it)
if ! command -v valgrind >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1; then
    { apt-get update -qq && apt-get install -y -qq valgrind; } \
        || echo "valgrind could not be installed: the memcheck tests will be skipped" >&2
fi
. .venv/bin/activate
python -m pytest -q -n auto "$@"  # one worker per core (pytest-xdist)
