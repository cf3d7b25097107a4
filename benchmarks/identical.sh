#!/usr/bin/env bash
# Same output before and after a refactor: runs `canopy fly --json` with two builds of the client
# on the same data folders and compares every per-frame figure except wall times.
#
#   benchmarks/identical.sh BASE_BIN_DIR NEW_BIN_DIR OUT_DIR [DATA_ROOT]
#
# BASE_BIN_DIR and NEW_BIN_DIR each hold a release `canopy` (NEW_BIN_DIR also `canopy-server`,
# which makes the data folders once under DATA_ROOT, default /tmp/canopy-identical): the demo
# (2,500 trees over 1.1 km × 1.0 km) and the plan bench's two 40,000-tree layouts (1.1 × 1.0 km
# and 10 × 10 km). Scenes are read with the file backend (no network, no ports), so bytes and
# requests are the file reader's. Writes one JSON per build, scene and path to OUT_DIR and
# OUT_DIR/identical.txt; exits 1 when any compared figure differs.
set -euo pipefail
base=$(cd "$1" && pwd); new=$(cd "$2" && pwd); out=$3; root=${4:-/tmp/canopy-identical}
mkdir -p "$out" "$root"
here=$(cd "$(dirname "$0")" && pwd)

# make_data NAME TREES WIDTH DEPTH: the server's demo in $root/NAME (once).
make_data() {
  local d=$root/$1
  if ls "$d"/assets/scenes/demo/v*.json >/dev/null 2>&1; then return; fi
  mkdir -p "$d/assets/trees"
  # The server bakes only when assets/trees is empty: reuse another folder's baked trees.
  for other in "$root"/*/assets/trees; do
    if [ "$other" != "$d/assets/trees" ] && ls "$other"/*.ctree >/dev/null 2>&1; then
      cp "$other"/*.ctree "$d/assets/trees/"; break
    fi
  done
  echo "making $1 ($2 trees, $3 m × $4 m) in $d" >&2
  "$new/canopy-server" serve --addr 127.0.0.1:18731 --data "$d" --demo-trees "$2" \
    --demo-width-m "$3" --demo-depth-m "$4" >/dev/null 2>&1 &
  local pid=$!
  for _ in $(seq 1 900); do
    if curl -sf http://127.0.0.1:18731/healthz >/dev/null 2>&1; then break; fi
    sleep 1
  done
  kill "$pid"; wait "$pid" || true
}

manifest() { ls "$root/$1"/assets/scenes/demo/v*.json | sort -V | tail -n 1; }

make_data demo 2500 1100 1000
make_data 40k 40000 1100 1000
make_data 40k-10km 40000 10000 10000

# scene path frames [extra flags...]
runs=(
  "demo flyover 300"
  "demo orbit 300"
  "demo walk 300"
  "demo lowflight 300"
  "demo turns 300"
  "demo lowflight 300 --flight-policy"
  "demo flyover 120 --full-detail"
  "demo flyover 150 --frame-budget-kb 256 --cache-mb 4"
  "40k flyover 120"
  "40k orbit 120"
  "40k-10km flyover 150"
  "40k-10km orbit 150"
  "40k-10km lowflight 150"
)
for r in "${runs[@]}"; do
  set -- $r
  scene=$1 path=$2 frames=$3; shift 3
  tag="$scene-$path${*:+-$(echo "$*" | tr -d ' -' )}"
  for build in base new; do
    bin=$base; [ $build = new ] && bin=$new
    echo "$build $tag" >&2
    "$bin/canopy" fly "$(manifest "$scene")" --path "$path" --frames "$frames" --json "$@" \
      > "$out/$build-$tag.json" 2>/dev/null
  done
done
python3 "$here/identical.py" "$out"
