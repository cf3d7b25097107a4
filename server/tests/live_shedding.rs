//! Presence limits over a real loopback connection, in-process: every bad frame gets a 1008 close
//! with its reason (over 4 KiB, invalid UTF-8, unmasked, binary, a fragmented message over the
//! limit), pings and pongs count towards the per-viewer frame limit, and poses coalesce (latest
//! wins) between two publications while the other viewers carry on.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use canopy_server::demo::{bake_and_store, synthetic_model};
use canopy_server::http::live::{MAX_CLIENT_MSG, MAX_CLIENT_MSGS_PER_S};
use canopy_server::http::{AppState, HttpConfig, serve};
use canopy_server::store::{AssetStore, SqliteStore};
use serde_json::{Value, json};
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

struct Fixture {
    addr: std::net::SocketAddr,
    dir: PathBuf,
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// A server with one public scene, `s`.
async fn fixture(name: &str, config: HttpConfig) -> Fixture {
    let dir = std::env::temp_dir().join(format!("canopy-live-shedding-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let assets = Arc::new(AssetStore::open(&dir).expect("asset store"));
    let scenes = Arc::new(SqliteStore::in_memory().expect("db"));
    let (state, stop) = AppState::new(assets, scenes, config);
    let model = bake_and_store(&state, &synthetic_model(0)).expect("bake");
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.expect("bind");
    let addr = listener.local_addr().expect("addr");
    tokio::spawn(serve(listener, state, stop, std::future::pending()));
    let body = json!({
        "name": "s", "id": "s", "public": true,
        "bounds": {"min": [-10.0, -10.0], "max": [10.0, 10.0]},
        "instances": [{"model": model, "position": [0.0, 0.0, 0.0]}],
    })
    .to_string();
    let mut s = TcpStream::connect(addr).await.expect("connect");
    let req = format!(
        "POST /api/scenes HTTP/1.1\r\nHost: x\r\nConnection: close\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\n\r\n{body}",
        body.len()
    );
    s.write_all(req.as_bytes()).await.expect("send");
    let mut out = Vec::new();
    s.read_to_end(&mut out).await.expect("read");
    assert!(out.starts_with(b"HTTP/1.1 201"), "{}", String::from_utf8_lossy(&out));
    Fixture { addr, dir }
}

/// A client frame, masked unless `unmasked`.
fn frame(opcode: u8, fin: bool, payload: &[u8], unmasked: bool) -> Vec<u8> {
    let mut f = vec![if fin { 0x80 } else { 0 } | opcode];
    let mask_bit = if unmasked { 0 } else { 0x80 };
    if payload.len() < 126 {
        f.push(mask_bit | payload.len() as u8);
    } else {
        // 126: a 16-bit extended payload length follows (RFC 6455 §5.2).
        f.push(mask_bit | 0x7e);
        f.extend_from_slice(&(payload.len() as u16).to_be_bytes());
    }
    if unmasked {
        f.extend_from_slice(payload);
    } else {
        let mask = [0x11u8, 0x22, 0x33, 0x44];
        f.extend_from_slice(&mask);
        f.extend(payload.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
    }
    f
}

#[derive(Debug)]
enum In {
    Text(Value),
    Pong,
    Close(u16, String),
}

struct Ws {
    s: TcpStream,
}

impl Ws {
    async fn connect(addr: std::net::SocketAddr) -> Self {
        let mut s = TcpStream::connect(addr).await.expect("connect");
        s.write_all(
            b"GET /api/scenes/s/live HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\
              Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n",
        )
        .await
        .expect("send");
        let mut head = Vec::new();
        while !head.ends_with(b"\r\n\r\n") {
            head.push(s.read_u8().await.expect("upgrade response"));
        }
        assert!(head.starts_with(b"HTTP/1.1 101"), "{}", String::from_utf8_lossy(&head));
        let mut ws = Self { s };
        match ws.recv().await {
            Some(In::Text(v)) => assert_eq!(v["type"], "welcome"),
            other => panic!("expected a welcome, got {other:?}"),
        }
        ws
    }

    /// The next text, pong or close frame within 10 s; `None` at the end of the stream.
    async fn recv(&mut self) -> Option<In> {
        tokio::time::timeout(Duration::from_secs(10), async {
            loop {
                let mut h = [0u8; 2];
                self.s.read_exact(&mut h).await.ok()?;
                let mut len = u64::from(h[1] & 0x7f);
                if len == 126 {
                    len = u64::from(self.s.read_u16().await.ok()?);
                } else if len == 127 {
                    len = self.s.read_u64().await.ok()?;
                }
                let mut p = vec![0u8; len as usize];
                self.s.read_exact(&mut p).await.ok()?;
                match h[0] & 0x0f {
                    1 => return Some(In::Text(serde_json::from_slice(&p).expect("JSON"))),
                    0xA => return Some(In::Pong),
                    8 => {
                        let code = p.get(..2).map_or(1005, |c| u16::from_be_bytes([c[0], c[1]]));
                        let reason = String::from_utf8_lossy(p.get(2..).unwrap_or_default()).into_owned();
                        return Some(In::Close(code, reason));
                    }
                    _ => {}
                }
            }
        })
        .await
        .expect("a frame within 10 s")
    }

    /// Skips text frames until a close frame; its code and reason.
    async fn close(&mut self) -> (u16, String) {
        loop {
            match self.recv().await {
                Some(In::Close(code, reason)) => return (code, reason),
                Some(_) => {}
                None => panic!("the connection ended without a close frame"),
            }
        }
    }
}

/// Sends `bytes` after the welcome and expects a 1008 close whose reason contains `expect`;
/// a bystander on the same scene is still served afterwards.
async fn closed_for(name: &str, bytes: Vec<u8>, expect: &str) {
    let f = fixture(name, HttpConfig::default()).await;
    let mut bystander = Ws::connect(f.addr).await;
    let mut bad = Ws::connect(f.addr).await;
    // The write may fail once the server has closed: what matters is what comes back.
    let _ = bad.s.write_all(&bytes).await;
    let (code, reason) = bad.close().await;
    assert_eq!(code, 1008, "{reason}");
    assert!(reason.contains(expect), "reason {reason:?} lacks {expect:?}");
    assert!(reason.len() <= 123);
    // The bystander sees the bad viewer's join and leave, and its own ping answered.
    bystander
        .s
        .write_all(&frame(9, true, b"still there", false))
        .await
        .expect("ping");
    let (mut left, mut pong) = (false, false);
    while !(left && pong) {
        match bystander.recv().await {
            Some(In::Text(v)) if v["type"] == "leave" => left = true,
            Some(In::Text(_)) => {}
            Some(In::Pong) => pong = true,
            other => panic!("bystander got {other:?}"),
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frame_over_the_limit_gets_1008() {
    let pose = format!(
        r#"{{"type":"pose","position":[0,0,0],"orientation":[0,0,0,1],"pad":"{}"}}"#,
        " ".repeat(MAX_CLIENT_MSG)
    );
    closed_for("big", frame(1, true, pose.as_bytes(), false), "Message too long").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_fragmented_message_over_the_limit_gets_1008() {
    let part = vec![b' '; 3000];
    let mut bytes = frame(1, false, &part, false);
    bytes.extend(frame(0, true, &part, false));
    closed_for("fragments", bytes, "Message too long").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn invalid_utf8_gets_1008() {
    closed_for("utf8", frame(1, true, b"{\"type\":\"\xff\xfe\"}", false), "UTF-8").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unmasked_frame_gets_1008() {
    let pose = br#"{"type":"pose","position":[0,0,0],"orientation":[0,0,0,1]}"#;
    closed_for("unmasked", frame(1, true, pose, true), "unmasked").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_binary_frame_gets_1008() {
    closed_for("binary", frame(2, true, b"\x00\x01", false), "binary").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_invalid_message_gets_1008() {
    closed_for(
        "invalid",
        frame(1, true, br#"{"type":"pose"}"#, false),
        "invalid message",
    )
    .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pings_and_pongs_count_towards_the_frame_limit() {
    let n = MAX_CLIENT_MSGS_PER_S as usize / 2 + 1;
    let mut bytes = Vec::new();
    for _ in 0..n {
        bytes.extend(frame(9, true, b"p", false));
        bytes.extend(frame(0xA, true, b"p", false));
    }
    closed_for("pings", bytes, "too many messages").await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pings_under_the_limit_are_answered() {
    let f = fixture("pings-ok", HttpConfig::default()).await;
    let mut ws = Ws::connect(f.addr).await;
    for _ in 0..20 {
        ws.s.write_all(&frame(9, true, b"p", false)).await.expect("ping");
        match ws.recv().await {
            Some(In::Pong) => {}
            other => panic!("expected a pong, got {other:?}"),
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn poses_between_two_publications_coalesce_latest_wins() {
    // Publications 400 ms apart: 30 poses written at once land in one or two of them.
    let config = HttpConfig {
        pose_interval: Duration::from_millis(400),
        ..HttpConfig::default()
    };
    let f = fixture("coalesce", config).await;
    let mut a = Ws::connect(f.addr).await;
    let mut b = Ws::connect(f.addr).await;
    let mut burst = Vec::new();
    for k in 0..30 {
        let pose = format!(r#"{{"type":"pose","position":[{k},0,0],"orientation":[0,0,0,1]}}"#);
        burst.extend(frame(1, true, pose.as_bytes(), false));
    }
    b.s.write_all(&burst).await.expect("send");
    let mut got = Vec::new();
    // Until the last pose arrives; then nothing else for a publication and more.
    while got.last() != Some(&29.0) {
        match a.recv().await {
            Some(In::Text(v)) if v["type"] == "presence" => {
                got.push(v["pose"]["position"][0].as_f64().expect("x"));
            }
            Some(In::Text(v)) => assert_eq!(v["type"], "join"),
            other => panic!("expected presence, got {other:?}"),
        }
    }
    assert!(got.len() <= 2, "30 poses in one burst arrived as {got:?}");
    // The sender never gets its own pose back.
    b.s.write_all(&frame(9, true, b"p", false)).await.expect("ping");
    match b.recv().await {
        Some(In::Pong) => {}
        other => panic!("the sender got {other:?} before its pong"),
    }
}
