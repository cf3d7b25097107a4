"""Replicas on PostgreSQL against one server on SQLite (issue 24's figures), on this machine.

  python3 benchmarks/replicas.py SERVER_BIN CANOPY_BIN PG_URL OUT_DIR [--quick] [--only=kill,edits,nginx,presence]

Three parts, each against its baseline in the same run:
1. kill: acknowledged edits lost after `kill -9` during a burst of edits (4 writers): SQLite (one
   server, restarted on its data) and PostgreSQL (two replicas, the survivor checked). Goal 0.
2. edits under load: one-instance edits through replica A, acknowledged and visible on replica B,
   while `canopy load` viewers stream from both replicas (half each); against one SQLite server
   under the same `canopy load` (all viewers on it).
3. load through nginx: `canopy load` through nginx (round robin over two replicas, tree assets from
   disk) against the same load on one replica directly.
4. presence: a viewer on replica A moves (one pose every 150 ms); the time until a viewer on replica B
   is told of each pose, against a second viewer on A (same server, no relay). Goal: under 1 s.
Writes OUT_DIR/results.json; PG_URL names a role that may create databases.
"""
import base64, json, os, socket, struct, random, shutil, signal, subprocess, sys, tempfile, threading, time, urllib.error, urllib.request

SERVER, CANOPY, PG, OUT = sys.argv[1:5]
QUICK = "--quick" in sys.argv
TRIALS = 3 if QUICK else 10
EDITS = 60 if QUICK else 300
LOAD_S = 10 if QUICK else 30
CLIENTS = 32
NGINX_CLIENTS = 256
NGINX_S = 10  # the cold burst: 256 viewers fetch nearly all they need in the first ~10 s
NGINX_ROUNDS = 1 if QUICK else 3
ONLY = next((a.split("=", 1)[1].split(",") for a in sys.argv if a.startswith("--only=")), None)
NGINX = shutil.which("nginx") or "/usr/sbin/nginx"
WORK = tempfile.mkdtemp(prefix="canopy-replicas-")


def start(data, extra):
    p = subprocess.Popen([SERVER, "serve", "--data", data, "--addr", "127.0.0.1:0", "--open-creation",
                          "--edits-per-s", "100000", "--demo-synthetic", "2", "--demo-trees", "300"] + extra,
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    for line in p.stdout:
        if "listening on http://" in line:
            threading.Thread(target=lambda: [None for _ in p.stdout], daemon=True).start()
            return p, "http://" + line.split("http://")[1].strip()
    raise SystemExit("server did not start")


def req(base, method, path, body=None, token=None, timeout=30):
    r = urllib.request.Request(base + path, method=method, data=None if body is None else json.dumps(body).encode())
    if body is not None:
        r.add_header("Content-Type", "application/json")
    if token:
        r.add_header("Authorization", "Bearer " + token)
    with urllib.request.urlopen(r, timeout=timeout) as f:
        return json.loads(f.read() or b"null")


def fresh_db(name):
    for sql in (f"DROP DATABASE IF EXISTS {name} WITH (FORCE)", f"CREATE DATABASE {name}"):
        subprocess.run(["psql", PG, "-qc", sql], check=True, capture_output=True)
    return PG.rsplit("/", 1)[0] + "/" + name


def pct(v, q):
    v = sorted(v)
    return v[min(len(v) - 1, int(q * len(v)))] if v else None


def stop(procs):
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
            p.wait()


def create(base, sid, n=10):
    inst = [{"model": "synthetic-0", "position": [k % 90 + 1, 0, 1 + k // 90]} for k in range(n)]
    return req(base, "POST", "/api/scenes", {"name": sid, "id": sid, "bounds": {"min": [0, 0], "max": [100, 100]},
                                             "instances": inst})["write_token"]


def ids(base, sid):
    return {i["id"] for i in req(base, "GET", f"/api/scenes/{sid}/instances")["instances"]}


def kill_trial(kind, k):
    data = f"{WORK}/kill-{kind}-{k}"
    if kind == "sqlite":
        a, ua = start(data, [])
        targets, procs = [ua], [a]
    else:
        url = fresh_db(f"kill_{k}")
        a, ua = start(data, ["--database", url])
        b, ub = start(data, ["--database", url, "--no-demo"])
        targets, procs = [ua, ub], [a, b]
    tok = create(ua, "burst", 0)
    acked, lock, done = [], threading.Lock(), threading.Event()

    def writer(w):
        n = 0
        while not done.is_set():
            base = targets[w % len(targets)]
            try:
                r = req(base, "POST", "/api/scenes/burst/instances",
                        {"add": [{"model": "synthetic-0", "position": [(w * 23 + n) % 97 + 1, 0, 5]}]}, tok, timeout=5)
                with lock:
                    acked.append(r["added_ids"][0])
            except Exception:
                if base == ua and a.poll() is not None:
                    return
            n += 1

    ws = [threading.Thread(target=writer, args=(w,)) for w in range(4)]
    for w in ws:
        w.start()
    time.sleep(random.uniform(0.5, 1.5))
    a.send_signal(signal.SIGKILL)
    a.wait()
    time.sleep(0.3)
    done.set()
    for w in ws:
        w.join()
    if kind == "sqlite":
        a, ua = start(data, [])
        procs = [a]
        check = ua
    else:
        check = ub
    try:
        kept = ids(check, "burst")
        versions = [v["version"] for v in req(check, "GET", "/api/scenes/burst/versions")["versions"]]
        manifest_ok = urllib.request.urlopen(check + "/api/scenes/burst/manifest", timeout=10).status == 200
    finally:
        stop(procs)
    lost = sorted(set(acked) - kept)
    return {"kind": kind, "trial": k, "acknowledged": len(acked), "lost": len(lost), "lost_ids": lost[:20],
            "duplicate_acks": len(acked) - len(set(acked)), "versions_unique": len(versions) == len(set(versions)),
            "served_after": manifest_ok}


def load(url, clients, seconds, out, fps=30, cache_mb=64):
    r = subprocess.run([CANOPY, "load", url, "--clients", str(clients), "--duration", str(seconds), "--fps", str(fps),
                        "--cache-mb", str(cache_mb), "--out", out, "--json"], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"canopy load failed: {r.stderr[-2000:]}")
    return json.loads(r.stdout)


def edits_under_load(kind):
    data = f"{WORK}/load-{kind}"
    if kind == "sqlite":
        a, ua = start(data, [])
        ub, procs, views = ua, [a], [(ua, CLIENTS)]
    else:
        url = fresh_db("under_load")
        a, ua = start(data, ["--database", url])
        b, ub = start(data, ["--database", url, "--no-demo"])
        procs, views = [a, b], [(ua, CLIENTS // 2), (ub, CLIENTS - CLIENTS // 2)]
    try:
        tok = create(ua, "edits")
        results = [None] * len(views)
        loaders = [threading.Thread(target=lambda i=i, u=u, c=c: results.__setitem__(
            i, load(f"{u}/api/scenes/demo", c, LOAD_S, f"{WORK}/load-{kind}-{i}"))) for i, (u, c) in enumerate(views)]
        for t in loaders:
            t.start()
        time.sleep(2)
        ack, seen, t_end = [], [], time.time() + LOAD_S - 4
        n = 0
        while time.time() < t_end and n < EDITS:
            t0 = time.perf_counter()
            v = req(ua, "POST", "/api/scenes/edits/instances", {"move": [{"id": 1, "position": [n % 97 + 1, 0, 3]}]}, tok)["version"]
            t1 = time.perf_counter()
            while req(ub, "GET", "/api/scenes/edits")["version"] < v:
                pass
            t2 = time.perf_counter()
            ack.append((t1 - t0) * 1e3)
            seen.append((t2 - t0) * 1e3)
            n += 1
            time.sleep(0.02)
        for t in loaders:
            t.join()
    finally:
        stop(procs)
    return {"kind": kind, "edits": len(ack), "ack_p50": pct(ack, .5), "ack_p99": pct(ack, .99),
            "seen_p50": pct(seen, .5), "seen_p99": pct(seen, .99),
            "load_requests_per_s": sum(r["requests_per_s"] for r in results),
            "load_errors": sum(r["errors"] for r in results), "loads": results}


def nginx_conf(port, a, b, data):
    d = f"{WORK}/nginx"
    os.makedirs(d, exist_ok=True)
    ha, hb = a.split("//")[1], b.split("//")[1]
    conf = f"""daemon off; master_process off; worker_processes 1; pid {d}/nginx.pid; error_log {d}/error.log warn;
events {{ worker_connections 1024; }}
http {{
  access_log off; types {{ }} default_type application/octet-stream; sendfile on;
  client_body_temp_path {d}/body; proxy_temp_path {d}/proxy; fastcgi_temp_path {d}/fcgi;
  uwsgi_temp_path {d}/uwsgi; scgi_temp_path {d}/scgi;
  upstream replicas {{ server {ha} max_fails=1 fail_timeout=5s; server {hb} max_fails=1 fail_timeout=5s; keepalive 32; }}
  server {{
    listen 127.0.0.1:{port};
    location /assets/ {{ alias {os.path.abspath(data)}/assets/; }}
    location /assets/scenes/ {{ proxy_pass http://replicas; proxy_http_version 1.1; proxy_set_header Connection ""; }}
    location / {{ proxy_pass http://replicas; proxy_http_version 1.1; proxy_set_header Connection "";
                 proxy_set_header Host $host; proxy_next_upstream error timeout http_503; }}
  }}
}}
"""
    open(f"{d}/nginx.conf", "w").write(conf)
    return f"{d}/nginx.conf", d


def through_nginx():
    data = f"{WORK}/lb"
    url = fresh_db("lb")
    a, ua = start(data, ["--database", url])
    b, ub = start(data, ["--database", url, "--no-demo"])
    import socket
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    conf, prefix = nginx_conf(port, ua, ub, data)
    ng = subprocess.Popen([NGINX, "-c", conf, "-p", prefix], stderr=subprocess.DEVNULL)
    time.sleep(0.5)
    try:
        # Back to back, many cold viewers at once, alternating; medians over rounds.
        lbs, ones = [], []
        for k in range(NGINX_ROUNDS):
            lbs.append(load(f"http://127.0.0.1:{port}/api/scenes/demo", NGINX_CLIENTS, NGINX_S, f"{WORK}/lb-{k}", fps=0))
            ones.append(load(f"{ua}/api/scenes/demo", NGINX_CLIENTS, NGINX_S, f"{WORK}/one-{k}", fps=0))
    finally:
        ng.send_signal(signal.SIGTERM)
        ng.wait()
        stop([a, b])
    pick = lambda r: {k: r[k] for k in ("requests_per_s", "latency", "errors", "requests", "bytes", "frames") if k in r}
    med = lambda rs: {"requests_per_s": pct([r["requests_per_s"] for r in rs], .5),
                      "p99_ms": pct([r["latency"]["p99_ms"] for r in rs], .5),
                      "errors": sum(r["errors"] for r in rs), "rounds": [pick(r) for r in rs]}
    return {"nginx_two_replicas": med(lbs), "one_replica": med(ones)}


class Ws:
    """The smallest WebSocket client the live endpoint needs: text frames out (masked), frames in."""

    def __init__(self, base, path):
        host, port = base.split("//")[1].split(":")
        self.s = socket.create_connection((host, int(port)), timeout=10)
        key = base64.b64encode(os.urandom(16)).decode()
        self.s.sendall((f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\n"
                        f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.s.recv(1)
        if b" 101 " not in head.split(b"\r\n")[0]:
            raise SystemExit(f"no upgrade: {head[:200]!r}")

    def _exact(self, n):
        b = b""
        while len(b) < n:
            c = self.s.recv(n - len(b))
            if not c:
                raise EOFError
            b += c
        return b

    def send(self, obj, opcode=1):
        data = json.dumps(obj).encode() if opcode == 1 else obj
        mask = os.urandom(4)
        n = len(data)
        head = bytes([0x80 | opcode]) + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n))
        self.s.sendall(head + mask + bytes(c ^ mask[i % 4] for i, c in enumerate(data)))

    def recv(self):
        while True:
            b0, b1 = self._exact(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._exact(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._exact(8))[0]
            data = self._exact(n)
            if b0 & 0x0F == 9:
                self.send(data, opcode=10)
            elif b0 & 0x0F == 8:
                raise EOFError
            elif b0 & 0x0F == 1:
                return json.loads(data)


def presence():
    data = f"{WORK}/presence"
    url = fresh_db("presence")
    a, ua = start(data, ["--database", url])
    b, ub = start(data, ["--database", url, "--no-demo"])
    poses = 40 if QUICK else 200
    try:
        path = "/api/scenes/demo/live"
        mover = Ws(ua, path)
        me = mover.recv()["viewer"]
        seen = {"same_replica": {}, "other_replica": {}}

        def watch(base, key):
            w = Ws(base, path)
            w.recv()
            try:
                while True:
                    m = w.recv()
                    if m.get("type") == "presence" and m.get("viewer") == me:
                        seen[key].setdefault(int(m["pose"]["position"][0]), time.perf_counter())
            except (EOFError, OSError):
                pass

        for base, key in ((ua, "same_replica"), (ub, "other_replica")):
            threading.Thread(target=watch, args=(base, key), daemon=True).start()
        time.sleep(3)
        sent = {}
        for n in range(poses):
            sent[n] = time.perf_counter()
            mover.send({"type": "pose", "position": [n, 2.0, 3.0], "orientation": [0.0, 0.0, 0.0, 1.0]})
            time.sleep(0.15)
        time.sleep(2)
    finally:
        stop([a, b])
    res = {"poses": poses, "interval_ms": 150}
    for key, got in seen.items():
        lat = [(got[n] - sent[n]) * 1e3 for n in sent if n in got]
        res[key] = {"told": len(lat), "p50_ms": pct(lat, .5), "p99_ms": pct(lat, .99), "max_ms": max(lat) if lat else None}
    return res


out = {"quick": QUICK, "clients": CLIENTS, "load_s": LOAD_S, "nginx_clients": NGINX_CLIENTS, "nginx_s": NGINX_S}
kills = []
for k in range(TRIALS if ONLY is None or "kill" in ONLY else 0):
    for kind in ("sqlite", "postgres"):
        r = kill_trial(kind, k)
        kills.append(r)
        print(json.dumps(r), flush=True)
out["kill"] = kills
out["kill_totals"] = {kind: {"trials": sum(1 for r in kills if r["kind"] == kind),
                             "acknowledged": sum(r["acknowledged"] for r in kills if r["kind"] == kind),
                             "lost": sum(r["lost"] for r in kills if r["kind"] == kind)} for kind in ("sqlite", "postgres")}
print(json.dumps(out["kill_totals"]), flush=True)
if ONLY is None or "edits" in ONLY:
    out["edits_under_load"] = {kind: edits_under_load(kind) for kind in ("sqlite", "postgres")}
    print(json.dumps({k: {x: v[x] for x in ("ack_p50", "ack_p99", "seen_p50", "seen_p99", "load_requests_per_s")}
                      for k, v in out["edits_under_load"].items()}), flush=True)
if ONLY is None or "nginx" in ONLY:
    out["nginx"] = through_nginx()
    print(json.dumps(out["nginx"]), flush=True)
if ONLY is None or "presence" in ONLY:
    out["presence"] = presence()
    print(json.dumps(out["presence"]), flush=True)
os.makedirs(OUT, exist_ok=True)
json.dump(out, open(os.path.join(OUT, "results.json"), "w"), indent=1)
shutil.rmtree(WORK, ignore_errors=True)
