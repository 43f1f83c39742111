#!/usr/bin/env bash
# `refnpr lpips` against the numpy reference (scripts/lpips_reference.py,
# float64, written from LPIPS's formula) on real image pairs, both nets:
# fails when any pair differs by more than 1e-4. Prints the agreement
# table (markdown) and writes it to OUT/lpips_agreement.md.
#   scripts/check_lpips.sh BIN OUT [DATA]
# DATA (default ../shared/data): lego and fern pairs, and each against a
# `refnpr paint --seed 7` repaint of itself; without it, the fixture pair
# and repaints of it only.
set -euo pipefail
cd "$(dirname "$0")/.."
bin=${1:?usage: scripts/check_lpips.sh BIN OUT [DATA]}
out=${2:?usage: scripts/check_lpips.sh BIN OUT [DATA]}
data=${3:-../shared/data}
mkdir -p "$out"
pairs="$out/pairs.txt"
: > "$pairs"
fixture=tests/fixtures/lpips
"$bin" paint --input "$fixture/a.png" --out "$out/fixture_painted.png" --seed 7 >/dev/null
echo "$fixture/a.png $fixture/b.png" >> "$pairs"
echo "$fixture/a.png $out/fixture_painted.png" >> "$pairs"
lego="$data/nerf_synthetic/lego"
fern="$data/nerf_llff_data/fern/images_8"
if [ -d "$lego" ] && [ -d "$fern" ]; then
  "$bin" paint --input "$lego/test/r_0.png" --out "$out/lego_painted.png" --seed 7 >/dev/null
  "$bin" paint --input "$fern/image000.png" --out "$out/fern_painted.png" --seed 7 >/dev/null
  {
    echo "$lego/test/r_0.png $lego/test/r_8.png"
    echo "$lego/train/r_0.png $lego/test/r_0.png"
    echo "$lego/test/r_0.png $out/lego_painted.png"
    echo "$fern/image000.png $fern/image001.png"
    echo "$fern/image000.png $out/fern_painted.png"
  } >> "$pairs"
else
  echo "check_lpips: $data has no lego and fern: the fixture pairs only" >&2
fi

table="$out/lpips_agreement.md"
echo "| pair | net | refnpr lpips | numpy reference | difference |" > "$table"
echo "| --- | --- | --- | --- | --- |" >> "$table"
worst=0
for net in vgg alex; do
  python3 scripts/lpips_reference.py --pairs "$pairs" --net "$net" > "$out/numpy_$net.txt"
  while read -r a b reference; do
    ours=$("$bin" lpips "$a" "$b" --net "$net")
    diff=$(python3 -c "print(f'{abs($ours - $reference):.2e}')")
    echo "| ${a#"$data"/} / ${b#"$data"/} | $net | $ours | $reference | $diff |" >> "$table"
    worst=$(python3 -c "print(max($worst, abs($ours - $reference)))")
  done < "$out/numpy_$net.txt"
done
cat "$table"
echo "largest difference: $worst"
python3 -c "import sys; sys.exit(0 if $worst <= 1e-4 else 1)" || {
  echo "error: refnpr lpips differs from the numpy reference by $worst (> 1e-4)" >&2
  exit 1
}
