#!/bin/bash
# Unique forest, static view at the flyover's start (camera held: --speed 0), 480x270:
# bytes to SSIM 0.95 per method. A long run with every tree as geometry (full detail and
# Canopy's geometry streams settle by frame ~420) and short runs over the switch size, where
# Canopy settles sooner and the discrete files' estimate has no link time.
# usage: run.sh CANOPY_BIN URL OUT
set -u
BIN=$1; URL=$2; OUT=$3
mkdir -p "$OUT"
ev() { # label frames every ladder [scales]
  local label=$1 frames=$2 every=$3 ladder=$4 scales=${5:-}
  local extra=(); [ -n "$scales" ] && extra=(--detail-scales "$scales")
  /usr/bin/time -f "%e s wall %U s user" "$BIN" eval "$URL" --speed 0 --frames "$frames" --every "$every" \
    --width 480 --height 270 --ladder "$ladder" "${extra[@]}" \
    --out "$OUT/eval-$label" --json > "$OUT/eval-$label.json" 2> "$OUT/eval-$label.err"
  echo "$label: $(tail -1 "$OUT/eval-$label.err")"
}
ev geometry0 451 225 "geometry:0" "0.5,0.25" &
( ev geometry8 181 90 "geometry:8,hemioct:0" "0.5"
  ev geometry30 181 90 "geometry:30,hemioct:0"
  ev geometry4 181 90 "geometry:4,hemioct:0" ) &
wait
