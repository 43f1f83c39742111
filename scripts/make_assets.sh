#!/usr/bin/env bash
# Remakes the reference cases in assets/cases for the demo scene (the
# built-in procedural scene with default options; reference = training view 0):
# - demo_repaint: the scene's ground-truth stylized twin at that view (an exact repaint);
# - demo_painterly: a loose painterly repaint of the photo (`refnpr paint`).
set -euo pipefail
cd "$(dirname "$0")/.."
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
cargo run --quiet -- scene --out "$tmp/scene"
cp "$tmp/scene/stylized/train/r_0.png" assets/cases/demo_repaint/style.png
cargo run --quiet -- paint --input "$tmp/scene/train/r_0.png" --out assets/cases/demo_painterly/style.png --seed 7
