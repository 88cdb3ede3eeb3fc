#!/usr/bin/env bash
# What issue 4 asks of a model: greedy decoding (unfitted) rebuilding boxes, prisms and
# pyramids from their points with every face right. Counts it on the held-aside ones (the 31
# of `meshstream-train shapes -n 60 --primitives`) and on a tuning set (the 111 of
# `shapes -n 240 --primitives --seed 20261122`) at several point-sampling seeds, because the
# count moves with where the encoder's points fall (docs/decisions.md, "Even encoder points").
# FIT_ROUNDS=40 counts them with the corners fitted to the points, as `meshstream reconstruct`
# does by default (the faces stay the model's; their corners move onto the points).
# CANDIDATES=N decodes N greedy meshes, each from its own draw of the points, and keeps the one
# that ends closest to them: what `meshstream reconstruct --temperature 0` makes with N = 4.
# Usage: [FIT_ROUNDS=N] [CANDIDATES=N] scripts/greedy-rebuilds.sh [MODEL_DIR] [OUT_DIR] [SEEDS...] (seeds 0-4
# by default, no fitting by default)
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-models/default}
out=${2:-target/greedy-rebuilds}
shift $(($# < 2 ? $# : 2))
seeds=${*:-0 1 2 3 4}
fit_rounds=${FIT_ROUNDS:-0}
candidates=${CANDIDATES:-1}
target="${CARGO_TARGET_DIR:-target}/release"
cargo build --release --quiet --bin meshstream --bin meshstream-train

levels=$(grep -o '"quant_levels": *[0-9]*' "$model/config.json" | grep -o '[0-9]*$')
"$target/meshstream-train" shapes -o "$out/held/shapes" -n 60 --primitives --levels "$levels"
"$target/meshstream-train" shapes -o "$out/tuning/shapes" -n 240 --primitives \
  --seed 20261122 --levels "$levels"
total=0
count=0
for set in held tuning; do
  gt="$out/$set/gt"
  mkdir -p "$gt"
  for f in "$out/$set/shapes"/*-{Box,Prism,Pyramid}.ply; do ln -sf "$(realpath "$f")" "$gt/"; done
  for seed in $seeds; do
    pred="$out/$set/seed-$seed"
    mkdir -p "$pred"
    # Two reconstructions at a time, one thread each.
    find "$gt" -name '*.ply' -printf '%f\n' | sed 's/\.ply$//' | xargs -P 2 -I{} env \
      RAYON_NUM_THREADS=1 "$target/meshstream" reconstruct "$gt/{}.ply" -o "$pred/{}.glb" \
      --model "$model" --temperature 0 --candidates "$candidates" --fit-rounds "$fit_rounds" --seed "$seed" 2>/dev/null
    "$target/meshstream" eval --pred "$pred" --gt "$gt" > "$pred/eval.txt"
    line=$(grep -o 'none extra: [0-9]* of [0-9]*' "$pred/eval.txt")
    read -r whole of <<<"$(echo "$line" | grep -o '[0-9]\+' | tr '\n' ' ')"
    echo "$set, seed $seed: $whole of $of rebuilt with every face right"
    total=$((total + whole))
    count=$((count + of))
  done
done
# By kind and face count (a prism's count gives its sides: 4n - 4 faces for n sides), over
# every set and seed: which shapes fail, not just how many.
cat "$out"/*/seed-*/eval.txt | awk -F'|' '/^\| [0-9]+-/ {
  name = $2; gsub(/ /, "", name); kind = substr(name, index(name, "-") + 1)
  split($7, f, " "); made = f[4]; gsub(/\(/, "", made)
  key = sprintf("%s, %3d faces", kind, f[3]); n[key]++
  if (f[1] == f[3] && made == f[3]) whole[key]++
} END { for (k in n) printf "%s: %d of %d\n", k, whole[k], n[k] }' | sort
echo "all: $total of $count"
