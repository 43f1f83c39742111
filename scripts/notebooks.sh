#!/usr/bin/env bash
# Executes every notebook in notebooks/ headless with the evcxr Rust kernel
# and fails on any cell error, or on a picture or table cell that no longer
# yields one (scripts/run_notebooks.py). Installs what it needs: evcxr_jupyter
# from crates.io, nbclient from PyPI.
#
#   bash scripts/notebooks.sh [--write] [NOTEBOOK...]   (--write: save the outputs into the notebooks)
#   bash scripts/notebooks.sh --install                 (only install the kernel and nbclient)
#
# The notebooks share one evcxr build folder (EVCXR_TMPDIR, default
# target/evcxr): the first compiles refnpr and its dependencies for the
# kernel (evcxr builds every crate as a dynamic library, so the project's own
# target/ cannot be reused); the others reuse it.
set -euo pipefail
cd "$(dirname "$0")/.."

EVCXR_VERSION=0.22.0
if ! cargo install --list | grep -q "^evcxr_jupyter v$EVCXR_VERSION:"; then
  echo "== installing evcxr_jupyter $EVCXR_VERSION (crates.io)"
  cargo install --locked evcxr_jupyter --version "$EVCXR_VERSION"
fi
# Registers (or refreshes) the "rust" kernel with Jupyter.
evcxr_jupyter --install >/dev/null
if ! python3 -c "import nbclient, nbformat" >/dev/null 2>&1; then
  python3 -m pip install --quiet nbclient nbformat
fi

if [ "${1:-}" = "--install" ]; then
  exit 0
fi

export EVCXR_TMPDIR="${EVCXR_TMPDIR:-$PWD/target/evcxr}"
mkdir -p "$EVCXR_TMPDIR"
# wgpu (winit) warns when this is unset on headless machines.
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"

WRITE=()
# NOTEBOOKS_WRITE=1 does what --write does (for a run inside .ci/run).
[ "${NOTEBOOKS_WRITE:-0}" = "1" ] && WRITE=(--write)
if [ "${1:-}" = "--write" ]; then
  WRITE=(--write)
  shift
fi
if [ "$#" -eq 0 ]; then
  set -- notebooks/*.ipynb
fi
python3 scripts/run_notebooks.py "${WRITE[@]}" "$@"
