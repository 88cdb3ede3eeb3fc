#!/usr/bin/env bash
# Every mesh of the lowpoly dev split and of famous-dev, written as a plain GLB, then made small
# for the web by the tools people use (tests/data/web-gltf: glTF-Transform's quantize, meshopt
# and Draco, gltfpack -cc -vpf), and each read back by `meshstream eval` against the plain one:
# what the reader makes of such files, mesh by mesh (faces right within 1.5 grid steps).
# Usage: scripts/check-web-gltf.sh [OUT_DIR]   (needs node and npm)
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-target/web-gltf}
data=../shared/data
bin="${CARGO_TARGET_DIR:-target}/release/meshstream"
cargo build --release --quiet --bin meshstream
tests/data/web-gltf/tools.sh "$out/tools"
mkdir -p "$out/plain" "$out/gltfpack"
awk -F, 'NR > 1 && $8 == "dev" { print "lowpoly/" $1 }' "$data/lowpoly/manifest.csv" \
    | cat - <(cd "$data" && ls famous-dev/*.ply) | while read -r f; do
    "$bin" convert "$data/$f" "$out/plain/$(basename "$f" .ply).glb" >/dev/null 2>&1
done
for mode in quantized meshopt draco; do
    mkdir -p "$out/$mode"
    node "$out/tools/make.mjs" "$mode" "$out/$mode" "$out"/plain/*.glb >/dev/null 2>&1
done
for f in "$out"/plain/*.glb; do
    node "$out/tools/node_modules/gltfpack/cli.js" -i "$f" -o "$out/gltfpack/$(basename "$f")" \
        -cc -vpf >/dev/null
done
for mode in quantized meshopt gltfpack draco; do
    echo "== $mode"
    "$bin" eval --pred "$out/$mode" --gt "$out/plain" | sed -n '/^| set /,$p'
done
