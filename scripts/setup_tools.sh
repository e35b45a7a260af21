#!/usr/bin/env bash
# The Debian tools the tests and benchmarks use, installed when missing and when apt-get exists:
# the Cortex-M4F cross toolchain and emulator (tests/test_cortex_m.py, the Crazyflie build),
# valgrind (memcheck and callgrind), clang (the C kit compiled by a second compiler) and cmake.
# A test that needs a tool that could not be installed skips and names it.
set -uo pipefail
declare -A need=([arm-none-eabi-gcc]=gcc-arm-none-eabi [qemu-system-arm]=qemu-system-arm
                 [valgrind]=valgrind [clang]=clang [cmake]=cmake [make]=make [xz]=xz-utils)
missing=()
for tool in "${!need[@]}"; do command -v "$tool" >/dev/null 2>&1 || missing+=("${need[$tool]}"); done
[ -e /usr/lib/arm-none-eabi/newlib ] || missing+=(libnewlib-arm-none-eabi)
[ ${#missing[@]} -eq 0 ] && exit 0
if ! command -v apt-get >/dev/null 2>&1; then
    echo "WARNING: no apt-get; missing ${missing[*]}: the tests that need them skip" >&2; exit 0
fi
SUDO=""; [ "$(id -u)" -eq 0 ] || SUDO="sudo"
{ $SUDO apt-get update -q && DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -q \
    --no-install-recommends "${missing[@]}"; } >/dev/null \
    || echo "WARNING: installing ${missing[*]} failed: the tests that need them skip" >&2
exit 0
