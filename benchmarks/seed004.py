#!/usr/bin/env python3
"""Seed 004's experiment on the project: the 1,660-tree forest (about 621 trees in view),
triangles drawn against full detail, frame time against no simplification, precision/recall at
50 % simplification (VMI against random pruning), crown-hull triangles per species against the
paper's Table 2, and what switch control (eq. 13) changes.

    python3 benchmarks/seed004.py http://127.0.0.1:8080 CREATION_TOKEN OUT_DIR
        [--canopy target/debug/canopy] [--server-bin target/debug/canopy-server]
        [--species assets/species] [--work /tmp/seed004-work] [--bench-frames 10] [--fly-frames 91]

On a running canopy-server with the demo's models, makes the scene `seed004-1660`: 1,660 trees
over the demo's 1.1 × 1.0 km (a jittered grid, species, rotation and scale in [0.7, 1.3] from a
fixed seed). Then, with a 700 m view distance on the `flyover` path at 1280 × 720 (620–622 trees
in view, the paper's 621):

- `canopy fly --json` (machine-independent counts): full detail (`--full-detail`), seed 004's
  scheme as a ladder (`geometry:150,hull0:0`: trees drawn as geometry at seed 004's per-node
  rates, far trees as crown hulls) and every tree as geometry (`geometry:0`, the per-node rate
  alone), each as well without switch control (`--no-switch-control`: every proposed rate change
  applies at once), with the leaves drawn changing between frames as the measure of LOD churn.
- `canopy view --bench-frames N --json` with seed 004's ladder: upload and render time per frame
  with LOD, then with LOD off (the paper's "15.18× faster than unsimplified").
- `canopy view --bench-frames M --bench-lod-only --json` for seed 004's ladder and for every tree
  as geometry, with and without switch control, one after the other: switch control's effect on
  frame time (what it saves is re-uploading index ranges whose rate changed).
- `canopy view --screenshot` at the viewer's start camera (20 m outside the south edge, 30 m up,
  looking north: `--screenshot` does not follow `--path`), PNG kept, to look at.
- `canopy-server bake SPECIES --json` into WORK (the bake is deterministic: each file's hash is
  checked against the served model's), `canopy-server eval-order FILE --rates 0.5 --json` per
  species (the file's VMI order against random order, 5 draws, 16 views at 256²) and
  `canopy-server export FILE -o WORK/x.glb` to count the model's triangles (bark and leaves) for
  Table 2 beside the bake's hull triangles.

Raw outputs go to OUT_DIR as they are; summary.json holds the derived figures. A step whose output
exists is not run again (delete it to redo it).

Frame times are the adapter's: on this project's machines Mesa's llvmpipe (a CPU rasterizer), so
only the ratio between the LOD and full-detail runs carries over; the same command on a GPU gives
seed 004's figure (30.21 fps, 15.18× unsimplified, on a GeForce 940MX). Standard library only.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import struct
import subprocess
import sys
from pathlib import Path

from seedlib import call, make_demo_extent_scene as make_scene, run_to

SPECIES = ["linden", "maple", "small_shrub", "spruce"]
TREES = 1660
SCENE = "seed004-1660"
VIEW = ["--path", "flyover", "--view-distance", "700", "--width", "1280", "--height", "720"]
SEED004_LADDER = "geometry:150,hull0:0"
# Seed 004 eq. 13 off: every proposed rate change applies at once.
NO_SWITCH = ["--no-switch-control"]
# Seed 004, Table 2: triangles of the original model and of its contour (hull) model.
TABLE2 = {"夏栎 (Quercus robur)": (133327, 4198), "毛脉槭 (Acer pubinerve)": (176236, 4946),
          "血皮槭 (Acer griseum)": (215142, 5230), "椴树 (Tilia)": (334700, 6713),
          "桤木 (Alnus)": (811710, 5624)}


def glb_triangles(path: Path) -> list[int]:
    """Triangles of each primitive of a .glb (indexed triangle lists)."""
    b = path.read_bytes()
    n = struct.unpack_from("<I", b, 12)[0]
    j = json.loads(b[20:20 + n])
    return [j["accessors"][p["indices"]]["count"] // 3 for m in j["meshes"] for p in m["primitives"]]


def models_step(a: argparse.Namespace, out: Path) -> dict:
    """Bake (checked against the served files), export for triangle counts, eval-order."""
    work: Path = a.work
    work.mkdir(parents=True, exist_ok=True)
    bake = run_to([a.server_bin, "bake", a.species, "-o", str(work / "bake"), "--json"], out / "bake.json")
    served = {m["name"]: m for m in call("GET", f"{a.server}/api/scenes/demo/manifest")["models"]}
    res: dict = {}
    for rep in bake:
        sp = rep["name"]
        f = work / "bake" / f"{sp}.ctree"
        sha = hashlib.sha256(f.read_bytes()).hexdigest()
        if sp in served and served[sp]["sha256"] != sha:
            raise RuntimeError(f"{sp}: the bake here differs from the served model")
        mpath = out / f"model-{sp}.json"
        if not mpath.exists():
            glb = work / f"{sp}.glb"
            subprocess.run([a.server_bin, "export", str(f), "-o", str(glb)], check=True, capture_output=True)
            tris = glb_triangles(glb)
            glb.unlink()
            mpath.write_text(json.dumps({"name": sp, "sha256": sha, "export_primitive_triangles": tris,
                                         "triangles": sum(tris), "leaves": rep["leaves"],
                                         "command": f"canopy-server export {sp}.ctree -o {sp}.glb"}, indent=1) + "\n")
        m = json.loads(mpath.read_text())
        order = run_to([a.server_bin, "eval-order", str(f), "--rates", "0.5", "--json"], out / f"order-{sp}.json")
        rows = {o["order"]: o["plain"][0] for o in order["orders"]}
        hulls = [lv["triangles"] for lv in rep["hulls"]["levels"]]
        res[sp] = {"triangles": m["triangles"], "leaves": m["leaves"], "hull_triangles": hulls,
                   "hull0_over_model": hulls[0] / m["triangles"],
                   "vmi_p_r": [rows["vmi"]["precision"], rows["vmi"]["recall"]],
                   "random_p_r": [rows["random"]["precision"], rows["random"]["recall"]]}
    k = len(res)
    res["mean"] = {"vmi_p_r": [sum(r["vmi_p_r"][i] for r in res.values()) / k for i in (0, 1)],
                   "random_p_r": [sum(r["random_p_r"][i] for r in res.values()) / k for i in (0, 1)]}
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("server")
    ap.add_argument("token", help="the server's creation token (DATA/creation-token)")
    ap.add_argument("out", type=Path)
    ap.add_argument("--canopy", default="target/debug/canopy")
    ap.add_argument("--server-bin", default="target/debug/canopy-server")
    ap.add_argument("--species", default="assets/species")
    ap.add_argument("--work", type=Path, default=Path("/tmp/seed004-work"), help="baked files and exports")
    ap.add_argument("--bench-frames", type=int, default=10)
    ap.add_argument("--fly-frames", type=int, default=91)
    ap.add_argument("--switch-bench-frames", type=int, default=30,
                    help="frames of each switch-control bench (LOD only)")
    a = ap.parse_args()
    out: Path = a.out
    out.mkdir(parents=True, exist_ok=True)
    sid = make_scene(a.server, a.token, SCENE, TREES, 4)
    url = f"{a.server}/api/scenes/{sid}"
    frames = ["--frames", str(a.fly_frames)]
    flies = {
        "full": ["--full-detail"],
        "seed004": ["--ladder", SEED004_LADDER],
        "seed004-noswitch": ["--ladder", SEED004_LADDER, *NO_SWITCH],
        "geometry": ["--ladder", "geometry:0"],
        "geometry-noswitch": ["--ladder", "geometry:0", *NO_SWITCH],
    }
    summary: dict = {"scene": sid, "trees": TREES, "view": VIEW, "ladder": SEED004_LADDER, "fly": {}}
    for name, flags in flies.items():
        fly = run_to([a.canopy, "fly", url, *VIEW, *frames, *flags, "--json"], out / f"fly-{name}.json")
        s, fr = fly["summary"], fly["frames"]
        summary["fly"][name] = {
            "mean_triangles": s["mean_triangles"], "mean_full_triangles": s["mean_full_triangles"],
            "triangle_share": s["mean_triangles"] / s["mean_full_triangles"], "bytes": s["bytes"],
            "plan_ms_p50": s["plan_ms_p50"], "mean_visible": sum(f["visible"] for f in fr) / len(fr),
            "mean_leaves": sum(f["leaves"] for f in fr) / len(fr),
            "mean_geometry_trees": sum(f["geometry_trees"] for f in fr) / len(fr),
            "mean_hull_trees": sum(f["hull_trees"] for f in fr) / len(fr),
            "nodes_evaluated": sum(f["nodes_evaluated"] for f in fr),
            "mean_leaf_change": sum(abs(b["leaves"] - a_["leaves"]) for a_, b in zip(fr, fr[1:])) / max(len(fr) - 1, 1)}
    summary["models"] = models_step(a, out)
    shot = out / "shot-seed004.png"
    run_to([a.canopy, "view", url, *VIEW, "--ladder", SEED004_LADDER, "--screenshot", str(shot), "--wait-idle",
            "--frames", "30", "--json"], out / "shot-seed004.json")
    v = run_to([a.canopy, "view", url, *VIEW, "--ladder", SEED004_LADDER, "--bench-frames", str(a.bench_frames),
                "--json"], out / "view-seed004.json")
    lod, full = v["runs"][0], v["runs"][1]
    summary["view"] = {"lod_ms_p50": lod["gpu_ms_p50"], "full_ms_p50": full["gpu_ms_p50"],
                       "speedup": full["gpu_ms_p50"] / lod["gpu_ms_p50"], "adapter": v["adapter"]}
    switch: dict = {}
    for name, ladder in (("seed004", SEED004_LADDER), ("geometry", "geometry:0")):
        for label, flags in (("switch", []), ("noswitch", NO_SWITCH)):
            b = run_to([a.canopy, "view", url, *VIEW, "--ladder", ladder, *flags, "--bench-frames",
                        str(a.switch_bench_frames), "--bench-lod-only", "--json"], out / f"view-{name}-{label}.json")
            r = b["runs"][0]
            switch.setdefault(name, {})[label] = {"ms_p50": r["gpu_ms_p50"], "ms_p95": r["gpu_ms_p95"],
                                                  "mean_leaves": r["mean_leaves"]}
        sw = switch[name]
        sw["noswitch_over_switch_p50"] = sw["noswitch"]["ms_p50"] / sw["switch"]["ms_p50"]
    summary["switch_view"] = switch
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
