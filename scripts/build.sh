#!/usr/bin/env bash
# Builds everything (C++ libraries, tools, tests, benchmarks) and installs the Python package with its
# command-line tools into the project's venv. One CMake tree in build/, driven by scikit-build-core,
# so `pip install` and ctest share one incremental build.
set -euo pipefail
source "$(dirname "${BASH_SOURCE[0]}")/install-deps.sh"
cd "$TRACKCAL_ROOT"
export CMAKE_BUILD_PARALLEL_LEVEL="${CMAKE_BUILD_PARALLEL_LEVEL:-$(nproc)}"
"$TRACKCAL_PYTHON" -m pip install -q --no-build-isolation --no-deps \
  -Cbuild-dir=build \
  -Ccmake.define.TRACKCAL_BUILD_TESTS=ON \
  -Ccmake.define.TRACKCAL_BUILD_BENCHMARKS=ON \
  "$@" .
