#!/usr/bin/env bash
# The model against the convex hull on procedural shapes it never trained on (the trainers'
# held-aside seed): 100 shapes of every kind, and 60 simple primitives. The hull is built from
# the points a reconstruction is judged and fitted against (16,384 per shape; the encoder takes
# 1,024 of its own); `meshstream eval` scores them (DESIGN.md's CD/HD).
# Usage: scripts/evaluate-procedural.sh [MODEL_DIR] [OUT_DIR] [RECONSTRUCT FLAGS...]
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-models/default}
out=${2:-target/eval-procedural}
shift $(($# < 2 ? $# : 2))
target="${CARGO_TARGET_DIR:-target}/release"
cargo build --release --quiet --bin meshstream --bin meshstream-train

# The shapes' flat polygons are split for the model's grid, as its training targets were.
levels=$(grep -o '"quant_levels": *[0-9]*' "$model/config.json" | grep -o '[0-9]*$')
"$target/meshstream-train" shapes -o "$out/all/gt" -n 100 --levels "$levels"
"$target/meshstream-train" shapes -o "$out/primitives/gt" -n 60 --primitives --levels "$levels"
for set in all primitives; do
  mkdir -p "$out/$set/model" "$out/$set/hull"
  for f in "$out/$set/gt"/*.ply; do
    name=$(basename "$f" .ply)
    RAYON_NUM_THREADS=1 "$target/meshstream" reconstruct "$f" -o "$out/$set/model/$name.glb" \
      --model "$model" "$@" 2>/dev/null || echo "no reconstruction for $name" >&2
    "$target/meshstream" baseline --method hull "$f" -o "$out/$set/hull/$name.glb" 2>/dev/null \
      || echo "no hull for $name" >&2
  done
  for method in model hull; do
    echo "== $set: $method"
    "$target/meshstream" eval --pred "$out/$set/$method" --gt "$out/$set/gt" | tail -n 6
  done
done
