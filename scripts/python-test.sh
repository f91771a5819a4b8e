#!/usr/bin/env bash
# Build the Python package lpvid (host-tools/python) into a virtual environment with a plain
# `pip install <path>` (maturin is its build backend: nothing else to run) and run its pytest
# suite. The environment is kept in target/pyenv and reused; the Rust build in
# target/python (own Cargo.lock: the crate is outside the workspace).
#
#   scripts/python-test.sh            # install + pytest
#   scripts/python-test.sh -k dask    # extra arguments go to pytest
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
VENV=${LPVID_PYENV:-$ROOT/target/pyenv}
PY=${PYTHON:-python3}
export CARGO_TARGET_DIR=${CARGO_TARGET_DIR_PYTHON:-$ROOT/target/python}

make_venv() {
  if "$PY" -m venv "$VENV" 2>/dev/null && [ -x "$VENV/bin/pip" ]; then
    return 0
  fi
  rm -rf "$VENV"
  echo "python-test: '$PY -m venv' failed (python3-venv missing?); trying virtualenv"
  if "$PY" -m pip install --user --quiet virtualenv 2>/dev/null \
    || "$PY" -m pip install --quiet --break-system-packages virtualenv 2>/dev/null; then
    "$PY" -m virtualenv --quiet "$VENV" && return 0
  fi
  echo "python-test: installing the Debian package python3-venv"
  SUDO=""
  [ "$(id -u)" -eq 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq python3-venv >/dev/null
  "$PY" -m venv "$VENV"
}

if [ ! -x "$VENV/bin/python" ]; then
  echo "python-test: creating the virtual environment $VENV"
  make_venv
fi
PIP=("$VENV/bin/python" -m pip --disable-pip-version-check)
# the test dependencies (once; pip skips what is installed)
if ! "$VENV/bin/python" -c "import numpy, pandas, pytest, dask.distributed, dask.dataframe, matplotlib, maturin" 2>/dev/null; then
  "${PIP[@]}" install --quiet --upgrade pip
  "${PIP[@]}" install --quiet maturin numpy pandas pytest "dask[dataframe,distributed]" matplotlib
fi
# the package itself, exactly as a user installs it (maturin builds the wheel)
echo "python-test: pip install host-tools/python"
"${PIP[@]}" install --quiet --force-reinstall --no-deps host-tools/python
# the command line, for the model round-trip test
cargo build --release --quiet -p lpvid-host --bin lpvid
export LPVID_BIN=${LPVID_BIN:-$ROOT/target/release/lpvid}
cd host-tools/python
exec "$VENV/bin/python" -m pytest -q tests "$@"
