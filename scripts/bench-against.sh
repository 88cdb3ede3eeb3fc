#!/usr/bin/env bash
# Decode speed of this tree against another revision, measured in one run: the two release
# binaries take turns running `meshstream bench decode` (random weights of the tiny preset, the
# shipped model's shapes), and the best faces/s of each batch size is compared.
#
# Usage: scripts/bench-against.sh REV [ROUNDS] [BENCH DECODE FLAGS...]
#   e.g. scripts/bench-against.sh main 3 --batches 1,16 --faces 200
# REV is built in a temporary git worktree with its own target dir (target/bench-against,
# kept between runs so a second comparison builds only what changed); BASE_BIN=PATH uses an
# already built binary of REV instead. This tree's binary is target/release/meshstream (built
# here). Only flags both revisions know may follow.
set -euo pipefail
cd "$(dirname "$0")/.."
rev=${1:?usage: scripts/bench-against.sh REV [ROUNDS] [BENCH DECODE FLAGS...]}
rounds=${2:-3}
shift $(($# < 2 ? $# : 2))
flags=("$@")
[ ${#flags[@]} -gt 0 ] || flags=(--batches 1,16 --faces 200 --compare 10)

cargo build --release --quiet --locked --bin meshstream
current=target/release/meshstream
base=${BASE_BIN:-}
if [ -z "$base" ]; then
  commit=$(git rev-parse --verify "$rev^{commit}")
  tree=$(mktemp -d)
  trap 'git worktree remove --force "$tree" >/dev/null 2>&1 || true; rm -rf "$tree"' EXIT
  git worktree add --detach "$tree" "$commit" >/dev/null
  CARGO_TARGET_DIR="$PWD/target/bench-against" \
    cargo build --release --quiet --locked --bin meshstream --manifest-path "$tree/Cargo.toml"
  base=target/bench-against/release/meshstream
fi

log=$(mktemp)
for round in $(seq "$rounds"); do
  for who in base current; do
    bin=$([ "$who" = base ] && echo "$base" || echo "$current")
    # One measurement a round for a binary that would otherwise keep the best of several.
    extra=()
    if "$bin" bench decode --help | grep -q -- --rounds; then extra=(--rounds 1); fi
    echo "== round $round $who" >>"$log"
    "$bin" bench decode "${flags[@]}" "${extra[@]}" >>"$log"
  done
done
python3 - "$log" "$rev" <<'PY'
import re, sys
best = {}
who = None
for line in open(sys.argv[1]):
    m = re.match(r"== round \d+ (\w+)", line)
    if m:
        who = m.group(1)
        continue
    # "FACE decode, batch 1 x 200 faces | 399 faces/s ..." (older) or "... | f32 399.12 | ...".
    m = re.search(r"FACE decode, batch (\d+) x (\d+) faces[^|]*\|\s*(?:f32\s+)?([\d.]+)", line)
    if m:
        key = (int(m.group(1)), int(m.group(2)))
        rate = float(m.group(3))
        best.setdefault(key, {}).setdefault(who, 0.0)
        best[key][who] = max(best[key][who], rate)
print(f"faces/s, best of the rounds: {sys.argv[2]} (base) vs this tree (current)")
for (batch, faces), r in sorted(best.items()):
    b, c = r.get("base"), r.get("current")
    if b and c:
        print(f"batch {batch:>3} x {faces} faces: base {b:8.1f}  current {c:8.1f}  ratio {c / b:.2f}x")
PY
rm -f "$log"
