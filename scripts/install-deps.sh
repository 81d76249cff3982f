#!/usr/bin/env bash
# Installs what trackcal needs on a Debian bookworm machine (run as root), and nothing when it is
# already there: Debian packages via apt-get, Python packages into the project's virtual environment.
# Sourced by scripts/demo.sh and scripts/test.sh; prints the venv's python as TRACKCAL_PYTHON.
set -euo pipefail

TRACKCAL_ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
TRACKCAL_VENV="${TRACKCAL_VENV:-$TRACKCAL_ROOT/.venv}"

apt_packages=(
  build-essential cmake ninja-build pkg-config
  libeigen3-dev libceres-dev libgtest-dev libgmock-dev libbenchmark-dev nlohmann-json3-dev
  libyaml-cpp-dev
)
# The tests render the HTML report in a headless browser.
apt_packages+=(chromium)
# The Unity plugin's tests (plugin/foreign_clients_test): its C# wrapper compiled and run with Mono,
# its Windows DLL cross-compiled with MinGW-w64 and run under Wine.
apt_packages+=(mono-mcs mono-runtime g++-mingw-w64-x86-64-posix wine64)

missing=()
for p in "${apt_packages[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
if ! command -v python3 >/dev/null 2>&1; then missing+=(python3 python3-dev python3-venv); fi
if ((${#missing[@]})); then
  echo "install-deps: apt-get install ${missing[*]}" >&2
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

if [[ ! -x "$TRACKCAL_VENV/bin/python" ]]; then
  if ! python3 -m venv "$TRACKCAL_VENV" 2>/dev/null; then
    # Debian's own python3 needs the venv module and headers as packages.
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq && apt-get install -y -qq --no-install-recommends python3-venv python3-dev >/dev/null
    rm -rf "$TRACKCAL_VENV"
    python3 -m venv "$TRACKCAL_VENV"
  fi
fi
TRACKCAL_PYTHON="$TRACKCAL_VENV/bin/python"

if ! "$TRACKCAL_PYTHON" - "$TRACKCAL_ROOT/requirements-dev.txt" <<'PY' 2>/dev/null; then
import sys
from importlib.metadata import version, PackageNotFoundError
from packaging.requirements import Requirement
for line in open(sys.argv[1]):
    line = line.split("#")[0].strip()
    if not line:
        continue
    req = Requirement(line)
    if not req.specifier.contains(version(req.name), prereleases=True):
        raise SystemExit(1)
PY
  echo "install-deps: pip install -r requirements-dev.txt" >&2
  "$TRACKCAL_PYTHON" -m pip install -q --upgrade pip >/dev/null
  "$TRACKCAL_PYTHON" -m pip install -q -r "$TRACKCAL_ROOT/requirements-dev.txt"
fi
export TRACKCAL_ROOT TRACKCAL_VENV TRACKCAL_PYTHON
