#!/usr/bin/env bash
# Remakes the test files beside this script (tests/formats_gltf.rs reads them): pine-tree.glb
# from the viewer's example (`meshstream convert`, so it has normals), then that file made
# small for the web by glTF-Transform (quantized; meshopt; Draco) and by gltfpack (meshopt,
# positions as floats through the exponential filter). Needs a release build, node and npm.
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../../.." && pwd)
"${CARGO_TARGET_DIR:-$root/target}/release/meshstream" convert \
    "$root/web/examples/pine-tree.ply" "$here/pine-tree.glb"
tools=$(mktemp -d)
trap 'rm -rf "$tools"' EXIT
"$here/tools.sh" "$tools"
for mode in quantized meshopt draco; do
    node "$tools/make.mjs" "$mode" "$tools" "$here/pine-tree.glb"
    mv "$tools/pine-tree.glb" "$here/pine-tree-$mode.glb"
done
node "$tools/node_modules/gltfpack/cli.js" -i "$here/pine-tree.glb" \
    -o "$here/pine-tree-gltfpack.glb" -cc -vpf
