#!/usr/bin/env bash
# The artist's controls on a painted scene, each beside the plain run:
# `--preserve-colour`, `--style-strength A`, `--stroke-scale S`, measured
# against the photoreal field's test renders (scripts/control_figures.py:
# colour, chroma and luminance distance, and the painting's stroke
# frequency).
#
# usage: scripts/controls.sh BIN OUT DATA [RUNS] [PRESET]
#   DATA    a scene folder (../shared/data/nerf_synthetic/lego, .../fern, or a `refnpr scene`)
#   RUNS    comma-separated, each `plain` or a control:
#           preserve, strength=A, stroke=S (default plain,preserve,strength=0.5)
#   PRESET  the stylize preset (default fast)
# The reference is training view 0 painted with `refnpr paint --seed 7`.
# Existing runs in OUT are reused.
set -euo pipefail
BIN=$1 OUT=$2 DATA=$3 RUNS=${4:-plain,preserve,strength=0.5} PRESET=${5:-fast}
mkdir -p "$OUT"
[ -f "$OUT/photo/checkpoint.bin" ] || "$BIN" train --data "$DATA" --out "$OUT/photo"
[ -d "$OUT/photo_test" ] || "$BIN" render --run "$OUT/photo" --path test --out "$OUT/photo_test" >/dev/null
if [ ! -f "$OUT/case/style.png" ]; then
  "$BIN" reference --run "$OUT/photo" --view train:0 --out "$OUT/case" >/dev/null
  "$BIN" paint --input "$OUT/case/content.png" --out "$OUT/case/style.png" --seed 7 >/dev/null
fi
IFS=, read -ra runs <<<"$RUNS"
for run in "${runs[@]}"; do
  case "$run" in
    plain) flags=() ;;
    preserve) flags=(--preserve-colour) ;;
    strength=*) flags=(--style-strength "${run#strength=}") ;;
    stroke=*) flags=(--stroke-scale "${run#stroke=}") ;;
    *) echo "unknown run $run (plain, preserve, strength=A, stroke=S)" >&2; exit 2 ;;
  esac
  if [ ! -f "$OUT/$run/stylize.json" ]; then
    /usr/bin/time -f "$run: %e s, peak %M KB" "$BIN" stylize --run "$OUT/photo" --reference "$OUT/case" \
      --out "$OUT/$run" --preset "$PRESET" "${flags[@]}" 2>&1 | grep -E "s, peak" || true
  fi
done
python3 scripts/control_figures.py "$OUT/photo_test/rgb" "$OUT" "${runs[@]}"
