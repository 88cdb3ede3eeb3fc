#!/usr/bin/env bash
# Packs what a one-shot training run on a rented GPU machine needs into one folder that travels
# beside the working tree: the compressed trainer, the training meshes, the weights to start
# from, and the PyTorch timing reference. scripts/device-run.sh runs it there.
#
# Usage: scripts/device-pack.sh [OPTIONS]
#   --binary PATH      meshstream-train to carry (default target/cuda/release/meshstream-train,
#                      from scripts/build-cuda.sh)
#   --init MODEL       model folder to start from (default models/default; "none": from scratch)
#   --data DIR         mesh folder with a manifest.csv (default ../shared/data/lowpoly)
#   --max-faces N      carry only meshes of at most N faces (default 800)
#   --reference FILE   the PyTorch timing reference (default ../shared/gpu/torch_reference.py;
#                      left out when absent)
#   --out DIR          the folder to write (default target/device-run; replaced)
#   --limit MIB        the most the folder and the working tree may weigh together (default 64)
#   --compression N    xz preset, 0 (fast) to 9 (small, the default)
set -euo pipefail
cd "$(dirname "$0")/.."
binary=target/cuda/release/meshstream-train
init=models/default
data=../shared/data/lowpoly
max_faces=800
reference=../shared/gpu/torch_reference.py
out=target/device-run
limit_mib=64
compression=9
while (($#)); do
    case $1 in
        --binary) binary=$2 ;;
        --init) init=$2 ;;
        --data) data=$2 ;;
        --max-faces) max_faces=$2 ;;
        --reference) reference=$2 ;;
        --out) out=$2 ;;
        --limit) limit_mib=$2 ;;
        --compression) compression=$2 ;;
        *) echo "device-pack: unknown option $1" >&2; exit 2 ;;
    esac
    shift 2
done
[[ -x $binary ]] || { echo "device-pack: no trainer at $binary (scripts/build-cuda.sh builds it)" >&2; exit 1; }
[[ -f $data/manifest.csv ]] || { echo "device-pack: no $data/manifest.csv" >&2; exit 1; }

rm -rf "$out"
mkdir -p "$out"
# Stripped and xz-compressed: about an eighth of the binary's size.
strip -o "$out/meshstream-train" "$binary"
xz "-$compression" -T0 "$out/meshstream-train"

# The manifest's rows of at most --max-faces faces (its face count is the source's; the
# trainer still skips meshes over the model's limit once quantized), and their files.
mkdir -p "$out/data"
python3 - "$data/manifest.csv" "$max_faces" "$out/data/manifest.csv" "$out/data/files" <<'EOF'
import csv, sys
src, max_faces, manifest, files = sys.argv[1], int(sys.argv[2]), sys.argv[3], sys.argv[4]
with open(src, newline="") as f:
    reader = csv.DictReader(f)
    rows = [r for r in reader if int(r["faces"]) <= max_faces]
    fields = reader.fieldnames
with open(manifest, "w", newline="") as f:
    writer = csv.DictWriter(f, fieldnames=fields)
    writer.writeheader()
    writer.writerows(rows)
with open(files, "w") as f:
    f.write("".join(r["file"] + "\n" for r in rows))
EOF
tar -C "$data" -cf - -T "$out/data/files" | xz "-$compression" -T0 >"$out/data/meshes.tar.xz"
rm "$out/data/files"

if [[ $init != none ]]; then
    mkdir -p "$out/init"
    cp "$init/config.json" "$init"/model*.safetensors* "$out/init/"
fi
if [[ -f $reference ]]; then
    cp "$reference" "$out/torch_reference.py"
fi

# What travels is the working tree (tracked and unignored files) plus this folder.
tree_bytes=$(git ls-files -co --exclude-standard -z | du -cb --files0-from=- | tail -1 | cut -f1)
bundle_bytes=$(du -sb "$out" | cut -f1)
total_mib=$(((tree_bytes + bundle_bytes) / 1048576))
echo "device-pack: $out is $((bundle_bytes / 1048576)) MiB ($(wc -l <"$out/data/manifest.csv") manifest lines), the working tree $((tree_bytes / 1048576)) MiB: $total_mib MiB travel" >&2
if ((total_mib >= limit_mib)); then
    echo "device-pack: over the $limit_mib MiB that may travel" >&2
    exit 1
fi
