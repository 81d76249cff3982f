#!/usr/bin/env bash
# The main job on the embedded default. Installs what is missing, builds, then runs the loop.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/install-deps.sh"
"$TRACKCAL_ROOT/scripts/build.sh"
export PATH="$TRACKCAL_VENV/bin:$PATH"
exec "$TRACKCAL_PYTHON" -m trackcal.demo "$@"
