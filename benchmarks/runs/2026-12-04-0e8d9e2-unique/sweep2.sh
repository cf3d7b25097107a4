#!/bin/bash
# Two more switch sizes between 8 (reaches 0.95) and 12 (0.9496).
set -u
BIN=$1; URL=$2; OUT=$3
ev() {
  /usr/bin/time -f "%e s wall %U s user" "$BIN" eval "$URL" --speed 0 --frames 241 --every 30 \
    --width 480 --height 270 --ladder "$2" --out "$OUT/eval-$1" --json > "$OUT/eval-$1.json" 2> "$OUT/eval-$1.err"
  echo "$1: $(tail -1 "$OUT/eval-$1.err")"
}
ev sweep-g10 "geometry:10,hemioct:0" &
ev sweep-g9 "geometry:9,hemioct:0" &
wait
