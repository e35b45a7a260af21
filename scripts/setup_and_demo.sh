#!/usr/bin/env bash
# Install everything into .venv/ and run the main job: the built-in cartpole demo.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
learnest demo "$@"
