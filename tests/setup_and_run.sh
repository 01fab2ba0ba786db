#!/usr/bin/env bash
# Set up everything the tests need on a fresh Debian machine, then run pytest.
#   bash tests/setup_and_run.sh [pytest arguments]
# Creates .venv (if missing), installs the project with its test extras,
# installs Debian's chromium for the browser tests if it is missing, and runs
# the whole suite.  Screenshots go to test-artifacts/ (outside git).
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e '.[test]'

if ! command -v chromium >/dev/null 2>&1; then
    echo "installing Debian's chromium for the browser tests..." >&2
    SUDO=""
    [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null
fi

mkdir -p test-artifacts
exec .venv/bin/python -m pytest "$@"
