#!/usr/bin/env bash
# The link model against a kernel-shaped link: for each link, `canopy fly --link` on the virtual
# clock and `canopy fly --wall-clock` over real TCP through htb and a delay line, in a network
# namespace on its loopback (tests/tests/client_shaped.rs, `shaped_benchmark`). Needs root.
#
#   benchmarks/shaped.sh OUT DATA [LINKS] [ROUNDS]
#
# OUT: the run folder (fly-LINK-model.json, fly-LINK-shaped.json, load.txt); DATA: a server data
# folder (copied first: serving writes to it); LINKS: names from client_shaped.rs, comma-separated
# (default slow4g,fast4g); ROUNDS: model/shaped pairs per link, alternating (default 1).
# Release binaries from $CARGO_TARGET_DIR (default target/) are used: build them first with
# `cargo build --release -p canopy-client -p canopy-server`. Fly's arguments: $FLY_ARGS (default
# a held camera until settled); the server's: $SERVER_ARGS (e.g. the small synthetic demo's).
set -euo pipefail
cd "$(dirname "$0")/.."
[ $# -ge 2 ] || { sed -n 2,13p "$0"; exit 2; }
out=$(realpath -m "$1")
links=${3:-slow4g,fast4g}
rounds=${4:-1}
target=${CARGO_TARGET_DIR:-target}
for b in canopy canopy-server; do
  [ -x "$target/release/$b" ] || { echo "missing $target/release/$b: build it first" >&2; exit 1; }
done
mkdir -p "$out"
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
cp -a "$2" "$work/data"
{ date -u +%FT%TZ; uptime; } > "$out/load.txt"
CANOPY_SHAPED_CLIENT=$(realpath "$target/release/canopy") \
CANOPY_SHAPED_SERVER=$(realpath "$target/release/canopy-server") \
CANOPY_SHAPED_OUT="$out" CANOPY_SHAPED_DATA="$work/data" CANOPY_SHAPED_SERVER_ARGS="${SERVER_ARGS:-}" \
CANOPY_SHAPED_LINKS="$links" CANOPY_SHAPED_ROUNDS="$rounds" \
CANOPY_SHAPED_FLY_ARGS="${FLY_ARGS:---speed 0 --frames 2400 --until-settled}" \
  cargo test -p canopy-e2e --test client_shaped -- --ignored --exact shaped_benchmark --nocapture \
  2>&1 | tee "$out/shaped.log" | grep -E "round|panicked|test result"
uptime >> "$out/load.txt"
