//! End-to-end tests of `canopy-server serve`: the real binary on a free loopback port.

use canopy_e2e::net::{Server, WsClient, WsMessage, get_range, http, multipart_parts};
use canopy_e2e::scratch;
use serde_json::json;

const SMALL_DEMO: &[&str] = &["--demo-synthetic", "2", "--demo-trees", "400"];

/// Every asset URL of the demo's manifest, with its file on disk.
fn demo_assets(s: &Server) -> Vec<(String, Vec<u8>)> {
    let m = http(s.addr, "GET", "/api/scenes/demo/manifest", &[], None).json();
    let mut urls: Vec<String> = m["models"]
        .as_array()
        .expect("models")
        .iter()
        .map(|m| m["url"].as_str().expect("url").to_string())
        .collect();
    urls.push(m["pack"]["url"].as_str().expect("pack").to_string());
    urls.iter()
        .map(|u| {
            let rel = u.strip_prefix("/assets/").expect("under /assets/");
            let bytes = std::fs::read(s.data.join("assets").join(rel)).expect("asset file on disk at its URL path");
            (u.clone(), bytes)
        })
        .collect()
}

#[test]
fn demo_assets_are_served_by_range_with_validators() {
    let dir = scratch("serve-ranges");
    let s = Server::start(&dir.join("data"), SMALL_DEMO);
    let list = http(s.addr, "GET", "/api/scenes", &[], None).json();
    let demo = &list["scenes"][0];
    assert_eq!(demo["id"], "demo");
    assert_eq!(demo["instance_count"], 400);
    // RFC 9112 §3.2: an HTTP/1.1 request needs exactly one Host header (400 otherwise).
    let status = |head: &str| -> u16 {
        use std::io::{Read, Write};
        let mut c = std::net::TcpStream::connect(s.addr).expect("connect");
        c.set_read_timeout(Some(std::time::Duration::from_secs(10)))
            .expect("timeout");
        c.write_all(head.as_bytes()).expect("send");
        let mut raw = Vec::new();
        let _ = c.read_to_end(&mut raw);
        String::from_utf8_lossy(&raw)
            .split(' ')
            .nth(1)
            .and_then(|x| x.parse().ok())
            .expect("status line")
    };
    let close = "Connection: close\r\n\r\n";
    assert_eq!(status(&format!("GET /healthz HTTP/1.1\r\n{close}")), 400, "no Host");
    assert_eq!(
        status(&format!("GET /healthz HTTP/1.1\r\nHost: a\r\nHost: b\r\n{close}")),
        400,
        "two Host headers"
    );
    assert_eq!(status(&format!("GET /healthz HTTP/1.1\r\nHost: a\r\n{close}")), 200);
    assert_eq!(status("GET /healthz HTTP/1.0\r\n\r\n"), 200, "HTTP/1.0 needs no Host");
    let assets = demo_assets(&s);
    assert_eq!(assets.len(), 3);
    for (url, data) in &assets {
        let n = data.len();
        let full = http(s.addr, "GET", url, &[], None);
        assert_eq!(full.status, 200);
        assert!(full.body == *data, "{url}: served bytes equal the file");
        let etag = full.header("etag").expect("etag").to_string();
        assert_eq!(
            full.header("cache-control"),
            Some("public, max-age=31536000, immutable")
        );
        assert_eq!(full.header("accept-ranges"), Some("bytes"));
        assert_eq!(full.header("access-control-allow-origin"), Some("*"));

        for (range, a, b) in [
            ("bytes=0-63", 0, 64),
            ("bytes=100-", 100, n),
            ("bytes=-16", n - 16, n),
            ("bYtEs=1-1", 1, 2),
        ] {
            let r = get_range(s.addr, url, range);
            assert_eq!(r.status, 206, "{range}");
            assert!(r.body == data[a..b], "{range}");
            assert_eq!(
                r.header("content-range"),
                Some(format!("bytes {a}-{}/{n}", b - 1).as_str())
            );
        }
        let r = get_range(s.addr, url, &format!("bytes=0-9,{}-{}", n - 10, n - 1));
        assert_eq!(r.status, 206);
        let parts = multipart_parts(r.header("content-type").expect("type"), &r.body);
        assert_eq!(parts.len(), 2);
        assert!(parts[0].2 == data[..10] && parts[1].2 == data[n - 10..]);
        assert_eq!(
            get_range(s.addr, url, "bytes=9-1").status,
            200,
            "invalid Range is ignored"
        );
        let r = get_range(s.addr, url, &format!("bytes={n}-"));
        assert_eq!(r.status, 416);
        assert_eq!(r.header("content-range"), Some(format!("bytes */{n}").as_str()));
        assert_eq!(http(s.addr, "GET", url, &[("If-None-Match", &etag)], None).status, 304);
        let r = http(
            s.addr,
            "GET",
            url,
            &[("Range", "bytes=0-0"), ("If-Range", "\"stale\"")],
            None,
        );
        assert_eq!(r.status, 200);
        let h = http(s.addr, "HEAD", url, &[], None);
        assert_eq!(h.status, 200);
        assert!(h.body.is_empty());
        assert_eq!(h.header("content-length"), Some(n.to_string().as_str()));
    }
    assert_eq!(http(s.addr, "GET", "/healthz", &[], None).status, 200);
    let m = String::from_utf8(http(s.addr, "GET", "/metrics", &[], None).body).expect("utf8");
    assert!(m.contains("canopy_asset_ranges_per_request_bucket{le=\"2\"}"), "{m}");
    assert!(m.contains("canopy_live_viewers 0"));
}

#[test]
fn restart_reuses_the_demo_and_sigterm_stops_cleanly() {
    let dir = scratch("serve-restart");
    let data = dir.join("data");
    let s = Server::start(&data, SMALL_DEMO);
    let first = http(s.addr, "GET", "/api/scenes/demo/manifest", &[], None).body;
    assert!(s.stop().success(), "graceful shutdown exits 0");
    // Different demo flags: the existing demo is kept, not rebuilt.
    let s = Server::start(&data, &["--demo-synthetic", "3", "--demo-trees", "50"]);
    let second = http(s.addr, "GET", "/api/scenes/demo/manifest", &[], None).body;
    assert!(first == second, "the demo was rebuilt");
}

#[test]
fn scene_api_over_the_wire() {
    let dir = scratch("serve-api");
    let s = Server::start(
        &dir.join("data"),
        &[
            "--demo-synthetic",
            "1",
            "--demo-trees",
            "20",
            "--demo-width-m",
            "200",
            "--demo-depth-m",
            "100",
            "--open-creation",
        ],
    );
    let manifest = http(s.addr, "GET", "/api/scenes/demo/manifest", &[], None).json();
    assert_eq!(
        manifest["bounds"],
        json!({"min": [-100.0, -50.0], "max": [100.0, 50.0]})
    );
    let model = manifest["models"][0]["name"].as_str().expect("model").to_string();
    let body = json!({"name": "Private", "public": false, "bounds": {"min": [0.0, 0.0], "max": [10.0, 10.0]},
        "instances": [{"model": model, "position": [1.0, 0.0, 1.0]}]})
    .to_string();
    let r = http(s.addr, "POST", "/api/scenes", &[], Some(body.as_bytes()));
    assert_eq!(r.status, 201);
    let v = r.json();
    let id = v["id"].as_str().expect("id").to_string();
    let (write, read) = (
        v["write_token"].as_str().expect("w").to_string(),
        v["read_token"].as_str().expect("r").to_string(),
    );
    let path = format!("/api/scenes/{id}/manifest");
    assert_eq!(http(s.addr, "GET", &path, &[], None).status, 401);
    assert_eq!(
        http(
            s.addr,
            "GET",
            &path,
            &[("Authorization", &format!("Bearer {read}"))],
            None
        )
        .status,
        200
    );
    let edit = format!("/api/scenes/{id}/instances");
    let bad = http(
        s.addr,
        "POST",
        &edit,
        &[("Authorization", &format!("Bearer {write}"))],
        Some(b"{\"add\": [{\"model\": 1"),
    );
    assert_eq!(bad.status, 400);
    assert!(bad.json()["error"].as_str().is_some_and(|e| e.contains("invalid JSON")));
    let add = json!({"add": [{"model": model, "position": [2.0, 0.0, 2.0]}]}).to_string();
    assert_eq!(
        http(
            s.addr,
            "POST",
            &edit,
            &[("Authorization", &format!("Bearer {read}"))],
            Some(add.as_bytes())
        )
        .status,
        403
    );
    let r = http(
        s.addr,
        "POST",
        &edit,
        &[("Authorization", &format!("Bearer {write}"))],
        Some(add.as_bytes()),
    );
    assert_eq!(r.status, 200);
    assert_eq!(r.json()["version"], 2);
    let pre = http(
        s.addr,
        "OPTIONS",
        "/api/scenes",
        &[("Origin", "http://x"), ("Access-Control-Request-Method", "POST")],
        None,
    );
    assert_eq!(pre.status, 204);
    assert!(
        pre.header("access-control-allow-headers")
            .is_some_and(|h| h.contains("Authorization"))
    );
}

#[test]
fn live_presence_and_edit_notifications_between_two_viewers() {
    let dir = scratch("serve-live");
    let data = dir.join("data");
    let s = Server::start(
        &data,
        &[
            "--demo-synthetic",
            "1",
            "--demo-trees",
            "20",
            "--pose-interval-ms",
            "20",
        ],
    );
    let mut a = WsClient::connect(s.addr, "/api/scenes/demo/live").expect("upgrade");
    let wa = a.recv_until(1, |v| v["type"] == "welcome");
    assert_eq!(wa["version"], 1);
    let mut b = WsClient::connect(s.addr, "/api/scenes/demo/live").expect("upgrade");
    let wb = b.recv_until(1, |v| v["type"] == "welcome");
    let b_id = wb["viewer"].clone();
    assert_eq!(wb["viewers"].as_array().map(Vec::len), Some(1), "B sees A");
    a.recv_until(5, |v| v["type"] == "join" && v["viewer"] == b_id);

    b.send_text(r#"{"type":"pose","position":[1.5,2.0,-3.0],"orientation":[0,0,0,1]}"#);
    let p = a.recv_until(5, |v| v["type"] == "presence");
    assert_eq!(p["viewer"], b_id);
    assert_eq!(p["pose"]["position"], json!([1.5, 2.0, -3.0]));

    // An edit notifies both viewers of the new version.
    let token = std::fs::read_to_string(data.join("demo-write-token")).expect("demo token");
    let add = json!({"remove": [1]}).to_string();
    let r = http(
        s.addr,
        "POST",
        "/api/scenes/demo/instances",
        &[("Authorization", &format!("Bearer {}", token.trim()))],
        Some(add.as_bytes()),
    );
    assert_eq!(r.status, 200, "{}", String::from_utf8_lossy(&r.body));
    for c in [&mut a, &mut b] {
        let v = c.recv_until(5, |v| v["type"] == "version");
        assert_eq!(v["version"], 2);
    }
    let m = String::from_utf8(http(s.addr, "GET", "/metrics", &[], None).body).expect("utf8");
    assert!(m.contains("canopy_live_viewers 2"), "{m}");

    // A malformed message closes that viewer with a reason; the other sees it leave.
    b.send_text(r#"{"type":"pose","position":"up"}"#);
    match b.recv() {
        Some(WsMessage::Close(code, reason)) => {
            assert_eq!(code, 1008);
            assert!(reason.contains("invalid message"), "{reason}");
        }
        other => panic!("expected a close frame, got {other:?}"),
    }
    a.recv_until(5, |v| v["type"] == "leave" && v["viewer"] == b_id);
    assert_eq!(WsClient::connect(s.addr, "/api/scenes/nope/live").err(), Some(404));

    // Shutdown closes the remaining viewer with "going away".
    let stopper = std::thread::spawn(move || s.stop());
    match a.recv() {
        Some(WsMessage::Close(code, _)) => assert_eq!(code, 1001),
        other => panic!("expected a close frame, got {other:?}"),
    }
    assert!(stopper.join().expect("stop thread").success());
}
