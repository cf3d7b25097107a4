//! The link model (`client/src/net/link.rs`) against a real shaped link: `canopy fly` on the
//! virtual clock with `--link`, and `canopy fly --wall-clock` over real TCP through the kernel's
//! token bucket and a delay line, on the same scene, path and link. Time to the first complete
//! frame and time to settled must agree within 15 %.
//!
//! The shaped path lives in a network namespace the test makes (`unshare -n`: the test binary
//! runs itself again inside it), on its loopback only:
//!
//! ```text
//! canopy fly --wall-clock ── 127.0.0.1:P ── delay line ── 127.0.0.1:S canopy-server
//!            htb 1:10: sport P, the downlink rate, shared by 1:100–1:10f (one per connection)
//!            htb 1:20: dport P, the uplink rate (requests, ACKs)
//!            htb 1:30: everything else, unshaped (the delay line ↔ server leg)
//! ```
//!
//! The rate is the kernel's (`htb`, a token bucket per class: the kernel here has `tbf` and `htb`
//! but not `netem`, and `tbf` alone would also shape the delay line's own leg to the server, so
//! every byte twice). `lo` runs at a 1,500-byte MTU and one segment per packet in the namespace, so
//! segments and their headers are what the model counts (htb counted 628,048 bytes for a
//! 600,000-byte range; the model's wire bytes for it: 627,652). The delay is a user-space delay
//! line ([`DelayLine`]): each chunk read is written on `rtt / 2` later in each direction, and a new
//! connection's first request is held one round trip more for the TCP handshake the model charges
//! (the client's `connect` to the delay line completes at once). What it does not reproduce: the
//! delay is outside TCP's own loop (the shaped connection's round trip is microseconds), so TCP
//! slow start plays no part on either side of the comparison.
//!
//! Needs root, `unshare`, `ip` and `tc` with `htb` and `u32`: skipped with a message where they
//! are missing, and a failure where `CI` is set (CI runs as root).
//!
//! Conventions: rates in bits per second as `tc` takes them, times in seconds.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc;
use std::thread;
use std::time::{Duration, Instant};

use canopy_e2e::{client, run_ok, scratch, server};
use serde_json::Value;

/// Set in the copy of the test binary that runs inside the network namespace.
const INNER_ENV: &str = "CANOPY_SHAPED_INNER";
/// The binaries, found by the outer run (the inner one has no network to run cargo with).
const CLIENT_ENV: &str = "CANOPY_SHAPED_CLIENT";
const SERVER_ENV: &str = "CANOPY_SHAPED_SERVER";
/// Largest disagreement allowed between the model and the shaped run, relative to the run.
const TOLERANCE: f64 = 0.15;
/// Connections: the model's (a browser's per host) and the client's `--max-in-flight`.
const CONNECTIONS: &str = "6";

/// A link: what the virtual clock models and the namespace shapes.
#[derive(Debug, Clone, Copy)]
struct Link {
    name: &'static str,
    down_mbit: f64,
    up_mbit: f64,
    rtt_ms: f64,
}

impl Link {
    /// `--link MBIT,RTT_MS,UP_MBIT`: the same numbers the namespace is shaped with.
    fn spec(&self) -> String {
        format!("{},{},{}", self.down_mbit, self.rtt_ms, self.up_mbit)
    }
}

/// The presets of `canopy fly --help` this file shapes (their numbers as `link.rs` states them).
const LINKS: &[Link] = &[
    Link {
        name: "slow4g",
        down_mbit: 1.6,
        up_mbit: 0.75,
        rtt_ms: 150.0,
    },
    Link {
        name: "fast4g",
        down_mbit: 8.1,
        up_mbit: 1.35,
        rtt_ms: 165.0,
    },
    Link {
        name: "dash5",
        down_mbit: 5.0,
        up_mbit: 5.0,
        rtt_ms: 38.0,
    },
];

fn link(name: &str) -> Link {
    *LINKS
        .iter()
        .find(|l| l.name == name)
        .unwrap_or_else(|| panic!("unknown link {name:?}"))
}

/// A TCP forwarder on 127.0.0.1 that holds every chunk it reads for `one_way` before writing it
/// on, in each direction, and a connection's first request one round trip more (the handshake).
/// Chunks keep their order. Threads: one accepting, two per direction per connection; they end
/// when their sockets close. Dropping it stops accepting.
struct DelayLine {
    addr: SocketAddr,
    stop: Arc<AtomicBool>,
}

impl DelayLine {
    fn start(upstream: SocketAddr, rtt: Duration) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").expect("bind the delay line");
        let addr = listener.local_addr().expect("address");
        listener.set_nonblocking(true).expect("non-blocking listener");
        let stop = Arc::new(AtomicBool::new(false));
        let flag = Arc::clone(&stop);
        thread::spawn(move || {
            while !flag.load(Ordering::Relaxed) {
                match listener.accept() {
                    Ok((conn, _)) => {
                        thread::spawn(move || Self::connection(conn, upstream, rtt));
                    }
                    // Polled so that dropping the line stops it; 1 ms is far under any RTT here.
                    Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                        thread::sleep(Duration::from_millis(1));
                    }
                    Err(_) => break,
                }
            }
        });
        Self { addr, stop }
    }

    fn connection(client: TcpStream, upstream: SocketAddr, rtt: Duration) {
        let Ok(server) = TcpStream::connect(upstream) else {
            return;
        };
        let one_way = rtt / 2;
        for s in [&client, &server] {
            let _ = s.set_nonblocking(false);
            let _ = s.set_nodelay(true);
        }
        let (Ok(c2), Ok(s2)) = (client.try_clone(), server.try_clone()) else {
            return;
        };
        Self::pump(client, server, one_way, rtt);
        Self::pump(s2, c2, one_way, Duration::ZERO);
    }

    /// Moves bytes `from` → `to`, each chunk `delay` after it was read (the first `first_extra`
    /// more); at the end of `from`, shuts `to` for writing after the same delay.
    fn pump(mut from: TcpStream, mut to: TcpStream, delay: Duration, first_extra: Duration) {
        let (tx, rx) = mpsc::channel::<(Instant, Option<Vec<u8>>)>();
        thread::spawn(move || {
            let mut buf = vec![0u8; 64 * 1024];
            let mut extra = first_extra;
            loop {
                let n = from.read(&mut buf).unwrap_or(0);
                let due = Instant::now() + delay + extra;
                extra = Duration::ZERO;
                let chunk = (n > 0).then(|| buf[..n].to_vec());
                let end = chunk.is_none();
                if tx.send((due, chunk)).is_err() || end {
                    break;
                }
            }
        });
        thread::spawn(move || {
            for (due, chunk) in rx {
                thread::sleep(due.saturating_duration_since(Instant::now()));
                match chunk {
                    Some(b) if to.write_all(&b).is_ok() => {}
                    _ => {
                        let _ = to.shutdown(Shutdown::Write);
                        break;
                    }
                }
            }
        });
    }
}

impl Drop for DelayLine {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

/// Runs a command inside the namespace, panicking with its output when it fails.
fn sh(args: &[&str]) {
    let out = Command::new(args[0]).args(&args[1..]).output().expect("spawn");
    assert!(
        out.status.success(),
        "{args:?} failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
}

/// Brings up the namespace's `lo` at a 1,500-byte MTU, one segment per packet: with `lo`'s
/// segmentation offload TCP hands the qdisc whole flights (a new flow's first 10 segments,
/// 14.5 kB, as one packet), which htb lets through at once and repays later, so every response
/// would start with a burst no link gives (measured: 11.2 kB in 31 ms at 1.6 Mbit/s instead of
/// 60 ms; with one segment per packet, 62 ms).
fn loopback_up() {
    sh(&[
        "ip",
        "link",
        "set",
        "lo",
        "up",
        "mtu",
        "1500",
        "gso_max_segs",
        "1",
        "gso_max_size",
        "1500",
    ]);
}

/// Classes the downlink is split into, by the client's port: flows share the downlink fairly.
const DOWN_FLOW_CLASSES: u16 = 16;

/// Shapes the traffic of the delay line's port `port` on `lo`: from it at the downlink rate,
/// to it at the uplink rate; the rest unshaped. The downlink is shared fairly between the
/// client's connections (one htb class per connection, by bits 1–4 of its port: Linux gives
/// successive connections successive even ports), as TCP flows sharing a bottleneck come to
/// share it once the round trip is in their loop, and as fq_codel, Linux's usual default
/// qdisc, shares it. One FIFO would serve each response whole in turn here, because the delay
/// line's connection to the client has a round trip of microseconds.
fn shape(port: u16, l: Link) {
    let bit = |mbit: f64| format!("{}bit", (mbit * 1e6).round() as u64);
    let (down, up) = (bit(l.down_mbit), bit(l.up_mbit));
    let flow_rate = bit(l.down_mbit / f64::from(DOWN_FLOW_CLASSES));
    let port = port.to_string();
    let tc = |args: &[&str]| sh(&[&["tc"], args].concat());
    // A fresh root each time (the benchmark shapes one namespace for several links).
    let _ = Command::new("tc").args(["qdisc", "del", "dev", "lo", "root"]).output();
    tc(&[
        "qdisc", "add", "dev", "lo", "root", "handle", "1:", "htb", "default", "30",
    ]);
    for (class, rate) in [("1:10", down.as_str()), ("1:20", up.as_str()), ("1:30", "10gbit")] {
        tc(&[
            "class", "add", "dev", "lo", "parent", "1:", "classid", class, "htb", "rate", rate, "ceil", rate,
        ]);
    }
    tc(&[
        "filter", "add", "dev", "lo", "parent", "1:", "protocol", "ip", "prio", "2", "u32", "match", "ip", "dport",
        &port, "0xffff", "flowid", "1:20",
    ]);
    for k in 0..DOWN_FLOW_CLASSES {
        let class = format!("1:{:x}", 0x100 + k);
        // Each flow is guaranteed its share and may borrow up to the whole downlink; borrowing
        // goes round in quanta of one segment.
        tc(&[
            "class", "add", "dev", "lo", "parent", "1:10", "classid", &class, "htb", "rate", &flow_rate, "ceil", &down,
            "quantum", "1514",
        ]);
        let bits = format!("{:#06x}", k << 1);
        tc(&[
            "filter", "add", "dev", "lo", "parent", "1:", "protocol", "ip", "prio", "1", "u32", "match", "ip", "sport",
            &port, "0xffff", "match", "ip", "dport", &bits, "0x001e", "flowid", &class,
        ]);
    }
}

/// A `canopy-server serve` on 127.0.0.1:0, killed on drop.
struct Served {
    child: Child,
    addr: SocketAddr,
}

impl Served {
    fn start(bin: &Path, data: &Path, args: &[String]) -> Self {
        let log = std::fs::File::create(data.with_extension("log")).expect("server log");
        let mut child = Command::new(bin)
            .arg("serve")
            .arg("--data")
            .arg(data)
            .args(["--addr", "127.0.0.1:0"])
            .args(args)
            .stdout(Stdio::piped())
            .stderr(log)
            .spawn()
            .expect("spawn canopy-server");
        let stdout = child.stdout.take().expect("stdout");
        let (tx, rx) = mpsc::channel();
        thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if let Some(a) = line.strip_prefix("canopy-server listening on http://") {
                    let _ = tx.send(a.trim().to_string());
                }
            }
        });
        let addr = rx.recv_timeout(Duration::from_mins(2)).unwrap_or_else(|_| {
            panic!(
                "canopy-server did not start (log {})",
                data.with_extension("log").display()
            )
        });
        Self {
            child,
            addr: addr.parse().expect("address"),
        }
    }
}

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// `canopy fly URL ARGS --json`: the whole document.
fn fly(bin: &Path, url: &str, args: &[&str]) -> Value {
    let out = run_ok(Command::new(bin).arg("fly").arg(url).args(args).arg("--json"));
    serde_json::from_slice(&out.stdout).expect("fly --json prints JSON")
}

/// The model's run and the shaped run of one link, each `fly --json`'s document.
struct Pair {
    model: Value,
    shaped: Value,
}

/// Inside the namespace: serves `data`, flies on the virtual clock with the link's model, then
/// on the wall clock through the shaped path. `fly_args` are given to both runs.
fn model_and_shaped(data: &Path, server_args: &[String], l: Link, fly_args: &[&str]) -> Pair {
    let bin = |k: &str| PathBuf::from(std::env::var_os(k).unwrap_or_else(|| panic!("{k} is not set")));
    let (client_bin, server_bin) = (bin(CLIENT_ENV), bin(SERVER_ENV));
    loopback_up();
    let srv = Served::start(&server_bin, data, server_args);
    let spec = l.spec();
    let common = [fly_args, &["--max-in-flight", CONNECTIONS]].concat();
    // The model first: it also warms the server's page cache for the shaped run.
    let url = format!("http://{}/api/scenes/demo", srv.addr);
    let model = fly(&client_bin, &url, &[&common[..], &["--link", &spec]].concat());
    let line = DelayLine::start(srv.addr, Duration::from_secs_f64(l.rtt_ms / 1e3));
    shape(line.addr.port(), l);
    let url = format!("http://{}/api/scenes/demo", line.addr);
    let shaped = fly(&client_bin, &url, &[&common[..], &["--wall-clock"]].concat());
    Pair { model, shaped }
}

/// Whether this machine can shape a namespace's loopback; `false` (with a message) skips.
fn shaping_available() -> bool {
    let probe = Command::new("unshare")
        .args(["-n", "sh", "-c"])
        .arg("ip link set lo up mtu 1500 gso_max_segs 1 && tc qdisc add dev lo root handle 1: htb default 30 && tc filter add dev lo parent 1: protocol ip prio 1 u32 match ip sport 1 0xffff flowid 1:10")
        .output();
    let why = match probe {
        Ok(o) if o.status.success() => return true,
        Ok(o) => String::from_utf8_lossy(&o.stderr).trim().to_string(),
        Err(e) => format!("cannot run unshare: {e}"),
    };
    assert!(
        std::env::var_os("CI").is_none(),
        "a network namespace with htb shaping is not available and CI is set (CI runs as root): {why}"
    );
    eprintln!("skipping: a network namespace with htb shaping needs root, unshare, ip and tc ({why})");
    false
}

/// Runs test `name` of this binary again inside a new network namespace, with the binaries'
/// paths (this profile's, or `CANOPY_SHAPED_CLIENT` and `CANOPY_SHAPED_SERVER` where set: the
/// benchmark's release builds); panics with its output when it fails.
fn in_namespace(name: &str) {
    let given = |k: &str, build: fn() -> PathBuf| std::env::var_os(k).map_or_else(build, PathBuf::from);
    let (client_bin, server_bin) = (given(CLIENT_ENV, client), given(SERVER_ENV, server));
    let exe = std::env::current_exe().expect("test binary");
    let mut cmd = Command::new("unshare");
    cmd.arg("-n")
        .arg(exe)
        .args([
            name,
            "--exact",
            "--nocapture",
            "--include-ignored",
            "--test-threads",
            "1",
        ])
        .env(INNER_ENV, "1")
        .env(CLIENT_ENV, client_bin)
        .env(SERVER_ENV, server_bin);
    let out = cmd.output().expect("run the test in a network namespace");
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    eprintln!("{text}");
    assert!(out.status.success(), "the run in the namespace failed");
    // libtest runs nothing, successfully, when the name matches no test.
    assert!(text.contains("1 passed"), "the test did not run in the namespace");
}

fn secs(v: &Value, k: &str) -> f64 {
    v["summary"][k]
        .as_f64()
        .unwrap_or_else(|| panic!("{k} was not reached: {}", v["summary"]))
}

/// The model's figure, the shaped run's, and the model's error relative to the shaped run.
fn compare(p: &Pair, k: &str) -> (f64, f64, f64) {
    let (m, s) = (secs(&p.model, k), secs(&p.shaped, k));
    (m, s, (m - s) / s)
}

/// Synthetic trees (0.45 MB in all), camera held: settled in about 2 s on fast4g, 5 s on
/// slow4g.
const SMALL_DEMO: &[&str] = &["--demo-synthetic", "2", "--demo-trees", "400"];

/// The figures compared, each the model's against the shaped run's.
const FIGURES: [&str; 2] = ["first_complete_s", "settled_s"];

/// Shaped runs per link at most: a wall-clock run that the machine's load held up is run again.
const ATTEMPTS: u32 = 2;

/// Most the model's bytes may differ from the shaped run's, relative to the shaped run's.
const BYTES_TOLERANCE: f64 = 0.15;

/// How far the model is from the shaped run on each figure, as "k: model m s, shaped s s, ±e %",
/// and on bytes; `Err` with the same text when some figure is off by more than [`TOLERANCE`] or
/// the bytes by more than [`BYTES_TOLERANCE`].
///
/// Bytes are part of the verdict rather than a hard assertion: a held camera asks the same
/// requests on both links only while both runs adapt their detail the same way, and the shaped
/// run's rate estimate follows the wall clock. On a loaded machine it once never stepped the
/// detail down where the model did (which stepped to 0.51 and back), and so fetched 387 kB
/// against the model's 450 kB (CI trial, 2026-12-05).
fn agreement(p: &Pair) -> Result<String, String> {
    let mut text = Vec::new();
    let mut ok = true;
    for k in FIGURES {
        let (m, s, err) = compare(p, k);
        ok &= err.abs() <= TOLERANCE;
        text.push(format!("{k}: model {m:.2} s, shaped {s:.2} s, {:+.1} %", err * 100.0));
    }
    let bytes = |v: &Value| v["summary"]["bytes"].as_f64().expect("bytes");
    let (mb, sb) = (bytes(&p.model), bytes(&p.shaped));
    ok &= (mb - sb).abs() <= BYTES_TOLERANCE * sb;
    text.push(format!("bytes: model {mb} B, shaped {sb} B"));
    let text = text.join("; ");
    if ok { Ok(text) } else { Err(text) }
}

#[test]
fn the_link_model_agrees_with_a_kernel_shaped_link() {
    const NAME: &str = "the_link_model_agrees_with_a_kernel_shaped_link";
    if std::env::var_os(INNER_ENV).is_none() {
        if shaping_available() {
            in_namespace(NAME);
        }
        return;
    }
    let dir = scratch("client-shaped");
    let args: Vec<String> = SMALL_DEMO.iter().map(ToString::to_string).collect();
    // The crown-hull ladder, under which the comparison was measured (log 2026-12-04). Under the
    // default ladder the two fast4g runs once moved 467 kB against 401 kB (on a loaded machine):
    // not looked into yet.
    let fly_args = [
        "--speed",
        "0",
        "--frames",
        "900",
        "--until-settled",
        "--ladder",
        "geometry:150,hull0:60,hull1:30,hemioct:0",
    ];
    for name in ["slow4g", "fast4g"] {
        let l = link(name);
        let mut tries = Vec::new();
        let mut agreed = false;
        for attempt in 1..=ATTEMPTS {
            let p = model_and_shaped(&dir.join("data"), &args, l, &fly_args);
            // Both documents in the scratch folder, for a look after a failure.
            for (v, what) in [(&p.model, "model"), (&p.shaped, "shaped")] {
                let path = dir.join(format!("fly-{}-{what}-{attempt}.json", l.name));
                std::fs::write(&path, v.to_string()).expect("write fly's output");
            }
            // The shaped run did wait for its link: the manifest alone takes a handshake and a
            // round trip. That it moved what the model did (the same requests, give or take the
            // frames at which they were sent) is part of the verdict.
            let manifest = secs(&p.shaped, "manifest_s");
            assert!(manifest >= 2.0 * l.rtt_ms / 1e3, "{name}: manifest in {manifest} s");
            let verdict = agreement(&p);
            eprintln!("{name}, attempt {attempt}: {verdict:?}");
            agreed = verdict.is_ok();
            tries.push(verdict.unwrap_or_else(|e| e));
            if agreed {
                break;
            }
        }
        assert!(
            agreed,
            "{name}: the model is more than {} % from every shaped run: {tries:#?}",
            TOLERANCE * 100.0
        );
    }
}

/// The benchmark (`benchmarks/shaped.sh`): for each link of `CANOPY_SHAPED_LINKS` (names from
/// [`LINKS`], comma-separated), the model's and the shaped run's `fly --json` on the scene
/// served from `CANOPY_SHAPED_DATA` (server arguments in `CANOPY_SHAPED_SERVER_ARGS`,
/// space-separated; fly's in `CANOPY_SHAPED_FLY_ARGS`), written to `CANOPY_SHAPED_OUT` as
/// `fly-LINK-model.json` and `fly-LINK-shaped.json`, `CANOPY_SHAPED_ROUNDS` times (model,
/// shaped, model, shaped…; rounds after the first get `-2`, `-3`… before `.json`).
#[test]
#[ignore = "a benchmark of a minute or more: benchmarks/shaped.sh"]
fn shaped_benchmark() {
    const NAME: &str = "shaped_benchmark";
    let var = |k: &str| std::env::var(k).unwrap_or_else(|_| panic!("{k} is not set (benchmarks/shaped.sh sets it)"));
    if std::env::var_os(INNER_ENV).is_none() {
        assert!(shaping_available(), "the benchmark needs a shaped namespace");
        in_namespace(NAME);
        return;
    }
    let out = PathBuf::from(var("CANOPY_SHAPED_OUT"));
    let data = PathBuf::from(var("CANOPY_SHAPED_DATA"));
    let words = |k: &str| -> Vec<String> {
        std::env::var(k)
            .unwrap_or_default()
            .split_whitespace()
            .map(ToString::to_string)
            .collect()
    };
    let server_args = words("CANOPY_SHAPED_SERVER_ARGS");
    let fly_args = words("CANOPY_SHAPED_FLY_ARGS");
    let fly_args: Vec<&str> = fly_args.iter().map(String::as_str).collect();
    let rounds: u32 = std::env::var("CANOPY_SHAPED_ROUNDS")
        .ok()
        .map_or(1, |r| r.parse().expect("CANOPY_SHAPED_ROUNDS is a number"));
    std::fs::create_dir_all(&out).expect("output folder");
    for name in var("CANOPY_SHAPED_LINKS").split(',') {
        let l = link(name.trim());
        for round in 1..=rounds {
            let p = model_and_shaped(&data, &server_args, l, &fly_args);
            let suffix = if round == 1 { String::new() } else { format!("-{round}") };
            for (v, what) in [(&p.model, "model"), (&p.shaped, "shaped")] {
                let path = out.join(format!("fly-{}-{what}{suffix}.json", l.name));
                std::fs::write(&path, serde_json::to_string_pretty(v).expect("JSON")).expect("write");
            }
            for k in ["first_complete_s", "settled_s"] {
                let (m, s, err) = compare(&p, k);
                eprintln!(
                    "{} round {round}: {k} model {m:.2} s, shaped {s:.2} s, error {:+.1} %",
                    l.name,
                    err * 100.0
                );
            }
        }
    }
}
