#!/usr/bin/env python3
"""Compares the `fly --json` outputs of two builds (base-*.json against new-*.json in a folder):
every per-frame and summary figure the two builds both report, except wall times, must be equal
(figures only the new build reports are listed, not compared). Writes identical.txt there; exits
1 on any difference."""
import json
import sys
from pathlib import Path

# Wall-clock figures: they differ run to run by nature.
TIMES = {"plan_ms", "frame_ms", "plan_ms_p50", "plan_ms_p95", "plan_ms_max", "seconds", "peak_rss_bytes"}


def strip(v, keep=None):
    """`v` without wall times, and with only the keys in `keep` at every object level."""
    if isinstance(v, dict):
        return {k: strip(x, keep) for k, x in v.items() if k not in TIMES and (keep is None or k in keep)}
    if isinstance(v, list):
        return [strip(x, keep) for x in v]
    return v


def keys(v, out=None):
    """Every object key anywhere in `v`."""
    out = set() if out is None else out
    if isinstance(v, dict):
        out.update(v)
        for x in v.values():
            keys(x, out)
    elif isinstance(v, list):
        for x in v:
            keys(x, out)
    return out


def main(folder: Path) -> int:
    lines, bad = [], 0
    for base in sorted(folder.glob("base-*.json")):
        new = folder / base.name.replace("base-", "new-", 1)
        tag = base.stem[len("base-"):]
        if not new.exists():
            lines.append(f"{tag}: no new run"); bad += 1; continue
        ra, rb = (json.loads(p.read_text()) for p in (base, new))
        common = keys(ra) & keys(rb)
        added = sorted(keys(rb) - keys(ra))
        a, b = strip(ra, common), strip(rb, common)
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
            + (f"; new figures not compared: {', '.join(added)}" if added else "")
        )
    text = "\n".join(lines) + f"\n{len(lines) - bad} identical, {bad} different\n"
    (folder / "identical.txt").write_text(text)
    print(text, end="")
    return 1 if bad or not lines else 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1])))
