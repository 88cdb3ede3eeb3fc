#!/usr/bin/env bash
# The quality cost of quantized inference: reconstructs a subset of the lowpoly dev split with
# the model in f32, q8_0 and q4k (same seed, same input points), then scores each against the
# ground truth and pairs it with f32 (`meshstream eval --against`: CD/HD, faces right, and the
# mean paired CD difference with its standard error).
# Usage: scripts/evaluate-quantized.sh [EVERY] [MODEL_DIR] [OUT_DIR] [RECONSTRUCT FLAGS...]
#   EVERY: take every EVERY-th dev mesh in name order (default 5: 44 of 220).
# DATA=DIR names the shared data folder when it is not ../shared/data.
set -euo pipefail
cd "$(dirname "$0")/.."
every=${1:-5}
model=${2:-models/default}
out=${3:-target/eval-quantized}
shift $(($# < 3 ? $# : 3))
data=${DATA:-../shared/data}
bin="${CARGO_TARGET_DIR:-target}/release/meshstream"
cargo build --release --quiet --locked --bin meshstream

mkdir -p "$out/gt"
awk -F, 'NR > 1 && $8 == "dev" { print $1 }' "$data/lowpoly/manifest.csv" | sort \
  | awk -v every="$every" '(NR - 1) % every == 0' | while read -r f; do
  ln -sf "$(realpath "$data/lowpoly/$f")" "$out/gt/$f"
done
echo "$(ls "$out/gt" | wc -l) dev meshes (every $every-th)"
for q in f32 q8_0 q4k; do
  mkdir -p "$out/$q"
  for f in "$out"/gt/*.ply; do
    name=$(basename "$f" .ply)
    RAYON_NUM_THREADS=1 "$bin" reconstruct "$f" -o "$out/$q/$name.glb" --model "$model" \
      --quantize "$q" "$@" 2>/dev/null || echo "no reconstruction for $name ($q)" >&2
  done
done
for q in q8_0 q4k; do
  echo "== $q against f32"
  "$bin" eval --pred "$out/$q" --gt "$out/gt" --against "$out/f32" | sed -n '/^| set /,$p'
done
