#!/usr/bin/env bash
# The training-free baselines on the same meshes as scripts/evaluate-model.sh: for every mesh of
# the lowpoly dev split and of famous-dev, the convex hull and the Poisson surface of the points
# a reconstruction is judged and fitted against (its reference points), at the model's face
# budget, scored with `meshstream eval`.
# Usage: scripts/evaluate-baselines.sh [MODEL_DIR] [OUT_DIR]
# (MODEL_DIR only supplies the face budget from its config.json.)
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-models/default}
out=${2:-target/eval-baselines}
data=../shared/data
bin="${CARGO_TARGET_DIR:-target}/release/meshstream"
cargo build --release --quiet --bin meshstream

mkdir -p "$out/dev-gt"
# The dev split of the low-poly set, linked into one folder so eval pairs them by name.
awk -F, 'NR > 1 && $8 == "dev" { print $1 }' "$data/lowpoly/manifest.csv" | while read -r f; do
  ln -sf "$(realpath "$data/lowpoly/$f")" "$out/dev-gt/$f"
done
for method in hull poisson; do
  start=$SECONDS
  for set in dev famous; do
    gt_dir=$([ "$set" = dev ] && echo "$out/dev-gt" || echo "$data/famous-dev")
    pred_dir="$out/$method-$set"
    mkdir -p "$pred_dir"
    for f in "$gt_dir"/*.ply; do
      name=$(basename "$f" .ply)
      RAYON_NUM_THREADS=1 "$bin" baseline "$f" -o "$pred_dir/$name.glb" --method "$method" \
        --model "$model" 2>/dev/null || echo "no $method baseline for $name" >&2
    done
  done
  echo "== $method: built in $((SECONDS - start)) s"
  echo "== $method, lowpoly dev split"
  "$bin" eval --pred "$out/$method-dev" --gt "$out/dev-gt" | sed -n '/^| set /,$p'
  echo "== $method, famous-dev"
  "$bin" eval --pred "$out/$method-famous" --gt "$data/famous-dev"
done
