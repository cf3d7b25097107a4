#!/usr/bin/env python3
"""One-instance edit latency and server CPU per edit on large scenes (issue 23), baseline and
this build in one run, alternating A/B/A/B.

  python3 benchmarks/edit_bench.py BASE_BIN NEW_BIN OUT.json [--rounds R] [--edits N] [--sizes 50000,200000]

Per run and size: a fresh data folder; the scene built through the API (a creation of 10,000
instances, then edits of 10,000 adds), 5 warm-up moves, then N one-instance moves back to back
(each to a new place, so it changes two tiles; retention at its default of 20 versions, so every
edit past the 20th prunes one). Latency is the client's HTTP round trip; CPU is the server
process's user + system time over the moves, divided by their count (it includes each edit's
cleanup after its answer). Run it at nice -20 (as root) so that the figures are those of a server
that gets a core when it asks for one. Writes per-round figures and, per size and binary, the
medians over the rounds (/summary_medians/<size>/<base|new>/<p50_ms|p99_ms|cpu_ms_per_edit>).
"""
import argparse, http.client, json, os, shutil, subprocess, tempfile, time


def start(binary, data):
    p = subprocess.Popen([binary, "serve", "--data", data, "--addr", "127.0.0.1:0",
                          "--demo-synthetic", "2", "--demo-trees", "400", "--edits-per-s", "1000"],
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    return p, int(p.stdout.readline().strip().rsplit(":", 1)[1])


class Client:
    def __init__(self, port):
        self.c = http.client.HTTPConnection("127.0.0.1", port, timeout=300)

    def req(self, method, path, body=None, token=None):
        h = {"Content-Type": "application/json"}
        if token:
            h["Authorization"] = "Bearer " + token
        self.c.request(method, path, body=json.dumps(body) if body is not None else None, headers=h)
        r = self.c.getresponse()
        return r.status, r.read()


def pct(xs, p):
    xs = sorted(xs)
    return xs[round((len(xs) - 1) * p)]


def insts(model, start, n):
    return [{"model": model, "position": [((k * 0.618) % 1) * 1900 - 950, 0, ((k * 0.414) % 1) * 1900 - 950]}
            for k in range(start, start + n)]


def cpu(pid):
    f = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def run(binary, size, n):
    data = tempfile.mkdtemp(prefix="edit-bench-")
    p, port = start(binary, data)
    try:
        token = open(os.path.join(data, "creation-token")).read().strip()
        c = Client(port)
        model = json.loads(c.req("GET", "/api/scenes/demo/manifest")[1])["models"][0]["name"]
        s, d = c.req("POST", "/api/scenes", {"id": "big", "name": "big", "bounds": {"min": [-1000, -1000], "max": [1000, 1000]},
                                             "instances": insts(model, 0, 10000)}, token)
        assert s == 201, (s, d)
        wb = json.loads(d)["write_token"]
        for k in range(1, size // 10000):
            s, d = c.req("POST", "/api/scenes/big/instances", {"add": insts(model, k * 10000, 10000)}, wb)
            assert s == 200, (s, d)
        for k in range(5):
            c.req("POST", "/api/scenes/big/instances", {"move": [{"id": 1 + k, "position": [k, 0, 5]}]}, wb)
        lat, c0 = [], cpu(p.pid)
        for k in range(n):
            t0 = time.perf_counter()
            s, d = c.req("POST", "/api/scenes/big/instances", {"move": [{"id": 100 + k, "position": [k, 0, 5]}]}, wb)
            lat.append(time.perf_counter() - t0)
            assert s == 200, (s, d)
        cpu_ms = (cpu(p.pid) - c0) / n * 1e3
        return {"size": size, "edits": n, "p50_ms": pct(lat, .5) * 1e3, "p90_ms": pct(lat, .9) * 1e3,
                "p99_ms": pct(lat, .99) * 1e3, "cpu_ms_per_edit": cpu_ms,
                "latencies_ms": [round(x * 1e3, 2) for x in lat], "load": os.getloadavg()}
    finally:
        p.terminate()
        p.wait()
        shutil.rmtree(data, ignore_errors=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("base")
    ap.add_argument("new")
    ap.add_argument("out")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--edits", type=int, default=100)
    ap.add_argument("--sizes", default="50000", help="scene sizes, multiples of 10,000 (comma-separated)")
    a = ap.parse_args()
    sizes = [int(s) for s in a.sizes.split(",")]
    res = {"machine": os.uname().nodename, "cores": os.cpu_count(), "build": "release", "rounds": []}
    for r in range(a.rounds):
        for size in sizes:
            for name, b in (("base", a.base), ("new", a.new)):
                out = run(b, size, a.edits)
                out.update(binary=name, round=r)
                res["rounds"].append(out)
                print(name, json.dumps({k: v for k, v in out.items() if k != "latencies_ms"}), flush=True)
    res["summary_medians"] = {
        str(size): {name: {m: sorted(x[m] for x in res["rounds"] if x["size"] == size and x["binary"] == name)[a.rounds // 2]
                           for m in ("p50_ms", "p99_ms", "cpu_ms_per_edit")}
                    for name in ("base", "new")}
        for size in sizes}
    print(json.dumps(res["summary_medians"]))
    json.dump(res, open(a.out, "w"), indent=1)


if __name__ == "__main__":
    main()
