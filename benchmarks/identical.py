#!/usr/bin/env python3
"""Compares the `fly --json` outputs of two builds (base-*.json against new-*.json in a folder):
every per-frame and summary figure except wall times must be equal. Writes identical.txt there;
exits 1 on any difference."""
import json
import sys
from pathlib import Path

# Wall-clock figures: they differ run to run by nature.
TIMES = {"plan_ms", "frame_ms", "plan_ms_p50", "plan_ms_p95", "plan_ms_max", "seconds", "peak_rss_bytes"}


def strip(v):
    if isinstance(v, dict):
        return {k: strip(x) for k, x in v.items() if k not in TIMES}
    if isinstance(v, list):
        return [strip(x) for x in v]
    return v


def main(folder: Path) -> int:
    lines, bad = [], 0
    for base in sorted(folder.glob("base-*.json")):
        new = folder / base.name.replace("base-", "new-", 1)
        tag = base.stem[len("base-"):]
        if not new.exists():
            lines.append(f"{tag}: no new run"); bad += 1; continue
        a, b = (strip(json.loads(p.read_text())) for p in (base, new))
        fa, fb = a.get("frames", []), b.get("frames", [])
        diffs = [i for i, (x, y) in enumerate(zip(fa, fb)) if x != y]
        same = a == b
        bad += not same
        s = a.get("summary", {})
        lines.append(
            f"{tag}: {'identical' if same else 'DIFFERENT'} over {len(fa)} frames "
            f"(bytes {s.get('bytes')}, requests {s.get('requests')}, mean triangles {s.get('mean_triangles')})"
            + (f"; first differing frame {diffs[0]}" if diffs else "")
            + ("" if len(fa) == len(fb) else f"; frame counts {len(fa)} vs {len(fb)}")
        )
    text = "\n".join(lines) + f"\n{len(lines) - bad} identical, {bad} different\n"
    (folder / "identical.txt").write_text(text)
    print(text, end="")
    return 1 if bad or not lines else 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1])))
