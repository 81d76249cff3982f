#!/usr/bin/env bash
# Installs what is missing, builds, and runs every test (C++ with ctest, Python with pytest).
# Exits non-zero on any failure.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/install-deps.sh"
"$TRACKCAL_ROOT/scripts/build.sh"
cd "$TRACKCAL_ROOT"
status=0
ctest --test-dir build --output-on-failure -j "$(nproc)" || status=1
PATH="$TRACKCAL_VENV/bin:$PATH" "$TRACKCAL_PYTHON" -m pytest -q python/tests || status=1
exit $status
