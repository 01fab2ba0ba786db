#!/usr/bin/env bash
# Set up everything the tests need on a fresh Debian machine, then run pytest.
#   bash tests/setup_and_run.sh [pytest arguments]
# Creates .venv (if missing), installs the project with its test extras,
# installs Debian's chromium for the browser tests and Debian's postgresql
# for the PostgreSQL archive tests if they are missing (the tests start their
# own server from it, in a temporary directory), and runs the whole suite.
# Screenshots go to test-artifacts/ (outside git).
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
    "$PYTHON" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e '.[test]'

SUDO=""
[ "$(id -u)" -ne 0 ] && SUDO="sudo"
APT_UPDATED=""
apt_install() {
    [ -n "$APT_UPDATED" ] || { $SUDO apt-get update -qq && APT_UPDATED=1; }
    $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" >/dev/null
}

if ! command -v chromium >/dev/null 2>&1; then
    echo "installing Debian's chromium for the browser tests..." >&2
    apt_install chromium
fi

# The server binaries only (initdb, pg_ctl): the tests run their own server; Debian's
# package also sets up a cluster of its own, which the tests leave alone.
if ! ls /usr/lib/postgresql/*/bin/initdb >/dev/null 2>&1; then
    echo "installing Debian's postgresql for the PostgreSQL archive tests..." >&2
    apt_install postgresql
fi

mkdir -p test-artifacts
# numba's kernels compiled, and the bright-pair indexes of every depth built, once into their on-disk caches
# before the tests (app/compiled.py, app/identification/sky.py): every server and worker process the tests
# start then loads them (a fraction of a second), instead of each compiling or building its own under a
# request's time-out (on a new machine: ~20 s of kernels, ~15 s of the Hp 8 index).
.venv/bin/python -c "from app.identification import Sky; Sky().with_every_depth(); from app.compiled import warm_up; warm_up()"
exec .venv/bin/python -m pytest "$@"
