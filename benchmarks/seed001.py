#!/usr/bin/env python3
"""Seed 001's experiment on the project: N trees drawn as multi-view billboards against full
models (frame time in the offscreen viewer, bytes, atlas bytes per tree).

Makes scenes of N trees (N = 100 and 500 by default) on a running canopy-server from the demo's
models, spread over a square around the origin, then runs `canopy view --bench-frames` on the
orbit path with the lat-long billboard ladder (seed 001: every tree a billboard) against full
detail, and writes one JSON per N.

    python3 benchmarks/seed001.py http://127.0.0.1:8080 CREATION_TOKEN OUT_DIR [--canopy BIN] [--sizes 100,500]

Frame times are the adapter's: on this project's machines Mesa's lavapipe (a CPU rasterizer), so
only the ratio between the two runs carries over; the same command on a GPU gives seed 001's
figure. Standard library only.
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
import time
from pathlib import Path

from seedlib import call


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("server")
    ap.add_argument("token", help="the server's creation token (DATA/creation-token)")
    ap.add_argument("out", type=Path)
    ap.add_argument("--canopy", default="target/release/canopy")
    ap.add_argument("--sizes", default="100,500")
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--spacing", type=float, default=12.0, help="metres between trees")
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    models = [m["name"] for m in call("GET", f"{a.server}/api/scenes/demo/manifest")["models"]]
    if not models:
        print("the demo has no models", file=sys.stderr)
        return 1
    for n in [int(x) for x in a.sizes.split(",")]:
        side = math.ceil(math.sqrt(n))
        half = side * a.spacing / 2
        inst = []
        for k in range(n):
            i, j = divmod(k, side)
            inst.append({"model": models[k % len(models)],
                         "position": [-half + (j + 0.5) * a.spacing, 0.0, -half + (i + 0.5) * a.spacing],
                         "rotation": (k * 2.399963) % (2 * math.pi)})
        sid = f"seed001-{n}-{int(time.time())}"
        b = half + 50
        made = call("POST", f"{a.server}/api/scenes",
             {"name": f"seed 001, {n} trees", "id": sid, "bounds": {"min": [-b, -b], "max": [b, b]}, "instances": inst},
             token=a.token)
        # The bench runs the ladder (every tree a lat-long billboard) and then full detail.
        cmd = [a.canopy, "view", f"{a.server}/api/scenes/{sid}", "--bench-frames", str(a.frames), "--path", "orbit",
               "--ladder", "latlong:0", "--width", "1280", "--height", "720", "--json"]
        print(" ".join(cmd), file=sys.stderr)
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=3600)
        if r.returncode != 0:
            print(r.stderr, file=sys.stderr)
            return 1
        (a.out / f"view-{n}.json").write_text(r.stdout)
        # The scene was only for the run.
        call("DELETE", f"{a.server}/api/scenes/{sid}", token=made["write_token"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
