#!/usr/bin/env python3
"""Regenerates the tables of BENCHMARKS.md from the runs under benchmarks/runs/.

Every run is a folder `benchmarks/runs/<YYYY-MM-DD>-<commit>[-<label>]/` holding one or more
figures files (JSON, schema `canopy-bench/1`, described in benchmarks/README.md) and, beside
them, any raw outputs of the tools (criterion estimates, `canopy fly --json`, ...), which a
figures entry may point into. For each (area, quantity) the newest run wins (folder date, then
the run's `time`, then folder and file name). Each area's table is written between

    <!-- dashboard:begin area=AREA -->
    <!-- dashboard:end -->

in BENCHMARKS.md; everything outside the markers is left as it is.

    python3 benchmarks/dashboard.py            # rewrite the tables
    python3 benchmarks/dashboard.py --check    # exit 1 if BENCHMARKS.md is not what it would write

Exit status: 0 done / up to date, 1 --check found a difference, 2 invalid runs or markers.
Python 3.11 standard library only.
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import os
import re
import sys
from dataclasses import dataclass
from decimal import Decimal
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
SCHEMA = "canopy-bench/1"
FOLDER_RE = re.compile(r"^(\d{4}-\d{2}-\d{2})-([0-9a-f]{7,40})(?:-([A-Za-z0-9._-]+))?$")
AREA_RE = re.compile(r"^[a-z0-9][a-z0-9-]*$")
BEGIN_RE = re.compile(r"^<!-- dashboard:begin area=(\S+) -->$")
END = "<!-- dashboard:end -->"
OPS = {
    "<=": ("≤", lambda x, t: x <= t),
    "<": ("<", lambda x, t: x < t),
    ">=": ("≥", lambda x, t: x >= t),
    ">": (">", lambda x, t: x > t),
    "==": ("=", lambda x, t: x == t),
}
ENTRY_KEYS = {
    "area", "quantity", "value", "baseline", "baseline_label", "unit", "goal", "command",
    "source", "note", "order", "digits",
}
HEADER = [
    "| quantity | value | baseline (same run) | ratio | goal | status | measured | reproduce | notes |",
    "|---|---:|---|---:|---|---|---|---|---|",
]


class Invalid(Exception):
    pass


@dataclass
class Entry:
    area: str
    quantity: str
    value: float
    baseline: float | None
    value_text: str  # as written in the figures file (trailing zeros kept), or rounded from a raw output
    baseline_text: str
    baseline_label: str
    unit: str
    goal: dict | None
    command: str
    source: str
    note: str
    order: float
    digits: int | None
    date: str
    commit: str
    time: str
    path: Path  # the figures file

    def sort_key(self) -> tuple:
        return (self.date, self.time, self.path.parent.name, self.path.name)


# ---------------------------------------------------------------- reading runs


def is_number(v: Any) -> bool:
    if isinstance(v, Decimal):
        return v.is_finite()
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def literal_text(v: int | Decimal) -> str:
    """A number as the figures file writes it, with thousands separators: 0.910 stays 0.910."""
    return f"{v:,}" if isinstance(v, int) else format(v, ",f")


def json_pointer(doc: Any, pointer: str, where: str) -> Any:
    """RFC 6901: "" is the whole document, "/a/0/b~1c" walks keys and list indices."""
    if pointer == "":
        return doc
    if not pointer.startswith("/"):
        raise Invalid(f"{where}: pointer {pointer!r} must start with '/'")
    cur = doc
    for raw in pointer[1:].split("/"):
        tok = raw.replace("~1", "/").replace("~0", "~")
        if isinstance(cur, list):
            if not tok.isdigit() or int(tok) >= len(cur):
                raise Invalid(f"{where}: pointer {pointer!r}: no index {tok!r}")
            cur = cur[int(tok)]
        elif isinstance(cur, dict):
            if tok not in cur:
                raise Invalid(f"{where}: pointer {pointer!r}: no key {tok!r}")
            cur = cur[tok]
        else:
            raise Invalid(f"{where}: pointer {pointer!r} walks into a {type(cur).__name__}")
    return cur


def number(v: Any, folder: Path, where: str, cache: dict, digits: int | None) -> tuple[float, str]:
    """A literal number, or {"from": FILE, "pointer": "/a/b", "scale": S} read from a raw
    output in the run folder (shown to `digits` significant digits, default 3).
    Returns (value, text to show)."""
    if is_number(v) and not isinstance(v, float):
        text = literal_text(v) if digits is None else fmt_sig(float(v), digits)
        return float(v), text
    if isinstance(v, dict) and set(v) <= {"from", "pointer", "scale"} and "from" in v:
        name = v["from"]
        if not isinstance(name, str) or not name:
            raise Invalid(f"{where}: 'from' must name a file in the run folder")
        p = (folder / name).resolve()
        if folder.resolve() not in p.parents:
            raise Invalid(f"{where}: 'from' {name!r} is outside the run folder")
        if p not in cache:
            try:
                cache[p] = json.loads(p.read_text(encoding="utf-8"))
            except (OSError, ValueError) as e:
                raise Invalid(f"{where}: cannot read {name}: {e}") from None
        x = json_pointer(cache[p], v.get("pointer", ""), f"{where} ({name})")
        scale = v.get("scale", 1)
        if not is_number(x) or not is_number(scale):
            raise Invalid(f"{where}: {name}{v.get('pointer', '')} is not a number (or bad scale)")
        x = float(x) * float(scale)
        return x, fmt_sig(x, digits or 3)
    raise Invalid(f"{where}: expected a number or {{\"from\", \"pointer\", \"scale\"}}, got {v!r}")


def check_goal(g: Any, has_baseline: bool, where: str) -> dict | None:
    if g is None:
        return None
    if not isinstance(g, dict):
        raise Invalid(f"{where}: goal must be null or an object")
    extra = set(g) - {"op", "target", "on", "noise", "text"}
    if extra:
        raise Invalid(f"{where}: unknown goal keys {sorted(extra)}")
    if g.get("op") not in OPS:
        raise Invalid(f"{where}: goal op must be one of {list(OPS)}")
    if not is_number(g.get("target")):
        raise Invalid(f"{where}: goal target must be a number")
    if g.get("on", "value") not in ("value", "ratio"):
        raise Invalid(f"{where}: goal 'on' must be 'value' or 'ratio'")
    if g.get("on") == "ratio" and not has_baseline:
        raise Invalid(f"{where}: a goal on the ratio needs a baseline")
    if "noise" in g and not (is_number(g["noise"]) and g["noise"] >= 0):
        raise Invalid(f"{where}: goal noise must be a number ≥ 0 (relative, 0.1 = ±10 %)")
    if "text" in g and not isinstance(g["text"], str):
        raise Invalid(f"{where}: goal text must be a string")
    return g


def read_entry(e: Any, i: int, path: Path, date: str, commit: str, time: str, cache: dict) -> Entry:
    where = f"{path}: entry {i}"
    if not isinstance(e, dict):
        raise Invalid(f"{where}: not an object")
    extra = set(e) - ENTRY_KEYS
    if extra:
        raise Invalid(f"{where}: unknown keys {sorted(extra)}")
    for k in ("area", "quantity", "value", "unit", "goal", "command", "source"):
        if k not in e:
            raise Invalid(f"{where}: missing {k!r}")
    for k in ("area", "quantity", "unit", "command", "source"):
        if not isinstance(e[k], str):
            raise Invalid(f"{where}: {k!r} must be a string")
    if not AREA_RE.match(e["area"]):
        raise Invalid(f"{where}: area {e['area']!r} must be lower-case letters, digits and '-'")
    if not e["quantity"].strip() or not e["source"].strip():
        raise Invalid(f"{where}: quantity and source must not be empty")
    for k in ("baseline_label", "note"):
        if k in e and not isinstance(e[k], str):
            raise Invalid(f"{where}: {k!r} must be a string")
    if "order" in e and not is_number(e["order"]):
        raise Invalid(f"{where}: order must be a number")
    digits = e.get("digits")
    if digits is not None and not (isinstance(digits, int) and not isinstance(digits, bool) and 1 <= digits <= 15):
        raise Invalid(f"{where}: digits must be an integer from 1 to 15")
    value, value_text = number(e["value"], path.parent, f"{where} value", cache, digits)
    baseline, baseline_text = None, "—"
    if e.get("baseline") is not None:
        baseline, baseline_text = number(e["baseline"], path.parent, f"{where} baseline", cache, digits)
    if "order" in e:
        e["order"] = float(e["order"])
    goal = check_goal(e["goal"], baseline is not None, where)
    if goal is not None:
        goal = {k: float(x) if isinstance(x, Decimal) else x for k, x in goal.items()}
    return Entry(
        area=e["area"], quantity=e["quantity"].strip(), value=value, baseline=baseline,
        value_text=value_text, baseline_text=baseline_text,
        baseline_label=e.get("baseline_label", ""), unit=e["unit"],
        goal=goal, command=e["command"],
        source=e["source"], note=e.get("note", ""), order=e.get("order", math.inf),
        digits=digits, date=date, commit=commit, time=time, path=path,
    )


def read_runs(runs: Path, verbose: bool) -> tuple[list[Entry], list[str]]:
    entries: list[Entry] = []
    errors: list[str] = []
    if not runs.is_dir():
        return entries, [f"{runs}: no such folder"]
    for folder in sorted(p for p in runs.iterdir() if p.is_dir()):
        m = FOLDER_RE.match(folder.name)
        if not m:
            errors.append(f"{folder}: a run folder is named YYYY-MM-DD-<commit>[-label] (commit: 7-40 hex digits)")
            continue
        date, commit = m.group(1), m.group(2)
        cache: dict = {}
        for path in sorted(folder.glob("*.json")):
            try:
                # Decimal keeps a figure as written (0.910, 46.0) for display.
                doc = json.loads(path.read_text(encoding="utf-8"), parse_float=Decimal)
            except (OSError, ValueError) as e:
                errors.append(f"{path}: not JSON: {e}")
                continue
            time = ""
            if isinstance(doc, dict) and isinstance(doc.get("schema"), str) and doc["schema"].startswith("canopy-bench/"):
                if doc["schema"] != SCHEMA:
                    errors.append(f"{path}: schema {doc['schema']!r}, this script reads {SCHEMA!r}")
                    continue
                c = doc.get("commit", commit)
                if not (isinstance(c, str) and len(c) >= 7 and (c.startswith(commit) or commit.startswith(c))):
                    errors.append(f"{path}: commit {doc['commit']!r} does not match the folder's {commit!r}")
                    continue
                time = doc.get("time", "")
                if not isinstance(time, str) or (time and not time.startswith(date)):
                    errors.append(f"{path}: time {time!r} must be an ISO time on the folder's date {date}")
                    continue
                items = doc.get("entries")
                if not isinstance(items, list):
                    errors.append(f"{path}: 'entries' must be a list")
                    continue
            elif isinstance(doc, list) and doc and all(isinstance(x, dict) and "area" in x for x in doc):
                items = doc
            else:
                if verbose:
                    print(f"raw output, not read as figures: {path}", file=sys.stderr)
                continue
            for i, e in enumerate(items):
                try:
                    entries.append(read_entry(e, i, path, date, commit, time, cache))
                except Invalid as err:
                    errors.append(str(err))
    return entries, errors


def newest(entries: list[Entry]) -> dict[str, list[Entry]]:
    best: dict[tuple[str, str], Entry] = {}
    for e in entries:
        k = (e.area, e.quantity)
        if k not in best or e.sort_key() > best[k].sort_key():
            best[k] = e
    areas: dict[str, list[Entry]] = {}
    for e in best.values():
        areas.setdefault(e.area, []).append(e)
    for rows in areas.values():
        rows.sort(key=lambda e: (e.order, e.quantity))
    return areas


# ---------------------------------------------------------------- rendering


def fmt_sig(v: float, digits: int) -> str:
    """`digits` significant digits, trailing zeros kept, thousands separators: 1.10, 0.0533, 189."""
    if v == 0:
        return "0"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(v))))
    return f"{v:,.{decimals}f}"


def with_unit(s: str, unit: str) -> str:
    return f"{s} {unit}" if unit else s


def cell(s: str) -> str:
    return s.replace("\n", " ").replace("|", "\\|")


def code(s: str) -> str:
    s = " ".join(s.split())
    if not s:
        return "—"
    tick = "``" if "`" in s else "`"
    pad = " " if tick == "``" else ""
    return f"{tick}{pad}{s}{pad}{tick}"


def ratio(e: Entry) -> float | None:
    if e.baseline is None or e.baseline == 0:
        return None
    return e.value / e.baseline


def fmt_ratio(r: float | None) -> str:
    if r is None:
        return "—"
    s = f"{fmt_sig(r, 3)}×"
    if 0 < r < 0.9:  # "1/x": x times less
        s += f" (1/{fmt_sig(1 / r, 3)})"
    return s


def fmt_goal(e: Entry) -> str:
    g = e.goal
    if g is None:
        return "—"
    if "text" in g:
        return g["text"]
    sym = OPS[g["op"]][0]
    target = g["target"]
    text = f"{int(target):,}" if float(target).is_integer() else f"{target:,}"
    if g.get("on") == "ratio":
        return f"ratio {sym} {fmt_sig(target, 3)}"
    return f"{sym} {with_unit(text, e.unit)}"


def status(e: Entry) -> str:
    g = e.goal
    if g is None:
        return "—"
    x = ratio(e) if g.get("on") == "ratio" else e.value
    t = g["target"]
    noise = g.get("noise")
    if noise and abs(x - t) <= noise * abs(t):
        return f"within noise (±{noise * 100:g} %)"
    return "met" if OPS[g["op"]][1](x, t) else "**not met**"


def row(e: Entry, doc_dir: Path) -> str:
    value = with_unit(e.value_text, e.unit)
    if e.baseline is None:
        base = "—"
    else:
        base = with_unit(e.baseline_text, e.unit)
        if e.baseline_label:
            base += f" ({e.baseline_label})"
    link = Path(os.path.relpath(e.path, doc_dir)).as_posix()
    measured = f"[{e.date}]({link}) `{e.commit[:7]}`"
    if e.source.lower().startswith("transcribed"):
        measured += " †"
    cells = [e.quantity, value, base, fmt_ratio(ratio(e)), fmt_goal(e), status(e), measured]
    return "| " + " | ".join([cell(c) for c in cells] + [cell(code(e.command)), cell(e.note)]) + " |"


def table(rows: list[Entry], doc_dir: Path) -> list[str]:
    if not rows:
        return ["_No run for this area yet._", ""]
    return HEADER + [row(e, doc_dir) for e in rows] + [""]


def render(text: str, areas: dict[str, list[Entry]], doc_dir: Path) -> tuple[str, list[str]]:
    out: list[str] = []
    errors: list[str] = []
    seen: set[str] = set()
    lines = text.split("\n")
    i = 0
    while i < len(lines):
        line = lines[i]
        m = BEGIN_RE.match(line.strip())
        if line.strip() == END:
            errors.append(f"line {i + 1}: {END} without a begin marker")
        if not m:
            out.append(line)
            i += 1
            continue
        area = m.group(1)
        if area in seen:
            errors.append(f"line {i + 1}: a second table for area {area!r}")
        seen.add(area)
        j = i + 1
        while j < len(lines) and lines[j].strip() != END:
            if BEGIN_RE.match(lines[j].strip()):
                errors.append(f"line {j + 1}: begin marker inside area {area!r}")
            j += 1
        if j == len(lines):
            errors.append(f"line {i + 1}: area {area!r} has no {END}")
            out.extend(lines[i:])
            break
        out.append(line)
        out.extend(table(areas.get(area, []), doc_dir))
        out.append(lines[j])
        i = j + 1
    for area in sorted(set(areas) - seen):
        errors.append(f"runs name area {area!r}, which has no '<!-- dashboard:begin area={area} -->' marker")
    return "\n".join(out), errors


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="exit 1 if the file differs from what would be written")
    ap.add_argument("--doc", type=Path, default=HERE.parent / "BENCHMARKS.md", help="the dashboard (BENCHMARKS.md)")
    ap.add_argument("--runs", type=Path, default=HERE / "runs", help="the runs folder (benchmarks/runs)")
    ap.add_argument("-v", "--verbose", action="store_true", help="list JSON files read as raw outputs")
    a = ap.parse_args(argv)

    entries, errors = read_runs(a.runs, a.verbose)
    try:
        text = a.doc.read_text(encoding="utf-8")
    except OSError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    areas = newest(entries)
    new, render_errors = render(text, areas, a.doc.resolve().parent)
    errors += render_errors
    if errors:
        for err in errors:
            print(f"error: {err}", file=sys.stderr)
        return 2
    rows = sum(len(v) for v in areas.values())
    if a.check:
        if new == text:
            print(f"{a.doc}: up to date ({rows} rows in {len(areas)} areas from {len(entries)} entries)")
            return 0
        diff = difflib.unified_diff(text.splitlines(), new.splitlines(), str(a.doc), "generated", lineterm="")
        for n, d in enumerate(diff):
            if n == 200:
                print("... (diff cut)", file=sys.stderr)
                break
            print(d, file=sys.stderr)
        print(f"{a.doc} differs from what benchmarks/dashboard.py writes: run it and commit the result",
              file=sys.stderr)
        return 1
    if new != text:
        a.doc.write_text(new, encoding="utf-8")
        print(f"{a.doc}: written ({rows} rows in {len(areas)} areas from {len(entries)} entries)")
    else:
        print(f"{a.doc}: already up to date ({rows} rows in {len(areas)} areas)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
