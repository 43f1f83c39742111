#!/usr/bin/env bash
# The test suite on every backend (the README's test command).
#   flex:    everything (unit tests, renderer, datasets, training, stylization, evaluation, demo, CLI), then examples/orbit.rs
#            and the README's quick start (scripts/check_docs.py: also the README's length and every doc link)
#   ndarray: renderer, grid, VGG16, the stylization losses / TCM / deferred back-propagation, the metrics, the notebook API
#   wgpu:    renderer, training, VGG16 (without its real-weight test), metrics, the notebook API and its whole pipeline, through Mesa's software Vulkan when no GPU is present
#   (end-to-end stylization and the demo run on flex only: VGG on lavapipe or ndarray is 10-100x slower)
#   exports: the example's runs as splats and a mesh, opened in headless Chromium (npm viewers) and trimesh
#   real data (../shared/data: lego, fern): loaders and a short fit, when that folder exists
#   LPIPS: `refnpr lpips` against the numpy reference (scripts/lpips_reference.py) on real image pairs, both nets
set -euo pipefail
cd "$(dirname "$0")/.."
# wgpu (winit) warns when this is unset on headless machines.
export XDG_RUNTIME_DIR="${XDG_RUNTIME_DIR:-/tmp}"
# The tests' runs go to a cost ledger of their own, not the user's
# (~/.cache/refnpr/costs.jsonl), whose estimates they would skew.
REFNPR_COSTS="$(mktemp -d)/costs.jsonl"
export REFNPR_COSTS
# Each stage prints the seconds since the suite started, so a CI log shows
# where its time went (CI stops at 90 minutes).
stage() { echo "== $* [${SECONDS} s]"; }

stage "formatting"
cargo fmt --check
stage "layering (imports point down the stage table of src/lib.rs)"
python3 scripts/check_layers.py
stage "docs: README.md at most 300 lines, every relative link in README.md and docs/ resolving"
python3 scripts/check_docs.py
stage "dependency tree: licences, bans, sources (cargo-deny, deny.toml)"
command -v cargo-deny >/dev/null 2>&1 || {
  echo "error: cargo-deny not found (install it with: cargo install --locked cargo-deny)" >&2
  exit 1
}
cargo deny --log-level error check licenses bans sources
stage "features: the test build and the plain build (binary, notebooks) compile each dependency once"
python3 scripts/check_features.py
# Lints: clippy is the compiler of our own crate in every build below (what
# `cargo clippy` itself does: cargo's RUSTC_WORKSPACE_WRAPPER), so the
# tests' build is the lint pass too, over every target and backend, without
# a second (check) build of all the dependencies.
RUSTC_WORKSPACE_WRAPPER="$(command -v clippy-driver)" || {
  echo "error: clippy-driver not found (install it with: rustup component add clippy)" >&2
  exit 1
}
export RUSTC_WORKSPACE_WRAPPER
export CLIPPY_ARGS="-D__CLIPPY_HACKERY__warnings__CLIPPY_HACKERY__"

stage "flex: full suite"
REFNPR_BACKEND=flex cargo test --all-targets

stage "the front API's example: procedural scene to stylized orbit (flex)"
REFNPR_BACKEND=flex cargo run --example orbit -- target/example-orbit
test -s target/example-orbit/orbit/path.gif

stage "the README's quick start, its commands read from README.md and run as written (flex)"
rm -rf demo-out
REFNPR_BACKEND=flex python3 scripts/check_docs.py --run-quickstart
test -s demo-out/eval.json && test -s demo-out/stylized/splats.ply && test -s demo-out/site/index.html
rm -rf demo-out

stage "exports in other tools: splats in a browser splat renderer, the mesh in three.js and trimesh (the example's runs)"
BIN="target/${CARGO_BUILD_TARGET:+$CARGO_BUILD_TARGET/}debug/refnpr"
bash scripts/check_exports.sh "$BIN" target/example-orbit/photo target/example-orbit/stylized
stage "refnpr view in a browser: the page against refnpr render, the static copy, a live reload (the example's runs; a 360° twin's field with a far background)"
rm -rf target/far-twin
"$BIN" scene --out target/far-twin/scene --environment --size 48 >/dev/null
"$BIN" train --data target/far-twin/scene --out target/far-twin/photo --steps 300 --config configs/far_background.toml >/dev/null
bash scripts/check_view.sh "$BIN" target/example-orbit/stylized target/example-orbit/photo target/far-twin/photo
stage "checkpoints read without refnpr (Python's safetensors and numpy)"
python3 scripts/check_checkpoint.py target/example-orbit/photo/checkpoint.bin target/example-orbit/stylized/checkpoint.bin target/far-twin/photo/checkpoint.bin

stage "docs: the library's rustdoc, warnings (broken links included) denied"
RUSTDOCFLAGS="-D warnings" cargo doc --no-deps --lib --quiet
stage "doc examples (compiled; run unless marked no_run)"
REFNPR_BACKEND=flex cargo test --doc

STYLIZE_UNITS=(--skip tiny_scene --skip arf_baseline --skip bad_input --skip robustness --skip a_killed_stylization --skip a_far_background)

stage "ndarray: renderer, grid, VGG16, stylization units, metrics"
REFNPR_BACKEND=ndarray cargo test --test renderer --test vgg --test evaluation --test notebook --lib
REFNPR_BACKEND=ndarray cargo test --test stylize -- "${STYLIZE_UNITS[@]}"

stage "wgpu: renderer, training, VGG16, metrics, the whole pipeline"
# On lavapipe (2 CPU cores) the stylization units took 1303 s and VGG16's
# real-weight test over 100 s, past what CI allows (90 min for everything):
# they run on flex and ndarray above, and wgpu's stylization is checked end
# to end by the notebook test's whole pipeline against a CPU backend's (its
# staged VGG16 forward by vgg's own wgpu tolerance).
REFNPR_BACKEND=wgpu cargo test --test renderer --test training --test evaluation --test notebook
REFNPR_BACKEND=wgpu cargo test --test vgg -- --skip real_weights_match_objects_across_views
# The plain-Rust kernels against the Burn graph (unit tests inside the crate).
REFNPR_BACKEND=wgpu cargo test --lib graph_oracle

DATA="${REFNPR_SHARED_DATA:-../shared/data}"
if [ -d "$DATA/nerf_synthetic/lego" ] && [ -d "$DATA/nerf_llff_data/fern" ]; then
  stage "real data group ($DATA)"
  REFNPR_SHARED_DATA="$DATA" REFNPR_BACKEND=flex cargo test --test real_data -- --ignored
else
  stage "real data group NOT RUN: $DATA/{nerf_synthetic/lego,nerf_llff_data/fern} not found"
fi
stage "LPIPS: refnpr lpips against the numpy reference on real image pairs, vgg and alex (within 1e-4)"
REFNPR_BACKEND=flex bash scripts/check_lpips.sh "$BIN" target/lpips-check "$DATA"
stage "suite done"
