#!/usr/bin/env python3
"""Issue 23 store figures, packs stored per tile: baseline and this build in one run, A/B/A/B.

usage: store_bench.py BASE_BIN NEW_BIN OUT.json [ROUNDS]
Per run (a fresh data folder, creation token, --edits-per-s 1000): a 50,000-instance scene built
through the API (a creation of 10,000 and four edits of 10,000 adds) and a 100-instance one;
B: 60 one-instance moves on the big scene, one at a time: latency, bytes the server process
wrote (/proc/PID/io wchar) per edit, the big scene's folder on disk after 35 and 65 versions; C: 400 manifest reads
of the small scene, 20 ms apart, idle, then 400 while 4 clients move instances of the big scene back to back.
"""
import json, os, shutil, subprocess, sys, tempfile, threading, time, http.client

def start(binary, data):
    p = subprocess.Popen([binary, "serve", "--data", data, "--addr", "127.0.0.1:0", "--demo-synthetic", "2",
                          "--demo-trees", "400", "--edits-per-s", "1000"],
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    port = int(p.stdout.readline().strip().rsplit(":", 1)[1])
    return p, port

class Client:
    def __init__(self, port): self.c = http.client.HTTPConnection("127.0.0.1", port, timeout=120)
    def req(self, method, path, body=None, token=None):
        h = {"Content-Type": "application/json"}
        if token: h["Authorization"] = "Bearer " + token
        self.c.request(method, path, body=json.dumps(body) if body is not None else None, headers=h)
        r = self.c.getresponse(); return r.status, r.read()

def pct(xs, p):
    xs = sorted(xs); return xs[round((len(xs) - 1) * p)]

def insts(model, start, n):
    return [{"model": model, "position": [((k * 0.618) % 1) * 1900 - 950, 0, ((k * 0.414) % 1) * 1900 - 950]}
            for k in range(start, start + n)]

def wchar(pid):
    for l in open(f"/proc/{pid}/io"):
        if l.startswith("wchar:"): return int(l.split()[1])

def folder_bytes(d):
    # Files deleted meanwhile (the server deletes pruned files after answering) count as gone.
    n = 0
    for r, _, fs in os.walk(d):
        for f in fs:
            try: n += os.path.getsize(os.path.join(r, f))
            except FileNotFoundError: pass
    return n

def run(binary):
    data = tempfile.mkdtemp(prefix="store-bench-")
    p, port = start(binary, data)
    out = {}
    try:
        token = open(os.path.join(data, "creation-token")).read().strip()
        c = Client(port)
        model = json.loads(c.req("GET", "/api/scenes/demo/manifest")[1])["models"][0]["name"]
        def create(id_, n):
            s, d = c.req("POST", "/api/scenes", {"id": id_, "name": id_, "bounds": {"min": [-1000, -1000], "max": [1000, 1000]},
                                                 "instances": insts(model, 0, n)}, token)
            assert s == 201, (s, d); return json.loads(d)["write_token"]
        wb = create("big", 10000)
        for k in range(1, 5):
            s, d = c.req("POST", "/api/scenes/big/instances", {"add": insts(model, k * 10000, 10000)}, wb)
            assert s == 200, (s, d)
        create("small", 100)
        m = json.loads(c.req("GET", "/api/scenes/big/manifest")[1])
        out["big_pack_bytes"] = m["pack"]["size"]; out["big_tiles"] = len(m["tiles"])
        lat = []; w0 = wchar(p.pid)
        for k in range(60):
            t0 = time.perf_counter()
            s, d = c.req("POST", "/api/scenes/big/instances", {"move": [{"id": 1 + k, "position": [k, 0, 5]}]}, wb)
            lat.append(time.perf_counter() - t0); assert s == 200, (s, d)
            if k == 29:  # 35 versions, as the earlier run measured
                out["big_scene_disk_bytes_after_35_versions"] = folder_bytes(os.path.join(data, "assets", "scenes", "big"))
        out["edit_50k_one_move_ms"] = {"p50": pct(lat, .5) * 1e3, "p99": pct(lat, .99) * 1e3, "n": len(lat)}
        out["written_per_edit_bytes"] = (wchar(p.pid) - w0) / len(lat)
        out["big_scene_folder_bytes_after"] = folder_bytes(os.path.join(data, "assets", "scenes", "big"))
        def reads(n, gap=0.02):
            # Spread over n × gap seconds, so that the loaded ones overlap many edits.
            r = Client(port); xs = []
            for _ in range(n):
                t0 = time.perf_counter(); s, _ = r.req("GET", "/api/scenes/small/manifest"); xs.append(time.perf_counter() - t0)
                assert s == 200
                time.sleep(gap)
            return xs
        reads(20); idle = reads(400)
        stop_w = [False]; edits = [0]
        def writer(k):
            w = Client(port); n = 0
            while not stop_w[0]:
                s, _ = w.req("POST", "/api/scenes/big/instances", {"move": [{"id": 1 + k * 1000 + n % 1000, "position": [n % 900, 0, 1]}]}, wb)
                assert s == 200, s
                n += 1; edits[0] += 1
        ws = [threading.Thread(target=writer, args=(k,)) for k in range(4)]
        [w.start() for w in ws]
        while edits[0] == 0: time.sleep(0.01)
        e0 = edits[0]; t0 = time.time(); loaded = reads(400); dur = time.time() - t0; e1 = edits[0]
        stop_w[0] = True; [w.join() for w in ws]
        out["reads_other_scene_ms"] = {"idle_p50": pct(idle, .5) * 1e3, "idle_p99": pct(idle, .99) * 1e3,
                                       "writers4_p50": pct(loaded, .5) * 1e3, "writers4_p99": pct(loaded, .99) * 1e3,
                                       "edits_per_s_during": (e1 - e0) / dur, "seconds": dur}
    finally:
        p.terminate(); p.wait(); shutil.rmtree(data, ignore_errors=True)
    return out

if __name__ == "__main__":
    base, new, path = sys.argv[1:4]
    rounds = int(sys.argv[4]) if len(sys.argv) > 4 else 2
    res = {"machine": os.uname().nodename, "cores": os.cpu_count(), "build": "dev profile (opt-level 1, deps 2)",
           "load_before": os.getloadavg(), "base": [], "new": []}
    for r in range(rounds):
        res["base"].append(run(base)); print("base", json.dumps(res["base"][-1]), flush=True)
        res["new"].append(run(new)); print("new", json.dumps(res["new"][-1]), flush=True)
    res["load_after"] = os.getloadavg()
    json.dump(res, open(path, "w"), indent=1)
