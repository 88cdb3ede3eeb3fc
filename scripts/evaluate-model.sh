#!/usr/bin/env bash
# Reconstructs every mesh of the lowpoly dev split and of famous-dev from points sampled on
# its surface, then scores the results against the ground truth with `meshstream eval`
# (DESIGN.md's CD/HD, faces right, boundary and non-manifold edges, connected parts).
# Usage: scripts/evaluate-model.sh [MODEL_DIR] [OUT_DIR] [RECONSTRUCT FLAGS...], e.g.
# --face-beam 1. With TURN=DEGREES in the environment every mesh is first turned about the
# vertical axis by that angle (`meshstream convert --turn`), so its walls are off the axes.
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-models/default}
out=${2:-target/eval}
shift $(($# < 2 ? $# : 2))
data=../shared/data
bin="${CARGO_TARGET_DIR:-target}/release/meshstream"
cargo build --release --quiet --bin meshstream

mkdir -p "$out/dev-gt" "$out/dev-pred" "$out/famous-pred"
famous_gt="$data/famous-dev"
# Each ground-truth mesh, linked (or turned) into the output folder so eval pairs them by name.
place() {
  if [ -n "${TURN:-}" ]; then
    "$bin" convert "$1" "$2" --turn "$TURN" 2>/dev/null
  else
    ln -sf "$(realpath "$1")" "$2"
  fi
}
# EVERY=N in the environment takes every N-th dev mesh (the first, the N+1-th, ...): a quicker check.
awk -F, 'NR > 1 && $8 == "dev" { print $1 }' "$data/lowpoly/manifest.csv" | awk -v n="${EVERY:-1}" 'NR % n == 1 % n' \
  | while read -r f; do
  place "$data/lowpoly/$f" "$out/dev-gt/$f"
done
if [ -n "${TURN:-}" ]; then
  famous_gt="$out/famous-gt"
  mkdir -p "$famous_gt"
  for f in "$data"/famous-dev/*.ply; do place "$f" "$famous_gt/$(basename "$f")"; done
fi
for gt_dir in "$out/dev-gt" "$famous_gt"; do
  pred_dir=$([ "$gt_dir" = "$out/dev-gt" ] && echo "$out/dev-pred" || echo "$out/famous-pred")
  for f in "$gt_dir"/*.ply; do
    name=$(basename "$f" .ply)
    RAYON_NUM_THREADS=1 "$bin" reconstruct "$f" -o "$pred_dir/$name.glb" --model "$model" "$@" 2>/dev/null \
      || echo "no reconstruction for $name" >&2
  done
done
echo "== lowpoly dev split (the summary; every mesh's row: meshstream eval --pred $out/dev-pred --gt $out/dev-gt)"
"$bin" eval --pred "$out/dev-pred" --gt "$out/dev-gt" | sed -n '/^| set /,$p'
echo "== famous-dev"
"$bin" eval --pred "$out/famous-pred" --gt "$famous_gt"
