#!/usr/bin/env bash
# The paper's comparison and ablations on one scene:
#   scripts/compare.sh procedural [OUT]   the demo scene, scored against its stylized twin
#   scripts/compare.sh lego [OUT]         ../shared/data/nerf_synthetic/lego
#   scripts/compare.sh fern [OUT]         ../shared/data/nerf_llff_data/fern
# Rows: Ref-NPR, ARF, Ref-NPR with the authors' settings (`--preset
# authors`), Ref-NPR and ARF with torchvision's VGG16 (`[vgg] weights =
# "torchvision"`: rows torchvision, arf_torchvision), and Ref-NPR without
# L_ref / with reference rays only / without L_feat / without L_color /
# without the smooth update. Reference: training view 0 (procedural: the
# stylized twin's view, an exact repaint; real scenes: `refnpr paint` over
# the content render). Existing runs in OUT are reused, so an interrupted
# comparison resumes (a row killed midway from its resume.bin). EPOCHS=N
# shortens every stylization; BACKEND picks the backend (default flex);
# ROWS="refnpr arf" runs a subset; SIZE=192 renders the procedural scene at
# 192x192 (default 96); BIN=path uses that binary instead of building one
# (a copy keeps a long comparison on one binary while the tree is rebuilt).
# Writes OUT/table.md with the rows that have results.
set -euo pipefail
cd "$(dirname "$0")/.."
scene=${1:?usage: scripts/compare.sh procedural|lego|fern [OUT]}
out=${2:-compare-$scene}
backend=${BACKEND:-flex}
shared=${REFNPR_SHARED_DATA:-../shared/data}
mkdir -p "$out"
if [ -n "${BIN:-}" ]; then bin=$BIN; else cargo build --quiet; bin=target/debug/refnpr; fi
epochs=()
[ -n "${EPOCHS:-}" ] && epochs=(--image-epochs "$EPOCHS")

gt=()
case "$scene" in
  procedural)
    [ -d "$out/scene" ] || $bin scene --out "$out/scene" --size "${SIZE:-96}"
    data="$out/scene"
    train_config=(--config configs/demo.toml)
    gt=(--gt "$out/scene/stylized")
    ;;
  lego) data="$shared/nerf_synthetic/lego"; train_config=() ;;
  fern) data="$shared/nerf_llff_data/fern"; train_config=() ;;
  *) echo "unknown scene $scene (procedural, lego or fern)" >&2; exit 2 ;;
esac

[ -f "$out/photo/checkpoint.bin" ] || $bin train --data "$data" --out "$out/photo" --backend "$backend" "${train_config[@]}"

if [ ! -f "$out/case/style.png" ]; then
  if [ "$scene" = procedural ]; then
    mkdir -p "$out/case"
    cp assets/cases/demo_repaint/reference.toml "$out/case/"
    cp "$out/scene/stylized/train/r_0.png" "$out/case/style.png"
  else
    $bin reference --run "$out/photo" --view train:0 --out "$out/case"
    $bin paint --input "$out/case/content.png" --out "$out/case/style.png" --seed 7
  fi
fi

all_rows=(refnpr arf torchvision arf_torchvision authors no_reference reference_rays_only no_feature no_colour no_smooth)
read -r -a rows <<< "${ROWS:-${all_rows[*]}}"
for row in "${rows[@]}"; do
  run="$out/$row"
  if [ ! -f "$run/stylize.json" ]; then
    case "$row" in
      refnpr) extra=() ;;
      arf) extra=(--method arf) ;;
      authors) extra=(--preset authors) ;;
      torchvision) extra=(--config configs/vgg_torchvision.toml) ;;
      arf_torchvision) extra=(--method arf --config configs/vgg_torchvision.toml) ;;
      *) extra=(--config "configs/ablations/$row.toml") ;;
    esac
    # A row killed midway continues from its resume.bin.
    [ -f "$run/resume.bin" ] && extra+=(--resume)
    echo "== $row" >&2
    $bin stylize --run "$out/photo" --reference "$out/case" --out "$run" --backend "$backend" --no-render "${extra[@]}" "${epochs[@]}"
  fi
  [ -f "$run/eval.json" ] || $bin eval --run "$run" --reference "$out/case" "${gt[@]}" --backend "$backend" --out "$run/eval.json" > /dev/null
done

python3 - "$out" "${all_rows[@]}" <<'EOF'
import json, os, sys
out, rows = sys.argv[1], [r for r in sys.argv[2:] if os.path.exists(f"{sys.argv[1]}/{r}/eval.json")]
names = {"refnpr": "Ref-NPR", "arf": "ARF", "torchvision": "Ref-NPR, torchvision VGG16", "arf_torchvision": "ARF, torchvision VGG16", "authors": "Ref-NPR, the authors' settings", "no_reference": "Ref-NPR w/o L_ref", "reference_rays_only": "Ref-NPR, reference rays only",
         "no_feature": "Ref-NPR w/o L_feat", "no_colour": "Ref-NPR w/o L_color", "no_smooth": "Ref-NPR w/o smooth update"}
fmt = lambda v, d=2: "-" if v is None else f"{v:.{d}f}"
lines = ["| method | gt_psnr | seen | unseen | near | far | Ref-LPIPS (vgg) | Ref-LPIPS (alex) | uncalibrated | at the reference: LPIPS, PSNR | texture at ref / near / far (tinted photo) | speckle (path) | stability (1 / 7 frames) | time |",
         "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
for r in rows:
    e = json.load(open(f"{out}/{r}/eval.json"))
    s = json.load(open(f"{out}/{r}/stylize.json"))
    st = " / ".join(fmt(x["rmse"], 4) for x in e["stability"])
    psnrs = " | ".join(fmt(e.get(k)) for k in ["gt_psnr", "gt_psnr_seen", "gt_psnr_occluded", "gt_psnr_near", "gt_psnr_far"])
    # The painting held at its own camera (each reference), and the texture figure (eval::texture).
    held = "; ".join(f"{fmt(v['lpips'], 3)}, {fmt(v['psnr'])} dB" for v in e.get("reference_views", [])) or "-"
    t = e.get("texture")
    tex = "-" if t is None else f"{fmt(t['at_reference'], 3)} / {fmt(t['near'], 3)} / {fmt(t['far'], 3)} ({fmt(t.get('tinted_photo'), 3)})"
    lines.append(f"| {names[r]} | {psnrs} | {fmt(e['ref_lpips'], 4)} | {fmt(e.get('ref_lpips_alex'), 4)} | {fmt(e.get('ref_lpips_uncalibrated'), 4)} | {held} | {tex} | {100 * e['speckle']:.2f} % | {st} | {s['total_seconds'] / 60:.1f} min |")
table = "\n".join(lines) + "\n"
open(f"{out}/table.md", "w").write(table)
print(table)
EOF
