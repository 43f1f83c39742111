#!/usr/bin/env bash
# Kills a stylization with SIGKILL at N random moments and resumes it each
# time; every resumed field must equal the uninterrupted run's, bit for bit.
#
#   scripts/kill_resume.sh PHOTO_RUN CASE CONFIG.toml N WORK_DIR
#
# Moment k is drawn uniformly in the k-th of N equal slices of the
# uninterrupted run's duration, so the kills spread over the refit, the
# image epochs and the smooth update. Prints, per kill: when, the phase it
# hit (the run's last progress line), the resume point it found, and the
# SHA-256 of the resumed field (the checkpoint's grid bytes).
set -euo pipefail
cd "$(dirname "$0")/.."
photo=${1:?usage: scripts/kill_resume.sh PHOTO_RUN CASE CONFIG.toml N WORK_DIR}
case_dir=${2:?}; config=${3:?}; n=${4:?}; work=${5:?}
# REFNPR_BIN: a binary to use instead of building this checkout's.
bin=${REFNPR_BIN:-}
if [ -z "$bin" ]; then
  cargo build -q --bin refnpr
  bin=target/debug/refnpr
fi
mkdir -p "$work"

# The grid bytes of a checkpoint (its metadata holds the run's duration).
field_hash() {
  python3 - "$1" <<'EOF'
import hashlib, struct, sys
b = open(sys.argv[1], "rb").read()
n = struct.unpack("<Q", b[8:16])[0]
print(hashlib.sha256(b[16 + n:]).hexdigest())
EOF
}

stylize() { # OUT [--resume]
  "$bin" stylize --run "$photo" --reference "$case_dir" --config "$config" --no-render --backend flex --out "$@"
}

rm -rf "$work/whole"
start=$(date +%s.%N)
stylize "$work/whole" > "$work/whole.log" 2>&1
total=$(python3 -c "print(round($(date +%s.%N) - $start, 1))")
whole=$(field_hash "$work/whole/checkpoint.bin")
echo "uninterrupted: ${total} s, field $whole"

same=0
for k in $(seq 1 "$n"); do
  out="$work/killed_$k"
  rm -rf "$out"
  at=$(python3 -c "import random; print(round($total * ($k - 1 + random.random()) / $n, 1))")
  # exec: the background job's pid is refnpr's own, the process killed.
  (exec "$bin" stylize --run "$photo" --reference "$case_dir" --config "$config" --no-render --backend flex \
    --out "$out" > "$out.log" 2>&1) &
  pid=$!
  sleep "$at"
  kill -9 "$pid" 2>/dev/null || true
  wait "$pid" 2>/dev/null || true
  phase=$(tr '\r' '\n' < "$out.log" | grep -v '^\s*$' | tail -1 | cut -c1-90)
  point=$([ -f "$out/resume.bin" ] && echo present || echo "none (starts again)")
  stylize "$out" --resume > "$out.resume.log" 2>&1
  resumed_at=$(grep -o 'after image step [0-9]*' "$out.resume.log" | head -1 || true)
  h=$(field_hash "$out/checkpoint.bin")
  [ "$h" = "$whole" ] && same=$((same + 1))
  echo "kill $k at ${at} s | last line: ${phase} | resume.bin: ${point} ${resumed_at} | field $h"
done
echo "$same of $n resumed fields equal the uninterrupted one"
[ "$same" -eq "$n" ]
