#!/usr/bin/env python3
"""Seed 000's experiment on the project: about 5,000 trees drawn three ways, the seed's Figure 5
(frame time) and the triangles each way draws:

    A  pure L-system geometry: every tree in view at full detail (`--full-detail`)
    B  L-system + crossed billboards: full-detail geometry down to 60 px of projected height,
       then two quads crossed at 90° (`--ladder geometry:60,crossed:0`)
    C  L-system + crossed billboards + iteration levels ("stand LOD"): full geometry down to
       150 px, then one, two and three iterations fewer down to 60 px (adjacent levels one
       iteration apart, within the quarter of the iterations that seed 000 finds do not fix the
       shape), then crossed billboards (`--ladder geometry:150,iter1:120,iter2:90,iter3:60,crossed:0`)

B and C draw their geometry as the L-system grew it, without seed 004's per-node rates
(`--lod-weights 0,0,0,0,0`: every leaf of every node kept; `--lod-near` alone does not do that,
as the factors f1, f3 and f5 do not depend on distance). The seed gives no ε; B and C switch to
billboards at the same projected height, so C differs from B only by its iteration levels. D, the
project's default geometry (C with seed 004's per-node rates), is flown beside them.

    python3 benchmarks/seed000.py http://127.0.0.1:8080 CREATION_TOKEN OUT_DIR
        [--canopy target/debug/canopy] [--fly-frames 91] [--rounds 3] [--bench-frames 0]
        [--sweep 250,500] [--sweep-frames 10] [--sweep-rounds 2]

On a running canopy-server with the demo's models, makes the scene `seed000-5000`: 5,000 trees
over the demo's 1.1 × 1.0 km (a jittered grid; species, rotation and scale in [0.7, 1.3] from a
fixed seed; the seed's area is not given). On the `flyover` path at 1280 × 720 with the default
1,500 m view distance (about 3,600 trees in view):

- `canopy fly --json` for A–D: triangles, leaves, billboards and bytes per frame
  (machine-independent);
- `canopy view --screenshot --wait-idle --json` at the viewer's start camera for B, C and D, in
  `--rounds` rounds alternating B, C, D: one frame's upload and render time (`render_ms`, renderer
  set-up and the first upload of every mesh included; the view bench is the steady-state figure)
  and the PNG;
- with `--bench-frames N` (N > 0; meant for a GPU), `canopy view --bench-frames N --json` for B
  and for C: N frames' upload and render time with each ladder, then with LOD off, which is A.
  On this project's 2-core machine without a GPU that is not possible: A draws 740–790 M
  triangles (360–390 M leaves) a frame; at the 2 M triangles a second llvmpipe managed in seed
  004's full-detail run that is about 6 minutes a frame, 2 hours for two 10-frame benches, with a
  leaf-draw buffer of several GB. So the default is 0 and A has no frame time here.
- with `--sweep N1,N2`: seed 000's Figure 5 is frame rate against the number of trees, so the
  view bench for B and for C (each followed by its full-detail pass, A) runs on smaller forests
  of N trees over the same extent (`seed000-N`, sparser), where A fits this machine, in
  `--sweep-rounds` rounds alternating B's bench and C's.

Raw outputs go to OUT_DIR as they are; summary.json holds the derived figures. A step whose output
exists is not run again (delete it to redo it).

Frame times are the adapter's: on this project's machines Mesa's llvmpipe (a CPU rasterizer), so
only ratios carry over; the seed's figure (a GeForce 9800GT) needs the bench on a GPU. Standard
library only.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from seedlib import call, make_demo_extent_scene as make_scene, run_to

TREES = 5000
SCENE = "seed000-5000"
VIEW = ["--path", "flyover", "--width", "1280", "--height", "720"]
PURE = ["--lod-weights", "0,0,0,0,0"]
LADDER_B = "geometry:60,crossed:0"
LADDER_C = "geometry:150,iter1:120,iter2:90,iter3:60,crossed:0"
CONFIGS = {
    "A": ["--full-detail"],
    "B": ["--ladder", LADDER_B, *PURE],
    "C": ["--ladder", LADDER_C, *PURE],
    "D": ["--ladder", LADDER_C],
}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("server")
    ap.add_argument("token", help="the server's creation token (DATA/creation-token)")
    ap.add_argument("out", type=Path)
    ap.add_argument("--canopy", default="target/debug/canopy")
    ap.add_argument("--fly-frames", type=int, default=91)
    ap.add_argument("--bench-frames", type=int, default=0, help="view bench frames for B and C (each with A); 0: none")
    ap.add_argument("--rounds", type=int, default=3, help="screenshot rounds, alternating B, C, D")
    ap.add_argument("--sweep", default="", help="also bench B and C (each with A) on forests of these sizes, e.g. 250,500")
    ap.add_argument("--sweep-frames", type=int, default=10)
    ap.add_argument("--sweep-rounds", type=int, default=2)
    a = ap.parse_args()
    out: Path = a.out
    out.mkdir(parents=True, exist_ok=True)
    sid = make_scene(a.server, a.token, SCENE, TREES, 0)
    url = f"{a.server}/api/scenes/{sid}"
    summary: dict = {"scene": sid, "trees": TREES, "view": VIEW, "ladders": {"B": LADDER_B, "C": LADDER_C},
                     "fly": {}, "screenshot": {}, "bench": {}}
    for c, flags in CONFIGS.items():
        fly = run_to([a.canopy, "fly", url, *VIEW, "--frames", str(a.fly_frames), *flags, "--json"],
                     out / f"fly-{c}.json")
        s, fr = fly["summary"], fly["frames"]
        last = fr[-1]
        summary["fly"][c] = {
            "mean_triangles": s["mean_triangles"], "mean_full_triangles": s["mean_full_triangles"],
            "bytes": s["bytes"], "plan_ms_p50": s["plan_ms_p50"],
            "last_frame": {k: last[k] for k in ("visible", "geometry_trees", "billboard_trees", "leaves",
                                                 "triangles", "billboard_quads", "full_triangles")}}
    # Rounds alternate B, C, D (A/B/A/B); each round's PNG overwrites the same file (same view).
    for r in range(1, a.rounds + 1):
        for c in "BCD":
            shot = run_to([a.canopy, "view", url, *VIEW, *CONFIGS[c], "--screenshot", str(out / f"shot-{c}.png"),
                           "--wait-idle", "--frames", "30", "--json"], out / f"shot-{c}-{r}.json")
            d = summary["screenshot"].setdefault(c, {"render_ms": [], "triangles": shot["draw"]["triangles"],
                                                     "upload_bytes": shot["draw"]["upload_bytes"]})
            d["render_ms"].append(shot["render_ms"])
    for d in summary["screenshot"].values():
        ms = sorted(d["render_ms"])
        d["render_ms_min"] = ms[0]
        d["render_ms_median"] = ms[len(ms) // 2]
    if a.bench_frames > 0:
        for c in "BC":
            v = run_to([a.canopy, "view", url, *VIEW, *CONFIGS[c], "--bench-frames", str(a.bench_frames), "--json"],
                       out / f"view-{c}.json")
            summary["bench"][c] = {"lod_ms_p50": v["runs"][0]["gpu_ms_p50"], "A_ms_p50": v["runs"][1]["gpu_ms_p50"],
                                   "adapter": v["adapter"]}
    # Seed 000's Figure 5 is frame rate against tree count: the same bench on smaller forests
    # (same extent, sparser), where A's full-detail pass fits this machine.
    for n in [int(x) for x in a.sweep.split(",") if x]:
        u = f"{a.server}/api/scenes/{make_scene(a.server, a.token, f'seed000-{n}', n, 0)}"
        row: dict = {}
        # Rounds alternate B's bench and C's (A/B/A/B); each bench ends with its A pass.
        for r in range(1, a.sweep_rounds + 1):
            for c in "BC":
                v = run_to([a.canopy, "view", u, *VIEW, *CONFIGS[c], "--bench-frames", str(a.sweep_frames),
                            "--json"], out / f"view-{n}-{c}-{r}.json")
                for key, run_ in ((c, v["runs"][0]), ("A", v["runs"][1])):
                    d = row.setdefault(key, {"ms_p50": [], "mean_triangles": run_["mean_triangles"]})
                    d["ms_p50"].append(run_["gpu_ms_p50"])
        for d in row.values():
            d["ms_p50_mean"] = sum(d["ms_p50"]) / len(d["ms_p50"])
        fly = run_to([a.canopy, "fly", u, *VIEW, "--frames", str(a.sweep_frames), *CONFIGS["B"], "--json"],
                     out / f"fly-{n}-B.json")
        row["visible"] = [min(f["visible"] for f in fly["frames"][2:]), max(f["visible"] for f in fly["frames"][2:])]
        summary.setdefault("sweep", {})[str(n)] = row
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
