#!/usr/bin/env bash
# Chooses greedy decoding's face beam on a tuning set that no reported figure uses: 60
# procedural shapes from seed 20261122 (neither a training stream's seed nor the held-aside
# one), reconstructed from their points at each beam width and scored with `meshstream eval`.
# Usage: scripts/sweep-face-beam.sh [MODEL_DIR] [OUT_DIR] [WIDTHS...]
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-models/default}
out=${2:-target/sweep-face-beam}
shift $(($# < 2 ? $# : 2))
widths=("${@:-1 2 4 8 16}")
target="${CARGO_TARGET_DIR:-target}/release"
cargo build --release --quiet --bin meshstream --bin meshstream-train

"$target/meshstream-train" shapes -o "$out/gt" -n 60 --seed 20261122 >/dev/null
for beam in ${widths[*]}; do
  mkdir -p "$out/beam-$beam"
  for f in "$out/gt"/*.ply; do
    name=$(basename "$f" .ply)
    RAYON_NUM_THREADS=1 "$target/meshstream" reconstruct "$f" -o "$out/beam-$beam/$name.obj" \
      --model "$model" --face-beam "$beam" 2>/dev/null || echo "no reconstruction for $name" >&2
  done
  echo "== face beam $beam"
  "$target/meshstream" eval --pred "$out/beam-$beam" --gt "$out/gt" | tail -n 4
done
