#!/usr/bin/env bash
# Reconstructions of dev meshes sent as users send them: the mesh tipped z up, in millimetres
# far off the origin, or 20,000 points on its surface with normals, without them, and with
# noise (scripts/input-variants.py, run with NumPy in a venv under target/). Each result is taken
# back to the ground truth's frame and scored with `meshstream eval`, paired against the mesh
# sent as stored.
# Usage: scripts/evaluate-inputs.sh [MODEL_DIR] [OUT_DIR] [RECONSTRUCT FLAGS...]. EVERY=N in the
# environment takes every N-th dev mesh (default 5: 44 meshes); VARIANTS="a b" picks variants.
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-models/default}
out=${2:-target/eval-inputs}
shift $(($# < 2 ? $# : 2))
data=../shared/data
bin="${CARGO_TARGET_DIR:-target}/release/meshstream"
cargo build --release --quiet --bin meshstream
venv="${CARGO_TARGET_DIR:-target}/picture-venv"
[ -x "$venv/bin/python" ] || { python3 -m venv "$venv" && "$venv/bin/pip" install --quiet pillow numpy; }
variants=${VARIANTS:-upright tipped mm points bare noisy05 noisy1 noisy2}

mkdir -p "$out/gt" "$out/mesh" "$out/points"
awk -F, 'NR > 1 && $8 == "dev" { print $1 }' "$data/lowpoly/manifest.csv" \
  | awk -v n="${EVERY:-5}" 'NR % n == 1 % n' | while read -r f; do
  name=$(basename "$f" .ply)
  ln -sf "$(realpath "$data/lowpoly/$f")" "$out/gt/$name.ply"
  [ -f "$out/mesh/$name.obj" ] || "$bin" convert "$data/lowpoly/$f" "$out/mesh/$name.obj" >/dev/null
  [ -f "$out/points/$name.obj" ] || "$bin" sample "$data/lowpoly/$f" -n 20000 \
    -o "$out/points/$name.obj" >/dev/null
  echo "$name"
done > "$out/names.txt"

for variant in $variants; do
  case $variant in upright | tipped | mm) source=mesh ;; *) source=points ;; esac
  mkdir -p "$out/$variant/input" "$out/$variant/raw" "$out/$variant/pred"
  while read -r name; do
    input="$out/$variant/input/$name.obj" raw="$out/$variant/raw/$name.obj"
    "$venv/bin/python" scripts/input-variants.py forward "$variant" "$out/$source/$name.obj" "$input"
    if RAYON_NUM_THREADS=1 "$bin" reconstruct "$input" -o "$raw" --model "$model" "$@" 2>/dev/null; then
      "$venv/bin/python" scripts/input-variants.py back "$variant" "$raw" "$out/$variant/pred/$name.obj"
    else
      echo "no reconstruction for $variant/$name" >&2
    fi
  done < "$out/names.txt"
done

for variant in $variants; do
  echo "== $variant"
  against=()
  [ "$variant" = upright ] || [ ! -d "$out/upright/pred" ] || against=(--against "$out/upright/pred")
  "$bin" eval --pred "$out/$variant/pred" --gt "$out/gt" "${against[@]}" | sed -n '/^| set /,$p'
done
