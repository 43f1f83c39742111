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
# target/evcxr) whose target/ is the project's own target directory. The
# kernel's crate depends on refnpr with its default features and builds with
# the project's dev profile (.cargo/config.toml) and the project's Cargo.lock
# (run_notebooks.py --cargo-lock), so every dependency that the project's
# build compiled with evcxr's two flags (RUSTFLAGS=-Cprefer-dynamic and
# --target <host>: .ci/run builds the tests so) is reused, and only refnpr
# itself is compiled again. Without those flags the first notebook compiles
# the dependencies once more (about 20 min on two cores).
set -euo pipefail
cd "$(dirname "$0")/.."

EVCXR_VERSION=0.22.0
if ! cargo install --list | grep -q "^evcxr_jupyter v$EVCXR_VERSION:"; then
  echo "== installing evcxr_jupyter $EVCXR_VERSION (crates.io)"
  # Optimised, although an unoptimised build takes 2.3 min instead of 11:
  # the kernel runs rust-analyzer over the crate and its dependencies at the
  # first `:dep`, and unoptimised that kept a core busy for minutes per
  # notebook (measured: the kernel process used 7.7 CPU-minutes before
  # notebook 1's third cell).
  # From / and without the project's build flags: the kernel is an ordinary
  # program.
  (cd / && env -u RUSTFLAGS -u CARGO_BUILD_TARGET -u RUSTC_WORKSPACE_WRAPPER \
    cargo install --locked evcxr_jupyter --version "$EVCXR_VERSION")
fi
# Registers (or refreshes) the "rust" kernel with Jupyter.
evcxr_jupyter --install >/dev/null
if ! python3 -c "import nbclient, nbformat" >/dev/null 2>&1; then
  python3 -m pip install --quiet nbclient nbformat
fi

if [ "${1:-}" = "--install" ]; then
  exit 0
fi

TARGET_DIR="${CARGO_TARGET_DIR:-$PWD/target}"
export EVCXR_TMPDIR="${EVCXR_TMPDIR:-$TARGET_DIR/evcxr}"
mkdir -p "$EVCXR_TMPDIR" "$TARGET_DIR"
# evcxr builds in $EVCXR_TMPDIR/target: make that the project's target dir
# (an older layout kept a separate one there).
if [ -d "$EVCXR_TMPDIR/target" ] && [ ! -L "$EVCXR_TMPDIR/target" ]; then
  rm -rf "$EVCXR_TMPDIR/target"
fi
ln -sfn "$(realpath "$TARGET_DIR")" "$EVCXR_TMPDIR/target"
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
# --cargo-lock: the project's versions of every dependency for the kernel's
# crate (run_notebooks.py says why it is copied after the kernel starts).
python3 scripts/run_notebooks.py --cargo-lock Cargo.lock "${WRITE[@]}" "$@"
