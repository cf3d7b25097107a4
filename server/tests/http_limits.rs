//! Deadlines, the connection bound and body limits, in process (so they can be set short): the
//! router for bodies too large (413) or too slow (408), and `serve` on a loopback port for
//! slowloris heads, idle keep-alive, clients that never read, and shedding at the bound.

use std::path::PathBuf;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use axum::body::{Body, Bytes};
use axum::http::{Request, StatusCode};
use canopy_server::demo::{bake_and_store, synthetic_model};
use canopy_server::http::{AppState, HttpConfig, MAX_BODY, router, serve};
use canopy_server::store::{AssetStore, SqliteStore};
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpSocket, TcpStream};
use tower::ServiceExt;

struct Fixture {
    addr: std::net::SocketAddr,
    state: AppState,
    dir: PathBuf,
    /// A tree's URL under `/assets/`.
    tree: String,
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn state(name: &str, config: HttpConfig) -> (AppState, canopy_server::http::Shutdown, PathBuf, String) {
    let dir = std::env::temp_dir().join(format!("canopy-http-limits-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let assets = Arc::new(AssetStore::open(&dir).expect("asset store"));
    let scenes = Arc::new(SqliteStore::in_memory().expect("db"));
    let (state, stop) = AppState::new(assets, scenes, config);
    let model = bake_and_store(&state, &synthetic_model(0)).expect("bake");
    let file = std::fs::read_dir(dir.join("trees"))
        .expect("trees")
        .filter_map(Result::ok)
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .find(|f| f.starts_with(&model))
        .expect("the baked tree");
    (state, stop, dir, format!("/assets/trees/{file}"))
}

/// `serve` on a free loopback port with `config`, running until the test ends.
async fn fixture(name: &str, config: HttpConfig) -> Fixture {
    let (state, stop, dir, tree) = state(name, config);
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let addr = listener.local_addr().expect("addr");
    tokio::spawn(serve(listener, state.clone(), stop, std::future::pending()));
    Fixture { addr, state, dir, tree }
}

/// Deadlines short enough for a test.
fn short() -> HttpConfig {
    HttpConfig {
        header_timeout: Duration::from_millis(400),
        idle_timeout: Duration::from_millis(1200),
        body_timeout: Duration::from_millis(400),
        write_timeout: Duration::from_millis(400),
        ..HttpConfig::default()
    }
}

fn metric(state: &AppState, name: &str) -> i64 {
    let text = state.inner.metrics.render();
    text.lines()
        .find_map(|l| l.strip_prefix(name)?.strip_prefix(' ')?.parse().ok())
        .unwrap_or(-1)
}

/// Reads until the server closes the connection (EOF or reset); how long that took, and the bytes.
async fn until_closed(s: &mut TcpStream, within: Duration) -> (Duration, Vec<u8>) {
    let t0 = Instant::now();
    let mut out = Vec::new();
    let mut buf = vec![0u8; 64 << 10];
    loop {
        let Ok(read) = tokio::time::timeout_at((t0 + within).into(), s.read(&mut buf)).await else {
            panic!("the connection was still open after {within:?}")
        };
        match read {
            Ok(0) | Err(_) => return (t0.elapsed(), out),
            Ok(n) => out.extend_from_slice(&buf[..n]),
        }
    }
}

/// One request on a fresh connection (`Connection: close`): status, headers and body as text.
async fn get(addr: std::net::SocketAddr, path: &str) -> (u16, String) {
    let mut s = TcpStream::connect(addr).await.expect("connect");
    let req = format!("GET {path} HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n");
    s.write_all(req.as_bytes()).await.expect("send");
    let (_, raw) = until_closed(&mut s, Duration::from_secs(10)).await;
    let text = String::from_utf8_lossy(&raw).into_owned();
    let status = text.split(' ').nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
    (status, text)
}

/// A request body that never sends anything.
struct Stalled;

impl http_body::Body for Stalled {
    type Data = Bytes;
    type Error = std::io::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        _: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, Self::Error>>> {
        Poll::Pending
    }
}

/// A request body of 64 KiB chunks without end (and without a declared length).
struct Endless;

impl http_body::Body for Endless {
    type Data = Bytes;
    type Error = std::io::Error;

    fn poll_frame(
        self: Pin<&mut Self>,
        _: &mut Context<'_>,
    ) -> Poll<Option<Result<http_body::Frame<Bytes>, Self::Error>>> {
        Poll::Ready(Some(Ok(http_body::Frame::data(Bytes::from(vec![b' '; 64 << 10])))))
    }
}

async fn post(
    app: &axum::Router,
    path: &str,
    len: Option<usize>,
    body: Body,
) -> (StatusCode, axum::http::HeaderMap, Value) {
    let mut req = Request::builder()
        .method("POST")
        .uri(path)
        .header("content-type", "application/json");
    if let Some(n) = len {
        req = req.header("content-length", n);
    }
    let resp = app
        .clone()
        .oneshot(req.body(body).expect("request"))
        .await
        .expect("infallible");
    let (parts, body) = resp.into_parts();
    let bytes = axum::body::to_bytes(body, usize::MAX).await.expect("body");
    let json = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
    (parts.status, parts.headers, json)
}

#[tokio::test]
async fn oversized_bodies_get_the_api_json_error() {
    let (state, _stop, dir, _) = state("413", HttpConfig::default());
    let app = router(state);
    // Declared too large: refused before a byte of it is read.
    let n = MAX_BODY + 1;
    let (status, headers, json) = post(&app, "/api/scenes", Some(n), Body::from(vec![b' '; n])).await;
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
    assert!(
        json["error"].as_str().is_some_and(|e| e.contains("body over")),
        "{json}"
    );
    assert_eq!(
        headers.get("content-type").and_then(|v| v.to_str().ok()),
        Some("application/json")
    );
    assert_eq!(headers.get("connection").and_then(|v| v.to_str().ok()), Some("close"));
    assert_eq!(
        headers.get("access-control-allow-origin").and_then(|v| v.to_str().ok()),
        Some("*")
    );
    // Chunked without end: refused once MAX_BODY bytes have come.
    let (status, _, json) = post(&app, "/api/scenes/x/instances", None, Body::new(Endless)).await;
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE);
    assert!(json["error"].is_string(), "{json}");
    // A body within the limit still reaches the handler (which finds it is not JSON).
    let (status, _, json) = post(&app, "/api/scenes", Some(3), Body::from("{{{")).await;
    assert_eq!(status, StatusCode::BAD_REQUEST);
    assert!(
        json["error"].as_str().is_some_and(|e| e.contains("invalid JSON")),
        "{json}"
    );
    let _ = std::fs::remove_dir_all(dir);
}

#[tokio::test]
async fn a_body_that_stalls_gets_408_after_the_body_timeout() {
    let (state, _stop, dir, _) = state("408", short());
    let app = router(state.clone());
    let t0 = Instant::now();
    let (status, headers, json) = post(&app, "/api/scenes", Some(100), Body::new(Stalled)).await;
    let took = t0.elapsed();
    assert_eq!(status, StatusCode::REQUEST_TIMEOUT);
    assert!(
        json["error"].as_str().is_some_and(|e| e.contains("did not arrive")),
        "{json}"
    );
    assert_eq!(headers.get("connection").and_then(|v| v.to_str().ok()), Some("close"));
    assert!(
        took >= Duration::from_millis(350) && took < Duration::from_secs(3),
        "{took:?}"
    );
    assert_eq!(metric(&state, "canopy_http_timeouts_total{stage=\"body\"}"), 1);
    let _ = std::fs::remove_dir_all(dir);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn slowloris_heads_and_idle_keep_alive_are_closed_on_their_own_deadlines() {
    let f = fixture("deadlines", short()).await;
    // Half a request line, then nothing: closed at the header deadline (400 ms).
    let mut slow = TcpStream::connect(f.addr).await.expect("connect");
    slow.write_all(b"GET /healthz HT").await.expect("send");
    let (took, _) = until_closed(&mut slow, Duration::from_secs(5)).await;
    assert!(
        took >= Duration::from_millis(300) && took < Duration::from_secs(2),
        "slowloris: {took:?}"
    );
    // A connection that never sends: the same deadline, from accept.
    let mut mute = TcpStream::connect(f.addr).await.expect("connect");
    let (took, _) = until_closed(&mut mute, Duration::from_secs(5)).await;
    assert!(
        took >= Duration::from_millis(300) && took < Duration::from_secs(2),
        "mute: {took:?}"
    );
    assert_eq!(metric(&f.state, "canopy_http_timeouts_total{stage=\"header\"}"), 2);

    // Kept alive after a request: the idle deadline (1.2 s), not the header one.
    let mut ka = TcpStream::connect(f.addr).await.expect("connect");
    ka.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")
        .await
        .expect("send");
    let mut head = [0u8; 256];
    let n = ka.read(&mut head).await.expect("response");
    assert!(
        head[..n].starts_with(b"HTTP/1.1 200"),
        "{}",
        String::from_utf8_lossy(&head[..n])
    );
    let (took, rest) = until_closed(&mut ka, Duration::from_secs(5)).await;
    assert!(rest.is_empty());
    assert!(
        took >= Duration::from_secs(1) && took < Duration::from_secs(3),
        "idle: {took:?}"
    );
    assert_eq!(metric(&f.state, "canopy_http_timeouts_total{stage=\"idle\"}"), 1);

    assert_eq!(metric(&f.state, "canopy_http_connections"), 0);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_that_never_reads_is_dropped_after_the_write_timeout() {
    let f = fixture("write", short()).await;
    let sock = TcpSocket::new_v4().expect("socket");
    sock.set_recv_buffer_size(4096).expect("SO_RCVBUF");
    let mut s = sock.connect(f.addr).await.expect("connect");
    // Pipelined requests for a tree, far more than the socket buffers hold (a few MiB).
    let len = std::fs::metadata(f.dir.join(f.tree.trim_start_matches("/assets/")))
        .expect("tree")
        .len() as usize;
    let n = (64 << 20) / len + 1;
    let req = format!("GET {} HTTP/1.1\r\nHost: x\r\n\r\n", f.tree);
    s.write_all(req.repeat(n).as_bytes()).await.expect("send");
    let t0 = Instant::now();
    while metric(&f.state, "canopy_http_timeouts_total{stage=\"write\"}") < 1 {
        assert!(t0.elapsed() < Duration::from_secs(5), "not dropped");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert!(t0.elapsed() >= Duration::from_millis(350), "{:?}", t0.elapsed());
    let (_, got) = until_closed(&mut s, Duration::from_secs(5)).await;
    assert!(got.len() < n * len, "all {} bytes came", got.len());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn at_the_bound_idle_connections_make_room_and_busy_ones_get_503() {
    let f = fixture(
        "bound",
        HttpConfig {
            max_connections: 8,
            header_timeout: Duration::from_secs(30),
            body_timeout: Duration::from_secs(30),
            ..HttpConfig::default()
        },
    )
    .await;
    // Three times the bound in sockets that never send: the oldest are closed for the new.
    let mut idle = Vec::new();
    for _ in 0..24 {
        idle.push(TcpStream::connect(f.addr).await.expect("connect"));
    }
    for _ in 0..10 {
        let t0 = Instant::now();
        assert_eq!(get(f.addr, "/healthz").await.0, 200);
        assert!(t0.elapsed() < Duration::from_secs(1), "{:?}", t0.elapsed());
        let (status, _) = get(f.addr, &f.tree).await;
        assert_eq!(status, 200);
    }
    // The bound, plus at most the evicted connection still closing and the last request's.
    assert!(metric(&f.state, "canopy_http_connections") <= 8 + 2);
    assert!(metric(&f.state, "canopy_http_connections_shed_total{action=\"evicted\"}") >= 16);
    assert_eq!(
        metric(&f.state, "canopy_http_connections_shed_total{action=\"refused\"}"),
        0
    );
    drop(idle);

    // Every slot busy with a body that trickles: nothing to evict, so 503 with Retry-After.
    let mut busy = Vec::new();
    for _ in 0..8 {
        let mut s = TcpStream::connect(f.addr).await.expect("connect");
        s.write_all(
            b"POST /api/scenes HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\nContent-Length: 100\r\n\r\n{",
        )
        .await
        .expect("send");
        busy.push(s);
    }
    // Until the server has read all 8 heads: before that a connection whose head waits unread
    // is as evictable as an idle one, and the probes below would close it (seen on a loaded
    // machine).
    let t0 = Instant::now();
    while metric(&f.state, "canopy_http_requests_in_flight") < 8 {
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "the 8 heads were not read in 10 s"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // Until the closed idle sockets have left.
    let t0 = Instant::now();
    let (status, text) = loop {
        let (status, text) = get(f.addr, "/healthz").await;
        if status == 503 || t0.elapsed() > Duration::from_secs(5) {
            break (status, text);
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    };
    assert_eq!(status, 503, "{text}");
    assert!(text.contains("Retry-After: 1"), "{text}");
    let body = text.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    assert!(
        serde_json::from_str::<Value>(body).is_ok_and(|v| v["error"].is_string()),
        "{text}"
    );
    drop(busy);
    let t0 = Instant::now();
    while get(f.addr, "/healthz").await.0 != 200 {
        assert!(t0.elapsed() < Duration::from_secs(5), "no recovery");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // The dropped bodies' requests ended with their connections: the gauge does not leak.
    while metric(&f.state, "canopy_http_requests_in_flight") != 0 {
        assert!(
            t0.elapsed() < Duration::from_secs(10),
            "requests still counted in flight"
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_response_still_being_written_is_not_cut_by_the_idle_deadline_or_the_bound() {
    let f = fixture(
        "flush",
        HttpConfig {
            idle_timeout: Duration::from_millis(300),
            write_timeout: Duration::from_secs(10),
            max_connections: 2,
            ..HttpConfig::default()
        },
    )
    .await;
    // Held in memory, so the whole body is one frame: hyper has it (and the request counts as
    // done) long before a slow client has taken it.
    let big: Vec<u8> = (0..16u32 << 20).map(|k| (k % 251) as u8).collect();
    let asset = f.state.inner.assets.put("trees", "big", "bin", &big).expect("put");
    let sock = TcpSocket::new_v4().expect("socket");
    sock.set_recv_buffer_size(4096).expect("SO_RCVBUF");
    let mut s = sock.connect(f.addr).await.expect("connect");
    let req = format!("GET /assets/{} HTTP/1.1\r\nHost: x\r\n\r\n", asset.rel);
    s.write_all(req.as_bytes()).await.expect("send");
    // Past the idle deadline without reading, while new connections push at the bound.
    tokio::time::sleep(Duration::from_millis(800)).await;
    for _ in 0..4 {
        let _ = get(f.addr, "/healthz").await;
    }
    let mut got = Vec::new();
    let mut buf = vec![0u8; 64 << 10];
    let t0 = Instant::now();
    let body_at = loop {
        let n = tokio::time::timeout(Duration::from_secs(10), s.read(&mut buf))
            .await
            .expect("the response keeps coming")
            .expect("read");
        assert!(n > 0, "closed after {} bytes", got.len());
        got.extend_from_slice(&buf[..n]);
        if let Some(at) = got.windows(4).position(|w| w == b"\r\n\r\n")
            && got.len() >= at + 4 + big.len()
        {
            break at + 4;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "too slow");
    };
    assert!(got[body_at..] == big[..], "the body came whole");
    // Then the connection is idle, and the idle deadline closes it.
    let (took, rest) = until_closed(&mut s, Duration::from_secs(5)).await;
    assert!(rest.is_empty());
    assert!(took < Duration::from_secs(2), "{took:?}");
    assert_eq!(metric(&f.state, "canopy_http_timeouts_total{stage=\"write\"}"), 0);
}
