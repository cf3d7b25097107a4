#!/bin/bash
# The switch-size sweep at the same static view: samples every 30 frames up to frame 240.
# usage: sweep.sh CANOPY_BIN URL OUT
set -u
BIN=$1; URL=$2; OUT=$3
ev() { # label ladder
  /usr/bin/time -f "%e s wall %U s user" "$BIN" eval "$URL" --speed 0 --frames 241 --every 30 \
    --width 480 --height 270 --ladder "$2" --out "$OUT/eval-$1" --json > "$OUT/eval-$1.json" 2> "$OUT/eval-$1.err"
  echo "$1: $(tail -1 "$OUT/eval-$1.err")"
}
( ev sweep-g5 "geometry:5,hemioct:0"; ev sweep-g8 "geometry:8,hemioct:0"; ev sweep-g15 "geometry:15,hemioct:0" ) &
( ev sweep-g6 "geometry:6,hemioct:0"; ev sweep-g12 "geometry:12,hemioct:0"; ev sweep-g20 "geometry:20,hemioct:0" ) &
wait
