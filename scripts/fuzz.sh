#!/usr/bin/env bash
# A long fuzz run of one target: scripts/fuzz.sh TARGET SECONDS [SEED]
# Targets: `refnpr fuzz --help` lists them (every parser of outside input, and cli).
# Prints a JSON report (inputs tried, crashes grouped by place, slowest case,
# peak memory); exits non-zero on any panic (the input is saved under
# $TMPDIR/refnpr-fuzz-crashes) or hang (status 3).
set -euo pipefail
cd "$(dirname "$0")/.."
target=${1:?usage: scripts/fuzz.sh TARGET SECONDS [SEED]}
seconds=${2:?usage: scripts/fuzz.sh TARGET SECONDS [SEED]}
seed=${3:-1}
cargo build -q --bin refnpr
exec target/debug/refnpr fuzz "$target" --seconds "$seconds" --seed "$seed"
