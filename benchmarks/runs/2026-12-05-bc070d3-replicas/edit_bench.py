"""One-instance edit latency over HTTP, acknowledged (POST answered) and visible on the other
replica (its GET /api/scenes/ID shows the new version), two replicas on PostgreSQL against one
server on SQLite, alternating rounds. Usage: edit_bench.py BIN PG_URL OUT.json [EDITS] [ROUNDS]"""
import json, shutil, signal, subprocess, sys, time, urllib.request
BIN, PG, OUT = sys.argv[1], sys.argv[2], sys.argv[3]
EDITS = int(sys.argv[4]) if len(sys.argv) > 4 else 200
ROUNDS = int(sys.argv[5]) if len(sys.argv) > 5 else 3

def start(data, extra):
    p = subprocess.Popen([BIN, "serve", "--data", data, "--addr", "127.0.0.1:0", "--open-creation",
                          "--edits-per-s", "100000", "--demo-synthetic", "1", "--demo-trees", "10"] + extra,
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    for line in p.stdout:
        if "listening on http://" in line:
            return p, "http://" + line.split("http://")[1].strip()
    raise SystemExit("server did not start")

def req(base, method, path, body=None, token=None):
    r = urllib.request.Request(base + path, method=method, data=None if body is None else json.dumps(body).encode())
    if body is not None: r.add_header("Content-Type", "application/json")
    if token: r.add_header("Authorization", "Bearer " + token)
    with urllib.request.urlopen(r, timeout=30) as f: return json.loads(f.read() or b"null")

def pct(v, q): v = sorted(v); return v[min(len(v) - 1, int(q * len(v)))]

def run(kind, rnd):
    data = f"/tmp/repbench/{kind}-{rnd}"
    shutil.rmtree(data, ignore_errors=True)
    if kind == "sqlite":
        p, a = start(data, []); procs = [p]; b = a
    else:
        db = f"bench_{rnd}"
        for sql in (f"DROP DATABASE IF EXISTS {db} WITH (FORCE)", f"CREATE DATABASE {db}"):
            subprocess.run(["psql", PG, "-qc", sql], check=True, capture_output=True)
        url = PG.rsplit("/", 1)[0] + "/" + db
        p1, a = start(data, ["--database", url])
        p2, b = start(data, ["--database", url, "--no-demo"]); procs = [p1, p2]
    try:
        inst = [{"model": "synthetic-0", "position": [k, 0, 1]} for k in range(10)]
        tok = req(a, "POST", "/api/scenes", {"name": "b", "id": "b", "bounds": {"min": [0, 0], "max": [100, 100]}, "instances": inst})["write_token"]
        ack, seen = [], []
        for n in range(EDITS):
            t0 = time.perf_counter()
            v = req(a, "POST", "/api/scenes/b/instances", {"move": [{"id": 1, "position": [n % 97, 0, 3]}]}, tok)["version"]
            t1 = time.perf_counter()
            while req(b, "GET", "/api/scenes/b")["version"] < v: pass
            t2 = time.perf_counter()
            ack.append((t1 - t0) * 1e3); seen.append((t2 - t0) * 1e3)
        return {"kind": kind, "round": rnd, "ack_p50": pct(ack, .5), "ack_p99": pct(ack, .99), "seen_p50": pct(seen, .5), "seen_p99": pct(seen, .99), "ack_mean": sum(ack) / len(ack)}
    finally:
        for p in procs: p.send_signal(signal.SIGTERM); p.wait()

out = []
for rnd in range(ROUNDS):
    for kind in ("sqlite", "postgres"):
        r = run(kind, rnd); out.append(r); print(json.dumps(r), flush=True)
json.dump(out, open(OUT, "w"), indent=1)
