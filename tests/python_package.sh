#!/bin/sh
# The Python package (python/) against a live `rigd --sim`: a fresh venv, `pip install
# ./python[test,typing]`, mypy --strict on the package and its tests, and pytest (python/tests,
# which starts its own rigd --sim on a temporary socket and data root; docs/python.md's
# code included). Builds nothing: give the daemon in $RIGD_BIN (default target/debug/rigd).
# Usage: RIGD_BIN=target/debug/rigd tests/python_package.sh [pytest args]
set -eu
cd "$(dirname "$0")/.."
RIGD_BIN=$(realpath "${RIGD_BIN:-target/debug/rigd}")
export RIGD_BIN
[ -x "$RIGD_BIN" ] || { echo "python_package: no rigd at $RIGD_BIN (cargo build --bin rigd)"; exit 1; }
if ! python3 -c 'import ensurepip, venv' 2>/dev/null; then
    echo "python_package: installing python3-venv"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq python3-venv >/dev/null
fi
VENV=$(mktemp -d)
trap 'rm -rf "$VENV"' EXIT
python3 -m venv "$VENV"
"$VENV/bin/pip" install -q --upgrade pip
"$VENV/bin/pip" install -q "./python[test,typing]"
echo "python_package: mypy --strict"
(cd python && "$VENV/bin/mypy" --strict src/rigd tests)
echo "python_package: pytest against $RIGD_BIN"
cd python && "$VENV/bin/python" -m pytest -q -rs "$@" tests
