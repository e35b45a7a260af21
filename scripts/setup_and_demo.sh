#!/usr/bin/env bash
# Install the locked Python environment into .venv/ and run the main job: the cartpole demo.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
. .venv/bin/activate
learnest demo "$@"
