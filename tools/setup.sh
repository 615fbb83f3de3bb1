#!/usr/bin/env bash
# Set up everything flexmbs needs, and be quick when it is already there:
#   1. system packages (gfortran, SuiteSparse, LAPACK/OpenBLAS, pkg-config), with apt-get as root;
#   2. a virtual environment .venv;
#   3. the package, editable, with its test, batch and docs extras (rebuilt on import after
#      Fortran edits; docs: mkdocs + mkdocstrings, the API reference that the tests build).
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}
PKGS="gfortran libsuitesparse-dev liblapack-dev libopenblas-dev pkg-config"

have_system() {
    command -v gfortran >/dev/null 2>&1 || return 1
    command -v pkg-config >/dev/null 2>&1 || return 1
    [ -f /usr/include/suitesparse/klu.h ] || [ -f /usr/local/include/suitesparse/klu.h ] \
        || [ -f /usr/include/klu.h ] || return 1
    # grep without -q reads all of ldconfig's output: with -q it may exit first, ldconfig dies
    # of SIGPIPE and pipefail made the check fail now and then (an apt-get for nothing, or an
    # error for a user without root)
    ldconfig -p 2>/dev/null | grep 'liblapack\.so' >/dev/null || return 1
    return 0
}

if ! have_system; then
    if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
        echo "flexmbs setup: installing system packages: $PKGS"
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -q
        apt-get install -y -q $PKGS
    else
        echo "flexmbs setup: missing system packages. Install them with:" >&2
        echo "    sudo apt-get update && sudo apt-get install -y $PKGS" >&2
        echo "then run this command again." >&2
        exit 1
    fi
fi

if [ ! -x "$VENV/bin/python" ]; then
    echo "flexmbs setup: creating $VENV"
    "$PYTHON" -m venv "$VENV"
fi

# Reinstall only when the project's metadata changed (the editable install
# itself rebuilds the compiled core on import when Fortran or C sources change).
stamp="$VENV/.flexmbs-installed"
want=$(cat pyproject.toml meson.build | sha1sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ] || ! "$VENV/bin/python" -c "import flexmbs" >/dev/null 2>&1; then
    echo "flexmbs setup: installing build tools and flexmbs (editable) into $VENV"
    "$VENV/bin/python" -m pip install -q --upgrade pip >/dev/null 2>&1 || true
    "$VENV/bin/python" -m pip install -q "meson-python>=0.15" "meson>=1.1" ninja "numpy>=1.26"
    "$VENV/bin/python" -m pip install -q --no-build-isolation -e ".[test,batch,docs]"
    "$VENV/bin/python" -c "import flexmbs" 
    echo "$want" > "$stamp"
fi

# Byte-compile the package (fast when nothing changed): with PYTHONDONTWRITEBYTECODE set, as
# on this machine, every fresh interpreter (a batch's worker processes) would otherwise
# compile flexmbs's sources again (~0.2 s each; benchmarks/README.md, batch scaling).
"$VENV/bin/python" -m compileall -q python/flexmbs >/dev/null || true
