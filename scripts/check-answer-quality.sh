#!/usr/bin/env bash
# What an answer says of itself, checked against the ground truth: reconstructs every EVERY-th
# mesh of the lowpoly dev split (default 5: 44 meshes) with `meshstream reconstruct` (the
# defaults, or the flags given), keeps the line it prints (parts, open and non-manifold edges,
# the Chamfer distance to the input points), scores the results with `meshstream eval --json`,
# and prints whether the counts agree with eval's and how well the distance to the input ranks
# the meshes by their distance to the ground truth (Spearman's rank correlation; how many of
# the worst fifth by ground truth the worst fifth by input distance finds).
# Usage: scripts/check-answer-quality.sh [MODEL_DIR] [OUT_DIR] [RECONSTRUCT FLAGS...]
set -euo pipefail
cd "$(dirname "$0")/.."
model=${1:-models/default}
out=${2:-target/answer-quality}
shift $(($# < 2 ? $# : 2))
data=../shared/data
bin="${CARGO_TARGET_DIR:-target}/release/meshstream"
cargo build --release --quiet --bin meshstream

mkdir -p "$out/gt" "$out/pred"
: > "$out/said.txt"
awk -F, 'NR > 1 && $8 == "dev" { print $1 }' "$data/lowpoly/manifest.csv" \
  | awk -v n="${EVERY:-5}" 'NR % n == 1 % n' | while read -r f; do
  name=$(basename "$f" .ply)
  ln -sf "$(realpath "$data/lowpoly/$f")" "$out/gt/$f"
  said=$(RAYON_NUM_THREADS=1 "$bin" reconstruct "$data/lowpoly/$f" -o "$out/pred/$name.glb" \
    --model "$model" "$@" 2>&1 | grep '^wrote ' || true)
  echo "$name	$said" >> "$out/said.txt"
done
"$bin" eval --pred "$out/pred" --gt "$out/gt" --json > "$out/eval.json"
python3 - "$out/said.txt" "$out/eval.json" <<'EOF'
import json, re, sys

said = {}
for line in open(sys.argv[1]):
    name, text = line.rstrip("\n").split("\t", 1)
    m = re.search(r"; (\d+) parts?, (?:watertight|(\d+) of (\d+) edges open, (\d+) non-manifold)"
                  r", input CD ([0-9.]+)", text)
    if m:
        parts, open_, edges, nm, cd = m.groups()
        said[name] = dict(parts=int(parts), boundary=int(open_ or 0), edges=edges and int(edges),
                          nm=int(nm or 0), cd=float(cd))
rows = [r for r in json.load(open(sys.argv[2]))["meshes"] if r["chamfer"] is not None]
pairs, agree = [], 0
for r in rows:
    s = said.get(r["name"])
    if s is None:
        continue
    t = r["topology"]
    agree += (s["parts"], s["boundary"], s["nm"]) == (
        t["parts"], t["boundary_edges"], t["non_manifold_edges"])
    pairs.append((s["cd"], r["chamfer"], r["name"]))
n = len(pairs)

def ranks(values):
    order = sorted(range(len(values)), key=lambda i: values[i])
    out = [0.0] * len(values)
    for rank, i in enumerate(order):
        out[i] = float(rank)
    return out

a, b = ranks([p[0] for p in pairs]), ranks([p[1] for p in pairs])
mean = (n - 1) / 2
cov = sum((x - mean) * (y - mean) for x, y in zip(a, b))
var = sum((x - mean) ** 2 for x in a)
k = max(1, n // 5)
worst = lambda key: {p[2] for p in sorted(pairs, key=key)[-k:]}
found = len(worst(lambda p: p[0]) & worst(lambda p: p[1]))
print(f"meshes: {n} of {len(rows)} scored ({len(said)} answers said how they are built)")
print(f"parts, open and non-manifold edges as eval counts them: {agree} of {n}")
print(f"Spearman rank correlation, input CD against CD to the ground truth: {cov / var:.2f}")
print(f"the worst {k} by CD to the ground truth, among the worst {k} by input CD: {found}")
print(f"mean input CD {sum(p[0] for p in pairs) / n:.4f}, mean CD to the ground truth "
      f"{sum(p[1] for p in pairs) / n:.4f}")
EOF
