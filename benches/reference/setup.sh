#!/usr/bin/env bash
# Create the Python virtual environments used by the reference benchmark drivers.
#
#   ${FACTORD_BENCH_VENVS:-$HOME/.cache/factord/venvs}/gtsam   gtsam + numpy
#   ${FACTORD_BENCH_VENVS:-$HOME/.cache/factord/venvs}/g2o     g2o-python + numpy<2
#                                                             (g2o-python 0.0.12 segfaults with numpy 2)
#
# Idempotent: a venv whose packages already import is left alone.
# Override the interpreter with PYTHON=/path/to/python3 (default: python3).
set -euo pipefail

PYTHON="${PYTHON:-python3}"
VENVS="${FACTORD_BENCH_VENVS:-$HOME/.cache/factord/venvs}"
mkdir -p "$VENVS"

# make_venv NAME IMPORT_CHECK PIP_ARGS...
make_venv() {
    local name="$1" check="$2"
    shift 2
    local dir="$VENVS/$name"
    if [[ -x "$dir/bin/python" ]] && "$dir/bin/python" -c "$check" >/dev/null 2>&1; then
        echo "[setup] $name: already installed ($dir)"
        return 0
    fi
    echo "[setup] $name: creating venv in $dir"
    [[ -x "$dir/bin/python" ]] || "$PYTHON" -m venv "$dir"
    "$dir/bin/python" -m pip install --quiet --upgrade pip
    "$dir/bin/python" -m pip install --quiet "$@"
    if ! "$dir/bin/python" -c "$check"; then
        echo "[setup] $name: import check failed after install" >&2
        return 1
    fi
}

make_venv gtsam "import gtsam, numpy" gtsam numpy
make_venv g2o "import numpy, g2o; assert int(numpy.__version__.split('.')[0]) < 2" g2o-python 'numpy<2'

echo
echo "Reference venvs are ready:"
for name in gtsam g2o; do
    ver=$("$VENVS/$name/bin/python" -m pip list 2>/dev/null \
          | awk -v n="$name" 'tolower($1)==n || tolower($1)==n"-python" || tolower($1)=="numpy" {printf "%s %s  ", $1, $2}')
    echo "  $name: $VENVS/$name/bin/python   ($ver)"
done
echo "Set FACTORD_BENCH_VENVS=$VENVS for benches/run_benchmarks.py if you used a non-default location."
