#!/usr/bin/env python3
"""Seed 002's experiment on the project: 40,000 trees over 10 km × 10 km flown low and fast, in
the seed's four configurations, frame time, maximum lag (v_max / fps) and bytes fetched.

    A  every tree full geometry (the viewer bench's full-detail run; `fly --full-detail`)
    B  stochastic billboard clouds (the bake's default clouds), levels by distance alone
    C  improved clouds (bake `--cloud-texture-density --cloud-view-height H`: seed 002's texture
       density and view-line penalty for the flight height H), levels by distance alone
    D  improved clouds with seed 002's flight policy: field sectors (120°), threat zone (t = 2 s)
       and the visual-redundancy table that `canopy redundancy` computes on the same scene over
       the seed's grid (H ≤ 1,000 m by 20 m, v ≤ 80 m/s by 10 m/s)

"Levels by distance alone" (seed 002's LOD_D without LOD_V and LOD_T): `--flight-policy` always
applies the field sectors and the threat zone, so B and C use seed 000's projected-size ladder
with the same rungs as D, its ε chosen so that a tree of the models' mean height (13.05 m,
scale 1) switches at the policy's σ = 100, 250, 500 and 1,000 m; geometry is then drawn at full
detail (`--lod-weights 0,0,0,0,0`: every node's rate 0, every leaf kept), as the policy's level 0
is. The project has 4 demo species (linden, maple, small_shrub, spruce), not the seed's 5 XFrog
trees.

Two steps, so that the server can index the extra models at its start:

    python3 benchmarks/seed002.py install DATA [--server-bin target/debug/canopy-server] [--heights 25,500]
    canopy-server serve --data DATA --no-demo --creation-token TOKEN --addr 127.0.0.1:8092 &
    python3 benchmarks/seed002.py run http://127.0.0.1:8092 TOKEN OUT_DIR [--canopy BIN] [--heights 25,500]
                                  [--bench-frames 10] [--fly-frames 150] [--width 640 --height 360]

`install` bakes assets/species three ways (default clouds, improved clouds per flight height)
into DATA/bake-*/ and copies the files into DATA/assets/trees/ as `<species>-<set>.<hash16>.ctree`.
`run` creates one scene per model set (the same 40,000 instances: a 200 × 200 jittered grid of
50 m, species, rotation and scale in [0.7, 1.3] drawn from a fixed seed; one creation of 10,000
and three edits of 10,000, the server's batch limit), computes the redundancy table of each
improved scene, then per flight height flies the `lowflight` path at 80 m/s (`canopy fly --json`:
bytes, planning time) and runs the offscreen viewer bench (`canopy view --bench-frames --json`:
upload and render time per frame, each config then full detail = A). Raw outputs go to OUT_DIR
as they are; summary.json holds the derived figures (fps = 1000 / p50 frame ms, lag = 80 / fps).
A step whose output exists is not run again (delete it to redo it).

Frame times are the adapter's: on this project's machines Mesa's llvmpipe (a CPU rasterizer), so
only ratios between configurations carry over; the same command on a GPU gives seed 002's figure.
Standard library only.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import random
import shutil
import subprocess
import sys
from pathlib import Path

from seedlib import call, run_to, scene_exists

SPECIES = ["linden", "maple", "small_shrub", "spruce"]
V_MAX = 80.0
SIGMA = [100.0, 250.0, 500.0, 1000.0]
MEAN_HEIGHT_M = 13.05  # mean of the 4 models' heights (19.27, 10.70, 4.20, 18.00 m)
FOV_DEG = 60.0
SIDE_M = 10_000.0
GRID = 200  # 200 × 200 = 40,000 trees, 50 m apart
BATCH = 10_000
RUNGS = ["geometry", "cloud0", "cloud1", "cloud2", "hemioct"]
# D's ladder: the policy's level k draws rung k, the ε are not used by it (as in the redundancy run).
FLIGHT_LADDER = "geometry:150,cloud0:60,cloud1:30,cloud2:20,hemioct:0"


def sets_for(heights: list[int]) -> list[str]:
    return ["sbc"] + [f"ic{h}" for h in heights]


def distance_ladder(screen_px: int) -> str:
    """Seed 000's projected-size ladder that switches a tree of the mean height at σ."""
    t = math.tan(math.radians(FOV_DEG) / 2)
    eps = [MEAN_HEIGHT_M * screen_px / (2 * s * t) for s in SIGMA]
    return ",".join(f"{r}:{e:.2f}" for r, e in zip(RUNGS, eps + [0.0]))


def install(a: argparse.Namespace) -> int:
    data = a.data
    trees = data / "assets" / "trees"
    trees.mkdir(parents=True, exist_ok=True)
    for s in sets_for(a.heights):
        out = data / f"bake-{s}"
        flags = [] if s == "sbc" else ["--cloud-texture-density", "--cloud-view-height", s[2:]]
        if not all((out / f"{sp}.ctree").exists() for sp in SPECIES):
            cmd = [a.server_bin, "bake", a.species, "-o", str(out), *flags, "--json"]
            print(" ".join(cmd), file=sys.stderr)
            with open(data / f"bake-{s}.json", "w") as f:
                subprocess.run(cmd, check=True, stdout=f)
        for sp in SPECIES:
            b = (out / f"{sp}.ctree").read_bytes()
            dst = trees / f"{sp.replace('_', '-')}-{s}.{hashlib.sha256(b).hexdigest()[:16]}.ctree"
            if not dst.exists():
                shutil.copyfile(out / f"{sp}.ctree", dst)
            print(dst, file=sys.stderr)
    return 0


def forest(model_set: str) -> list[dict]:
    """The same 40,000 instances for every model set (same draws, model names per set)."""
    rng = random.Random(2)
    step = SIDE_M / GRID
    out = []
    for i in range(GRID):
        for j in range(GRID):
            x = -SIDE_M / 2 + (j + 0.5) * step + rng.uniform(-0.4, 0.4) * step
            z = -SIDE_M / 2 + (i + 0.5) * step + rng.uniform(-0.4, 0.4) * step
            sp = SPECIES[rng.randrange(len(SPECIES))]
            rot = rng.uniform(0, 2 * math.pi)
            scale = rng.uniform(0.7, 1.3)
            out.append({"model": f"{sp.replace('_', '-')}-{model_set}", "position": [round(x, 3), 0.0, round(z, 3)],
                        "rotation": round(rot, 5), "scale": round(scale, 4)})
    return out


def make_scene(server: str, token: str, model_set: str) -> str:
    sid = f"seed002-{model_set}"
    if scene_exists(server, sid, GRID * GRID):
        return sid
    inst = forest(model_set)
    h = SIDE_M / 2
    made = call("POST", f"{server}/api/scenes",
                {"name": f"seed 002, 40,000 trees over 10 km × 10 km ({model_set})", "id": sid,
                 "bounds": {"min": [-h, -h], "max": [h, h]}, "instances": inst[:BATCH]}, token=token)
    for k in range(BATCH, len(inst), BATCH):
        call("POST", f"{server}/api/scenes/{sid}/instances", {"add": inst[k:k + BATCH]}, token=made["write_token"])
    return sid


def run(a: argparse.Namespace) -> int:
    out: Path = a.out
    out.mkdir(parents=True, exist_ok=True)
    scenes = {s: make_scene(a.server, a.token, s) for s in sets_for(a.heights)}
    url = {s: f"{a.server}/api/scenes/{sid}" for s, sid in scenes.items()}
    vp = ["--width", str(a.width), "--height", str(a.height)]
    dl = distance_ladder(a.height)
    flight = {"ladder": FLIGHT_LADDER, "distance_ladder": dl, "viewport": [a.width, a.height],
              "speed_mps": V_MAX, "scenes": scenes}
    # D's redundancy table, per improved scene, over the seed's grid.
    for h in a.heights:
        s = f"ic{h}"
        run_to([a.canopy, "redundancy", url[s], "--ladder", FLIGHT_LADDER, *vp, "--h-max", str(a.prepass_h_max),
                "--out", str(out / f"flight-table-{s}.json"), "--json"], out / f"redundancy-{s}.json")
    summary: dict = {"setup": flight, "heights": {}}
    for h in a.heights:
        ic = f"ic{h}"
        common = ["--path", "lowflight", "--eye-height", str(h), "--speed", str(V_MAX), *vp]
        near = ["--lod-weights", "0,0,0,0,0"]
        configs = {
            "A": (url["sbc"], ["--full-detail", "--ladder", dl]),
            "B": (url["sbc"], ["--ladder", dl, *near]),
            "C": (url[ic], ["--ladder", dl, *near]),
            "D": (url[ic], ["--ladder", FLIGHT_LADDER, "--flight-table", str(out / f"flight-table-{ic}.json")]),
        }
        res: dict = {}
        for c, (u, flags) in configs.items():
            fly = run_to([a.canopy, "fly", u, *common, "--frames", str(a.fly_frames), *flags, "--json"],
                         out / f"fly-{h}-{c}.json")
            sm = fly["summary"]
            res[c] = {"fly": {k: sm.get(k) for k in ("bytes", "requests", "mean_triangles", "plan_ms_p50",
                                                       "plan_ms_p95", "full_download_bytes")}}
            if c == "A":
                continue  # A's frame time: the full-detail run of every bench below
            v = run_to([a.canopy, "view", u, "--bench-frames", str(a.bench_frames), *common, *flags, "--json"],
                       out / f"view-{h}-{c}.json")
            for run_, key in ((v["runs"][0], c), (v["runs"][1], f"A-with-{c}")):
                ms = run_["gpu_ms_p50"]
                fps = 1e3 / ms if ms > 0 else 0.0
                res.setdefault(key, {})["view"] = {
                    "gpu_ms_p50": ms, "gpu_ms_p95": run_["gpu_ms_p95"], "fps": fps,
                    "lag_m": V_MAX / fps if fps > 0 else None, "mean_triangles": run_["mean_triangles"],
                    "mean_leaves": run_["mean_leaves"], "mean_instances": run_["mean_instances"],
                    "bytes": run_["bytes"]}
        a_runs = [res[k]["view"]["gpu_ms_p50"] for k in res if k.startswith("A-with-")]
        if a_runs:
            ms = sorted(a_runs)[len(a_runs) // 2]
            res["A"]["view"] = {"gpu_ms_p50": ms, "fps": 1e3 / ms, "lag_m": V_MAX * ms / 1e3,
                                "note": "median over the benches' full-detail runs"}
        for c in "BCD":
            if "view" in res.get(c, {}):
                res[c]["view"]["fps_over_a"] = res["A"]["view"]["gpu_ms_p50"] / res[c]["view"]["gpu_ms_p50"]
        summary["heights"][str(h)] = res
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="step", required=True)
    i = sub.add_parser("install", help="bake the model sets into a data folder")
    i.add_argument("data", type=Path)
    i.add_argument("--server-bin", default="target/debug/canopy-server")
    i.add_argument("--species", default="assets/species")
    r = sub.add_parser("run", help="scenes, pre-pass, fly and bench")
    r.add_argument("server")
    r.add_argument("token", help="the server's creation token")
    r.add_argument("out", type=Path)
    r.add_argument("--canopy", default="target/debug/canopy")
    r.add_argument("--bench-frames", type=int, default=10)
    r.add_argument("--fly-frames", type=int, default=150)
    r.add_argument("--width", type=int, default=640)
    r.add_argument("--height", type=int, default=360)
    r.add_argument("--prepass-h-max", type=int, default=1000)
    for p in (i, r):
        p.add_argument("--heights", default="25,500", help="flight heights H, metres (comma-separated)")
    a = ap.parse_args()
    a.heights = [int(x) for x in a.heights.split(",")]
    return install(a) if a.step == "install" else run(a)


if __name__ == "__main__":
    sys.exit(main())
