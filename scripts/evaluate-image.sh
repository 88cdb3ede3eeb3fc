#!/usr/bin/env bash
# Image -> mesh on the lowpoly dev split: renders every dev mesh from one fixed view (the
# DiT trainer's evaluation view: azimuth 30, elevation 20, field of view 40, the whole
# normalized cube in frame, 256 px), runs `meshstream generate` on the picture, and scores the
# result against the ground truth with `meshstream eval` (DESIGN.md's CD/HD, both in the
# normalized frame, since an image carries no scale or position).
# Usage: scripts/evaluate-image.sh [MODEL_DIR] [OUT_DIR] [GUIDANCE] [STEPS] [GENERATE FLAGS...],
# e.g. --temperature 0. GUIDANCE and STEPS default to the server's (8 and 25).
# GUIDANCE 0 ignores the image: the unconditional lower bound.
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-models/default}
out=${2:-target/eval-image}
guidance=${3:-8}
steps=${4:-25}
shift $(($# < 4 ? $# : 4))
data=../shared/data
bin="${CARGO_TARGET_DIR:-target}/release/meshstream"
cargo build --release --quiet --bin meshstream

# sqrt(3) / sin(20 degrees): the distance at which the normalized cube fits a 40-degree view.
distance=5.0642
view=(--views 1 --size 256 --azimuth 30 --elevation 20 --fov 40 --distance "$distance")
mkdir -p "$out/gt" "$out/views" "$out/pred"
# VARIANT=tight|offcentre|offjpeg|greybg|colour in the environment generates from the views
# reframed or recoloured as users take pictures (scripts/picture-variants.py, run with Pillow
# and NumPy in a venv under target/), written to OUT/VARIANT; VARIANT=parts from views with a
# colour for each part (`render --color-parts`), as multi-coloured objects are.
# EVERY=N in the environment takes every N-th dev mesh (the first, the N+1-th, ...): a quicker check.
awk -F, 'NR > 1 && $8 == "dev" { print $1 }' "$data/lowpoly/manifest.csv" | awk -v n="${EVERY:-1}" 'NR % n == 1 % n' \
  | while read -r f; do
  name=$(basename "$f" .ply)
  [ -f "$out/gt/$name.ply" ] || "$bin" convert "$data/lowpoly/$f" "$out/gt/$name.ply" --normalize 2>/dev/null
  [ -f "$out/views/$name.png" ] || "$bin" render "$data/lowpoly/$f" -o "$out/views/$name.png" \
    "${view[@]}" 2>/dev/null
  if [ "${VARIANT:-}" = parts ]; then
    mkdir -p "$out/parts"
    [ -f "$out/parts/$name.png" ] || "$bin" render "$data/lowpoly/$f" -o "$out/parts/$name.png" \
      "${view[@]}" --color-parts 2>/dev/null
  fi
  echo "$name"
done > "$out/names.txt"
if [ -n "${VARIANT:-}" ] && [ "$VARIANT" != parts ]; then
  venv="${CARGO_TARGET_DIR:-target}/picture-venv"
  [ -x "$venv/bin/python" ] || { python3 -m venv "$venv" && "$venv/bin/pip" install --quiet pillow numpy; }
  "$venv/bin/python" scripts/picture-variants.py "$VARIANT" "$out/views" "$out/$VARIANT"
fi
while read -r name; do
  picture="$out/views/$name.png"
  if [ -n "${VARIANT:-}" ]; then
    picture=$(ls "$out/$VARIANT/$name".* 2>/dev/null || true)
    [ -n "$picture" ] || { echo "no $VARIANT picture for $name" >&2; continue; }
  fi
  RAYON_NUM_THREADS=1 "$bin" generate "$picture" -o "$out/pred/$name.glb" \
    --model "$model" --guidance "$guidance" --steps "$steps" "$@" 2>/dev/null \
    || echo "no mesh for $name" >&2
done < "$out/names.txt"
echo "== lowpoly dev split, image -> mesh (guidance $guidance, $steps steps)"
"$bin" eval --pred "$out/pred" --gt "$out/gt" | tail -n 6
