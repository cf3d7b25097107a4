"""What the seed experiments (`seed000.py` … `seed004.py`) share: the scene API over HTTP, the
demo-extent forest they place, and running a tool with its raw output kept.

Standard library only; imported from beside the scripts (`python3 benchmarks/seedNNN.py` puts this
folder on `sys.path`).
"""

from __future__ import annotations

import json
import math
import random
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

# The demo's extent, metres (x, z): the forests of seeds 000 and 004 cover it.
DEMO_WIDTH_M, DEMO_DEPTH_M = 1100.0, 1000.0


def call(method: str, url: str, body: dict | None = None, token: str | None = None) -> dict:
    """One JSON request; a 429 waits its Retry-After and tries again (at most 20 times)."""
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method=method)
    req.add_header("Content-Type", "application/json")
    if token:
        req.add_header("Authorization", f"Bearer {token}")
    for attempt in range(20):
        try:
            with urllib.request.urlopen(req, timeout=300) as r:
                return json.loads(r.read() or b"{}")
        except urllib.error.HTTPError as e:
            if e.code == 429 and attempt < 19:
                time.sleep(float(e.headers.get("Retry-After") or 1))
                continue
            raise RuntimeError(f"{method} {url}: {e.code} {e.read()[:300]!r}") from e
    raise RuntimeError("unreachable")


def scene_exists(server: str, sid: str, n: int) -> bool:
    """Whether scene `sid` is there with `n` instances; raises when it is there with another count."""
    try:
        s = call("GET", f"{server}/api/scenes/{sid}")
    except RuntimeError as e:
        if ": 404 " in str(e):
            return False
        raise
    if s.get("instance_count") == n:
        return True
    raise RuntimeError(f"scene {sid} exists with {s.get('instance_count')} instances: delete it first")


def demo_extent_forest(models: list[str], n: int, seed: int) -> list[dict]:
    """n trees on a jittered grid over the demo's extent: cells drawn without repeats."""
    rng = random.Random(seed)
    cols = math.ceil(math.sqrt(n * DEMO_WIDTH_M / DEMO_DEPTH_M))
    rows = math.ceil(n / cols)
    sx, sz = DEMO_WIDTH_M / cols, DEMO_DEPTH_M / rows
    out = []
    for c in sorted(rng.sample(range(cols * rows), n)):
        i, j = divmod(c, cols)
        x = -DEMO_WIDTH_M / 2 + (j + 0.5 + rng.uniform(-0.4, 0.4)) * sx
        z = -DEMO_DEPTH_M / 2 + (i + 0.5 + rng.uniform(-0.4, 0.4)) * sz
        out.append({"model": models[rng.randrange(len(models))], "position": [round(x, 3), 0.0, round(z, 3)],
                    "rotation": round(rng.uniform(0, 2 * math.pi), 5), "scale": round(rng.uniform(0.7, 1.3), 4)})
    return out


def make_demo_extent_scene(server: str, token: str, sid: str, n: int, seed: int) -> str:
    """Scene `sid`: n trees of the demo's models over the demo's extent (kept when already there)."""
    if scene_exists(server, sid, n):
        return sid
    models = sorted(m["name"] for m in call("GET", f"{server}/api/scenes/demo/manifest")["models"])
    call("POST", f"{server}/api/scenes",
         {"name": f"{sid}: {n} trees over 1.1 × 1.0 km", "id": sid,
          "bounds": {"min": [-DEMO_WIDTH_M / 2, -DEMO_DEPTH_M / 2], "max": [DEMO_WIDTH_M / 2, DEMO_DEPTH_M / 2]},
          "instances": demo_extent_forest(models, n, seed)}, token=token)
    return sid


def loadavg() -> str:
    try:
        return Path("/proc/loadavg").read_text().split(" ", 1)[0]
    except OSError:
        return "?"


def run_to(cmd: list[str], out: Path, parse: bool = True):
    """Runs `cmd`, keeps its stdout as `out` (raw output) and returns it (parsed as JSON unless
    `parse` is false); an `out` that exists is reused, not run again."""
    if not out.exists():
        print(" ".join(cmd), f"(load {loadavg()})", file=sys.stderr)
        t0 = time.time()
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=7200)
        if r.returncode != 0:
            sys.stderr.write(r.stderr[-4000:])
            raise RuntimeError(f"{cmd[1]} failed ({r.returncode})")
        out.write_text(r.stdout)
        print(f"  {time.time() - t0:.0f} s -> {out.name} (load {loadavg()})", file=sys.stderr)
    return json.loads(out.read_text()) if parse else out.read_text()
