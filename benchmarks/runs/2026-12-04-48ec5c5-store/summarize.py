#!/usr/bin/env python3
"""Medians over the rounds of results.json (store_bench.py), per server: summary.json."""
import json, statistics, sys

src = sys.argv[1] if len(sys.argv) > 1 else "results.json"
d = json.load(open(src))
out = {"from": src, "rounds": len(d["new"])}
for k in ("base", "new"):
    rs = d[k]
    med = lambda f: statistics.median(f(r) for r in rs)
    out[k] = {
        "edit_p50_ms": med(lambda r: r["edit_50k_one_move_ms"]["p50"]),
        "edit_p99_ms": med(lambda r: r["edit_50k_one_move_ms"]["p99"]),
        "written_per_edit_bytes": med(lambda r: r["written_per_edit_bytes"]),
        "disk_bytes_after_35_versions": med(lambda r: r["big_scene_disk_bytes_after_35_versions"]),
        "reads_idle_p99_ms": med(lambda r: r["reads_other_scene_ms"]["idle_p99"]),
        "reads_writers4_p99_ms": med(lambda r: r["reads_other_scene_ms"]["writers4_p99"]),
        "reads_writers4_p50_ms": med(lambda r: r["reads_other_scene_ms"]["writers4_p50"]),
        "reads_p99_loaded_over_idle": med(lambda r: r["reads_other_scene_ms"]["writers4_p99"] / r["reads_other_scene_ms"]["idle_p99"]),
        "edits_per_s_during_reads": med(lambda r: r["reads_other_scene_ms"]["edits_per_s_during"]),
    }
json.dump(out, open("summary.json", "w"), indent=1)
print(json.dumps(out, indent=1))
