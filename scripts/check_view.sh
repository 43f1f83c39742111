#!/usr/bin/env bash
# `refnpr view` in a real browser (part of the test command):
#   - the page served by `refnpr view`, shot in headless Chromium (WebGL2 on
#     SwiftShader) at the test cameras, against `refnpr render` of the same
#     cameras: a stylized run (SH 0) and a photoreal one;
#   - the static copy (`--static DIR`) behind Python's plain file server,
#     shot again: the same pixels as the served page;
#   - the controls: a drag moves the view, the camera list and a click on a
#     drawn camera show that dataset camera exactly, the comparison splits
#     the two runs at the slider;
#   - live reload: a served run's checkpoint replaced (as a fit in progress
#     replaces it) must reach the page, which then shows the new field.
#   - a run with a far background (FAR_RUN), shot the same way;
#   bash scripts/check_view.sh REFNPR_BINARY STYLIZED_RUN PHOTO_RUN [FAR_RUN]
set -euo pipefail
cd "$(dirname "$0")/.."
BIN="$(realpath "$1")"
STYLIZED="$(realpath "$2")"
PHOTO="$(realpath "$3")"
# The page's arithmetic is refnpr's; what separates them is f16 SH
# coefficients, GPU exp/division rounding and 8-bit output (the example's
# runs measure 77-79 dB): floors far under that, far over a misplaced camera.
STYLIZED_FLOOR=35
PHOTO_FLOOR=30

(cd scripts/browser && PUPPETEER_SKIP_DOWNLOAD=1 npm ci --silent --no-audit --no-fund)
OUT="$(mktemp -d)"
PIDS=()
trap 'kill "${PIDS[@]}" 2>/dev/null || true; wait 2>/dev/null || true; rm -rf "$OUT"' EXIT
above() { python3 -c "import json,sys; m=json.load(open('$1'))['mean']; print(f'{m:.2f} dB'); sys.exit(0 if m >= $2 else 1)"; }
# Starts a server in the background (killed on exit) and sets $url once it
# listens. Not called in $(...): the server's PID must reach this shell.
start() {
  local log="$1"; shift
  "$@" >"$log" 2>&1 &
  PIDS+=($!)
  for _ in $(seq 100); do
    url="$(grep -o 'http://[0-9.:]*/' "$log" | head -1 || true)"
    [ -n "$url" ] && return
    sleep 0.2
  done
  echo "error: $* did not start: $(cat "$log")" >&2
  exit 1
}

"$BIN" export "$STYLIZED" --format cameras --out "$OUT/cameras.json" >/dev/null
for name in stylized photo; do
  run="$STYLIZED"; [ $name = photo ] && run="$PHOTO"
  "$BIN" render --run "$run" --path test --out "$OUT/render-$name" >/dev/null
done

start "$OUT/server.log" "$BIN" view "$STYLIZED" "$PHOTO" --port 0
for i in 0 1; do
  name=stylized; floor=$STYLIZED_FLOOR; size=800
  [ $i = 1 ] && name=photo && floor=$PHOTO_FLOOR && size=0
  controls=(); [ $i = 0 ] && controls=(--controls)
  node scripts/browser/view.mjs "$url" "$OUT/cameras.json" "$OUT/shots-$name" --run $i --frame-size $size "${controls[@]}"
  python3 scripts/browser/compare.py "$OUT/shots-$name" "$OUT/render-$name/rgb" --json "$OUT/$name.json" | tail -1
  mean="$(above "$OUT/$name.json" $floor)" || { echo "error: $name run in refnpr view: $mean, below the floor $floor" >&2; exit 1; }
  echo "$name run in refnpr view: $mean against refnpr render (floor $floor)"
done

# A field with a far background (a 360° capture's): the page reads the far
# map in each ray's direction, as refnpr's renderer does.
if [ -n "${4:-}" ]; then
  FAR="$(realpath "$4")"
  "$BIN" export "$FAR" --format cameras --out "$OUT/cameras-far.json" >/dev/null
  "$BIN" render --run "$FAR" --path test --out "$OUT/render-far" >/dev/null
  start "$OUT/far.log" "$BIN" view "$FAR" --port 0
  node scripts/browser/view.mjs "$url" "$OUT/cameras-far.json" "$OUT/shots-far" --run 0 --frame-size 0
  python3 scripts/browser/compare.py "$OUT/shots-far" "$OUT/render-far/rgb" --json "$OUT/far.json" | tail -1
  mean="$(above "$OUT/far.json" $PHOTO_FLOOR)" || { echo "error: the far-background run in refnpr view: $mean, below the floor $PHOTO_FLOOR" >&2; exit 1; }
  echo "far-background run in refnpr view: $mean against refnpr render (floor $PHOTO_FLOOR)"
fi

"$BIN" view "$STYLIZED" --static "$OUT/site"
start "$OUT/static.log" python3 -u -m http.server --bind 127.0.0.1 --directory "$OUT/site" 0
node scripts/browser/view.mjs "$url" "$OUT/cameras.json" "$OUT/shots-static" --frame-size 0
python3 scripts/browser/compare.py "$OUT/shots-static" "$OUT/shots-stylized" --json "$OUT/static.json" | tail -1
mean="$(above "$OUT/static.json" 99)" || { echo "error: the static copy renders other pixels than the served page: $mean" >&2; exit 1; }
echo "static copy behind a plain file server: the served page's pixels ($mean, 100 = identical)"

mkdir -p "$OUT/live"
cp "$PHOTO/checkpoint.bin" "$OUT/live/checkpoint.bin"
start "$OUT/live.log" "$BIN" view "$OUT/live" --port 0
node scripts/browser/view.mjs "$url" "$OUT/cameras.json" "$OUT/shots-live" --frame-size 0 \
  --live "$STYLIZED/checkpoint.bin" "$OUT/live/checkpoint.bin"
python3 scripts/browser/compare.py "$OUT/shots-live/live" "$OUT/render-stylized/rgb" --json "$OUT/live.json" | tail -1
mean="$(above "$OUT/live.json" $STYLIZED_FLOOR)" || { echo "error: after the live reload the page does not show the new checkpoint: $mean" >&2; exit 1; }
echo "live: a replaced checkpoint reached the page, which shows it ($mean against the new field's render)"
