#!/usr/bin/env bash
# Presence under load (issue 23, item 6): the e2e test `presence_shedding` with figures written as
# JSON, against this checkout's server and, for the baseline, a build of the commit before the
# change (`OLD`, 01a987d: one broadcast message per pose per viewer).
#
#   bash benchmarks/runs/2026-12-04-b4b941e-presence/run.sh [OLD_SERVER_BINARY]
#
# Debug builds (the test profile), loopback, one scene ("demo"), the viewers' threads in the test
# process. Each run writes `<label>.json`; the test's assertions fail for a server that drops
# well-behaved viewers, which is the point of the baseline, so failures do not stop the script.
set -u
here="$(cd "$(dirname "$0")" && pwd)"
cd "$here/../../.."
export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$PWD/target}"
old="${1:-}"

run() { # label steady fast seconds [server]
  local label=$1 steady=$2 fast=$3 secs=$4 server=${5:-}
  echo "== $label: $steady at 10 Hz, $fast at 95 Hz, ${secs} s ${server:+(server $server)}"
  env CANOPY_PRESENCE_STEADY="$steady" CANOPY_PRESENCE_FAST="$fast" CANOPY_PRESENCE_SECONDS="$secs" \
    CANOPY_PRESENCE_FIGURES="$here/$label.json" ${server:+CANOPY_PRESENCE_SERVER="$server"} \
    cargo nextest run -p canopy-e2e --test presence_shedding --no-capture 2>&1 \
    | grep -E "PRESENCE_FIGURES|whole run|PASS|FAIL|panicked" || true
}

# The test's own load: ten times the old collapse rate in poses a second.
run new-240 150 90 12
# The issue's breaking loads, on the new server.
run new-120 120 0 20
run new-150 150 0 20
if [ -n "$old" ]; then
  run old-120 120 0 20 "$old"
  run old-150 150 0 20 "$old"
  run old-240 150 90 12 "$old"
fi
