#!/usr/bin/env bash
# Installs the tools that make glTF small for the web into DIR (once), with make.mjs beside
# them: glTF-Transform and Google's Draco encoder, meshoptimizer, gltfpack. Needs node and npm.
# Usage: tests/data/web-gltf/tools.sh DIR
set -euo pipefail
dir=$1
if [ ! -d "$dir/node_modules/gltfpack" ]; then
    npm install --prefix "$dir" --no-audit --no-fund --silent @gltf-transform/core@4.5.1 \
        @gltf-transform/extensions@4.5.1 @gltf-transform/functions@4.5.1 draco3dgltf@1.5.7 \
        meshoptimizer@1.3.0 gltfpack@1.3.0
fi
cp "$(dirname "$0")/make.mjs" "$dir/"
