//! Server hardening over the wire (issue 23): the real `canopy-server serve` on a loopback port,
//! with short deadlines set by flags. A slowloris head and an idle keep-alive connection are
//! closed on time, `/healthz` and asset ranges answer past the connection bound, a client that
//! never reads is dropped, an oversized body gets the API's JSON 413, a JSON body sent as a form
//! gets 415, and readers of a large instance list that never read hold little memory.

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::time::{Duration, Instant};

use canopy_e2e::net::{Server, get_range, http};
use canopy_e2e::scratch;

const SMALL_DEMO: [&str; 4] = ["--demo-synthetic", "2", "--demo-trees", "400"];

fn start(name: &str, flags: &[&str]) -> Server {
    let dir = scratch(name);
    let args: Vec<&str> = SMALL_DEMO.iter().chain(flags).copied().collect();
    Server::start(&dir.join("data"), &args)
}

/// The value of one metric line (`name value`), -1 when absent.
fn metric(addr: SocketAddr, name: &str) -> i64 {
    let text = String::from_utf8(http(addr, "GET", "/metrics", &[], None).body).expect("utf8");
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or(-1)
}

/// Reads until the server closes the connection (EOF or reset): how long that took, the bytes.
/// Panics if it is still open after `within`.
fn until_closed(s: &mut TcpStream, within: Duration) -> (Duration, Vec<u8>) {
    let t0 = Instant::now();
    s.set_read_timeout(Some(within)).expect("timeout");
    let mut out = Vec::new();
    let mut buf = vec![0u8; 64 << 10];
    loop {
        match s.read(&mut buf) {
            Ok(0) => return (t0.elapsed(), out),
            Ok(n) => out.extend_from_slice(&buf[..n]),
            Err(e) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {
                panic!("the connection was still open after {within:?}")
            }
            Err(_) => return (t0.elapsed(), out),
        }
        assert!(t0.elapsed() < within, "the connection was still open after {within:?}");
    }
}

/// The demo's largest asset: its URL and length.
fn largest_asset(addr: SocketAddr) -> (String, usize) {
    let m = http(addr, "GET", "/api/scenes/demo/manifest", &[], None).json();
    let mut urls: Vec<String> = m["models"]
        .as_array()
        .expect("models")
        .iter()
        .map(|m| m["url"].as_str().expect("url").to_string())
        .collect();
    urls.push(m["pack"]["url"].as_str().expect("pack").to_string());
    urls.into_iter()
        .map(|u| {
            let len = http(addr, "HEAD", &u, &[], None)
                .header("content-length")
                .and_then(|v| v.parse().ok())
                .expect("length");
            (u, len)
        })
        .max_by_key(|(_, len)| *len)
        .expect("an asset")
}

#[test]
fn slowloris_heads_and_idle_keep_alive_are_closed_on_time() {
    let s = start(
        "limits-deadlines",
        &["--header-timeout-s", "1", "--idle-timeout-s", "2"],
    );
    // Half a request line, then nothing.
    let mut slow = TcpStream::connect(s.addr).expect("connect");
    slow.write_all(b"GET /healthz HT").expect("send");
    let (took, _) = until_closed(&mut slow, Duration::from_secs(6));
    assert!(
        took >= Duration::from_millis(800) && took < Duration::from_secs(3),
        "slowloris closed after {took:?}"
    );
    // One request kept alive, then nothing: closed at the idle deadline, not the header one.
    let mut ka = TcpStream::connect(s.addr).expect("connect");
    ka.write_all(format!("GET /healthz HTTP/1.1\r\nHost: {}\r\n\r\n", s.addr).as_bytes())
        .expect("send");
    ka.set_read_timeout(Some(Duration::from_secs(5))).expect("timeout");
    let mut head = [0u8; 512];
    let n = ka.read(&mut head).expect("response");
    assert!(head[..n].starts_with(b"HTTP/1.1 200"));
    let (took, rest) = until_closed(&mut ka, Duration::from_secs(8));
    assert!(rest.is_empty());
    assert!(
        took >= Duration::from_millis(1800) && took < Duration::from_secs(5),
        "idle keep-alive closed after {took:?}"
    );
    assert_eq!(metric(s.addr, "canopy_http_timeouts_total{stage=\"header\"}"), 1);
    assert_eq!(metric(s.addr, "canopy_http_timeouts_total{stage=\"idle\"}"), 1);
}

#[test]
fn healthz_and_asset_ranges_answer_past_the_connection_bound() {
    // Deadlines long enough that only the bound makes room during the test.
    let s = start(
        "limits-bound",
        &[
            "--max-connections",
            "64",
            "--header-timeout-s",
            "60",
            "--idle-timeout-s",
            "60",
        ],
    );
    let (asset, _) = largest_asset(s.addr);
    // Four times the bound in sockets that never send.
    let idle: Vec<TcpStream> = (0..256).map(|_| TcpStream::connect(s.addr).expect("connect")).collect();
    let mut took = Vec::new();
    for k in 0..50 {
        let t0 = Instant::now();
        let r = http(s.addr, "GET", "/healthz", &[], None);
        took.push(t0.elapsed());
        assert_eq!(r.status, 200, "try {k}");
        if k % 10 == 0 {
            let r = get_range(s.addr, &asset, "bytes=0-63");
            assert_eq!(r.status, 206);
            assert_eq!(r.body.len(), 64);
        }
    }
    took.sort();
    let p99 = took[(took.len() * 99).div_ceil(100) - 1];
    eprintln!(
        "/healthz past the bound (256 idle sockets, 64 max): p50 {:?}, p99 {p99:?}",
        took[took.len() / 2]
    );
    assert!(p99 < Duration::from_millis(50), "p99 {p99:?}");
    assert!(metric(s.addr, "canopy_http_connections_shed_total{action=\"evicted\"}") >= 192);
    assert_eq!(
        metric(s.addr, "canopy_http_connections_shed_total{action=\"refused\"}"),
        0
    );
    assert!(metric(s.addr, "canopy_http_connections") <= 64 + 2);
    drop(idle);
}

#[test]
fn a_client_that_never_reads_is_dropped_after_the_write_timeout() {
    let s = start("limits-write", &["--write-timeout-s", "1"]);
    let (asset, len) = largest_asset(s.addr);
    // Pipelined requests for far more than the socket buffers hold (a few MiB on loopback),
    // written from a thread (the server stops reading them once it stalls), never read.
    let n = (64 << 20) / len + 1;
    let c = TcpStream::connect(s.addr).expect("connect");
    let mut w = c.try_clone().expect("clone");
    let reqs = format!("GET {asset} HTTP/1.1\r\nHost: {}\r\n\r\n", s.addr).repeat(n);
    let writer = std::thread::spawn(move || {
        let _ = w.write_all(reqs.as_bytes());
        w
    });
    let t0 = Instant::now();
    while metric(s.addr, "canopy_http_timeouts_total{stage=\"write\"}") < 1 {
        assert!(t0.elapsed() < Duration::from_secs(8), "not dropped");
        std::thread::sleep(Duration::from_millis(50));
    }
    assert!(t0.elapsed() >= Duration::from_millis(800), "{:?}", t0.elapsed());
    let mut c = c;
    let (_, got) = until_closed(&mut c, Duration::from_secs(10));
    assert!(got.len() < n * len, "all {} bytes came", got.len());
    drop(writer.join());
    assert_eq!(http(s.addr, "GET", "/healthz", &[], None).status, 200);
}

#[test]
fn an_oversized_body_gets_the_api_json_413() {
    let s = start("limits-413", &[]);
    let mut c = TcpStream::connect(s.addr).expect("connect");
    let head = format!(
        "POST /api/scenes HTTP/1.1\r\nHost: {}\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n{{",
        s.addr,
        5 << 20
    );
    c.write_all(head.as_bytes()).expect("send");
    let (_, raw) = until_closed(&mut c, Duration::from_secs(10));
    let text = String::from_utf8_lossy(&raw);
    assert!(text.starts_with("HTTP/1.1 413 "), "{text}");
    let lower = text.to_ascii_lowercase();
    assert!(lower.contains("content-type: application/json"), "{text}");
    let body = text.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    let v: serde_json::Value = serde_json::from_str(body).expect("a JSON body");
    assert!(v["error"].as_str().is_some_and(|e| e.contains("body over")), "{v}");
    // The server carries on.
    assert_eq!(http(s.addr, "GET", "/healthz", &[], None).status, 200);
}

/// Sends one raw request (`Connection: close`) and returns the status and the body.
fn raw(addr: SocketAddr, head: &str, body: &[u8]) -> (u16, Vec<u8>) {
    let mut c = TcpStream::connect(addr).expect("connect");
    let req = format!(
        "{head}\r\nHost: {addr}\r\nConnection: close\r\nContent-Length: {}\r\n\r\n",
        body.len()
    );
    c.write_all(req.as_bytes()).expect("send");
    c.write_all(body).expect("send body");
    let (_, got) = until_closed(&mut c, Duration::from_secs(10));
    let text = String::from_utf8_lossy(&got);
    let status = text.get(9..12).and_then(|s| s.parse().ok()).unwrap_or(0);
    let body = got
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .map_or(Vec::new(), |e| got[e + 4..].to_vec());
    (status, body)
}

#[test]
fn a_json_body_sent_as_a_form_gets_415() {
    let s = start("limits-415", &["--open-creation"]);
    let scene = serde_json::json!({"id": "form", "name": "Form", "bounds": {"min": [0, 0], "max": [10, 10]}});
    let body = scene.to_string();
    for ct in [
        "text/plain",
        "application/x-www-form-urlencoded",
        "multipart/form-data; boundary=b",
    ] {
        let (status, got) = raw(
            s.addr,
            &format!("POST /api/scenes HTTP/1.1\r\nContent-Type: {ct}"),
            body.as_bytes(),
        );
        assert_eq!(status, 415, "{ct}: {}", String::from_utf8_lossy(&got));
        let v: serde_json::Value = serde_json::from_slice(&got).expect("a JSON error");
        assert!(
            v["error"].as_str().is_some_and(|e| e.contains("application/json")),
            "{v}"
        );
    }
    assert_eq!(http(s.addr, "GET", "/api/scenes/form", &[], None).status, 404);
    let (status, _) = raw(
        s.addr,
        "POST /api/scenes HTTP/1.1\r\nContent-Type: application/json; charset=utf-8",
        body.as_bytes(),
    );
    assert_eq!(status, 201);
}

/// Resident memory of a process, in MiB.
fn rss_mib(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).expect("/proc status");
    status
        .lines()
        .find_map(|l| {
            l.strip_prefix("VmRSS:")?
                .trim()
                .strip_suffix("kB")?
                .trim()
                .parse::<f64>()
                .ok()
        })
        .expect("VmRSS")
        / 1024.0
}

#[test]
fn readers_of_a_large_instance_list_that_never_read_hold_little_memory() {
    const INSTANCES: usize = 100_000;
    const READERS: usize = 32;
    let s = start("limits-instances", &["--write-timeout-s", "3", "--open-creation"]);
    let m = http(s.addr, "GET", "/api/scenes/demo/manifest", &[], None).json();
    let models: Vec<String> = m["models"]
        .as_array()
        .expect("models")
        .iter()
        .map(|m| m["name"].as_str().expect("name").to_string())
        .collect();
    // Built through the API as anyone can: a creation, then batches of 10,000 adds.
    let adds = |from: usize| -> Vec<serde_json::Value> {
        (from..from + 10_000)
            .map(|k| {
                let t = k as f32;
                serde_json::json!({
                    "model": models[k % models.len()],
                    "position": [(t * 0.618).fract() * 1900.0 - 950.0, 0.0, (t * 0.414).fract() * 1900.0 - 950.0],
                    "rotation": t * 0.1,
                })
            })
            .collect()
    };
    let create = serde_json::json!({
        "id": "big", "name": "Big", "bounds": {"min": [-1000, -1000], "max": [1000, 1000]}, "instances": adds(0)
    });
    let r = http(s.addr, "POST", "/api/scenes", &[], Some(create.to_string().as_bytes()));
    assert_eq!(r.status, 201);
    let auth = format!("Bearer {}", r.json()["write_token"].as_str().expect("token"));
    for k in 1..INSTANCES / 10_000 {
        let batch = serde_json::json!({ "add": adds(k * 10_000) }).to_string();
        let r = http(
            s.addr,
            "POST",
            "/api/scenes/big/instances",
            &[("Authorization", &auth)],
            Some(batch.as_bytes()),
        );
        assert_eq!(r.status, 200);
    }
    let whole = http(s.addr, "GET", "/api/scenes/big/instances", &[], None);
    let body_mib = whole.body.len() as f64 / f64::from(1 << 20);
    let v = whole.json();
    assert_eq!(v["instances"].as_array().map(Vec::len), Some(INSTANCES));
    let before = rss_mib(s.pid());
    let readers: Vec<TcpStream> = (0..READERS)
        .map(|_| {
            let mut c = TcpStream::connect(s.addr).expect("connect");
            c.write_all(format!("GET /api/scenes/big/instances HTTP/1.1\r\nHost: {}\r\n\r\n", s.addr).as_bytes())
                .expect("send");
            c
        })
        .collect();
    std::thread::sleep(Duration::from_millis(1500));
    let held = rss_mib(s.pid());
    let per = (held - before) / READERS as f64;
    eprintln!(
        "{READERS} readers of a {body_mib:.1} MiB list that never read: RSS {before:.1} -> {held:.1} MiB, {per:.2} MiB each"
    );
    // Built whole per request, each would hold the body and more (the bound here is a tenth).
    assert!(held - before < body_mib * READERS as f64 / 10.0, "{per:.2} MiB each");
    // Then the write deadline drops them.
    let t0 = Instant::now();
    while metric(s.addr, "canopy_http_timeouts_total{stage=\"write\"}") < READERS as i64 {
        assert!(t0.elapsed() < Duration::from_secs(20), "the readers were not dropped");
        std::thread::sleep(Duration::from_millis(100));
    }
    drop(readers);
    assert_eq!(http(s.addr, "GET", "/healthz", &[], None).status, 200);
}
