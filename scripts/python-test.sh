#!/usr/bin/env bash
# Build the Python package lpvid (host-tools/python) into a virtual environment with a plain
# `pip install <path>` (maturin is its build backend: nothing else to run) and run its pytest
# suite. The environment is kept in target/pyenv and reused. The crate is outside the
# workspace (own Cargo.lock) but builds in the workspace's target directory, where
# `cargo build --release -p lpvid-host --bin lpvid` has already compiled its dependencies
# with the same versions, features and profile (host-tools/python/Cargo.toml says how):
# only lpvid, lpvid-host (a path dependency of another workspace is another artefact),
# pyo3, numpy, ndarray and the extension are compiled here.
#
#   scripts/python-test.sh            # install + pytest
#   scripts/python-test.sh -k dask    # extra arguments go to pytest
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
VENV=${LPVID_PYENV:-$ROOT/target/pyenv}
PY=${PYTHON:-python3}
TARGET=${CARGO_TARGET_DIR:-$ROOT/target}
PY_TARGET=${CARGO_TARGET_DIR_PYTHON:-$TARGET}

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
# the command line, for the model round-trip test (in CI already built by device-test); first,
# so that the extension's build below finds the dependencies compiled
cargo build --release --quiet -p lpvid-host --bin lpvid
export LPVID_BIN=${LPVID_BIN:-$TARGET/release/lpvid}
# The extension reuses a dependency only if it has the version and features the lpvid build
# gave it: warn (only time is at stake) about each shared crate where the two differ.
deps() { cargo tree -q "$@" -e normal,build --prefix none -f '{p} {f}' | sed 's/ (\*)$//' | sort -u; }
if bin_deps=$(deps -p lpvid-host) && py_deps=$(cd host-tools/python && deps); then
  drift=$(comm -13 <(echo "$bin_deps") <(echo "$py_deps") \
    | awk 'NR == FNR { shared[$1] = 1; next } ($1 in shared) { print "  " $0 }' \
      <(echo "$bin_deps") -)
  if [ -n "$drift" ]; then
    echo "python-test: warning: these crates differ (version or features) from the lpvid build's, so"
    echo "the extension's build recompiles them and all above them (see host-tools/python/Cargo.toml):"
    echo "$drift"
  fi
fi
# the package itself, exactly as a user installs it (maturin builds the wheel)
echo "python-test: pip install host-tools/python"
CARGO_TARGET_DIR=$PY_TARGET "${PIP[@]}" install --quiet --force-reinstall --no-deps host-tools/python
cd host-tools/python
exec "$VENV/bin/python" -m pytest -q tests "$@"
