#!/usr/bin/env bash
# Local edits on the procedural scene, measured per object: objects graded
# in a reference view and nothing else painted, stylized with
# `region = "difference"` ("local") and without a region ("whole": the
# painting as a whole, as before local edits), each against the scene with
# only those objects graded (`refnpr recolour --objects`) and, for the other
# objects, against the photoreal field's renders
# (scripts/local_edit_figures.py).
#
# usage: scripts/local_edit.sh BIN OUT [EDITS] [SIZE] [PRESET]
#   EDITS   one or more OBJECT@VIEW:GRADE, comma-separated, one reference each
#           (default 2@0:hue: the sphere in training view 0, hues rotated;
#           two styles on two objects: 2@0:hue,3@5:teal-orange)
#   SIZE    the scene's pixels (default 64); PRESET the stylize preset (default fast)
set -euo pipefail
BIN=$1 OUT=$2 EDITS=${3:-2@0:hue} SIZE=${4:-64} PRESET=${5:-fast}
mkdir -p "$OUT"
[ -d "$OUT/scene" ] || "$BIN" scene --out "$OUT/scene" --size "$SIZE"
[ -f "$OUT/photo/checkpoint.bin" ] || "$BIN" train --data "$OUT/scene" --out "$OUT/photo" --config configs/demo.toml
[ -d "$OUT/photo_test" ] || "$BIN" render --run "$OUT/photo" --path test --out "$OUT/photo_test" >/dev/null
rm -rf "$OUT/case_whole" "$OUT/case_local" "$OUT/graded" "$OUT/graded_"*
mkdir -p "$OUT/case_whole" "$OUT/case_local"
truth="$OUT/scene" objects="" views=""
IFS=, read -ra parts <<<"$EDITS"
for i in "${!parts[@]}"; do
  object=${parts[$i]%%@*} rest=${parts[$i]#*@}
  view=${rest%%:*} grade=${rest#*:}
  "$BIN" reference --run "$OUT/photo" --view "train:$view" --out "$OUT/ref_$i" >/dev/null
  "$BIN" paint --input "$OUT/ref_$i/content.png" --out "$OUT/case_local/style_$i.png" --grade "$grade" \
    --objects "$object" --ids "$OUT/scene/train/r_${view}_id.png" >/dev/null
  cp "$OUT/case_local/style_$i.png" "$OUT/case_whole/"
  for v in whole local; do
    printf '[[reference]]\nstyle = "style_%s.png"\nview = "train:%s"\n' "$i" "$view" >>"$OUT/case_$v/reference.toml"
  done
  echo 'region = "difference"' >>"$OUT/case_local/reference.toml"
  "$BIN" recolour --data "$truth" --out "$OUT/graded_$i" --grade "$grade" --objects "$object" >/dev/null
  truth="$OUT/graded_$i" objects="$objects${objects:+,}$object" views="$views${views:+,}$view"
  echo "reference $i: object $object painted ($grade) in training view $view"
done
for v in whole local; do
  if [ ! -f "$OUT/$v/stylize.json" ]; then
    /usr/bin/time -f "$v: %e s, peak %M KB" "$BIN" stylize --run "$OUT/photo" --reference "$OUT/case_$v" \
      --out "$OUT/$v" --preset "$PRESET" 2>&1 | grep -E "local edit|s, peak" || true
  fi
  echo "== $v (region: $([ "$v" = local ] && echo difference || echo none))"
  python3 scripts/local_edit_figures.py "$OUT/scene" "$truth" "$OUT/photo_test/rgb" "$OUT/$v/test/rgb" "$objects" "$views"
done
