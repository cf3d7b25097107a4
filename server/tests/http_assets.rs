//! In-process tests of `/assets/`: every Range case of RFC 9110 §14, conditional requests, HEAD,
//! CORS, and the abuse limits.

use std::path::PathBuf;
use std::sync::Arc;

use axum::body::Body;
use axum::http::{Request, Response, StatusCode};
use canopy_server::http::range::{COALESCE_GAP, MAX_RANGE_SPECS};
use canopy_server::http::{AppState, HttpConfig, router};
use canopy_server::store::{AssetStore, SqliteStore};
use tower::ServiceExt;

struct Fixture {
    app: axum::Router,
    dir: PathBuf,
    small: (String, Vec<u8>, String),
    large: (String, Vec<u8>, String),
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// The small file (10 kB) is held in memory, the large one (1 MB) is read from disk: both paths
/// answer every test.
fn fixture(name: &str) -> Fixture {
    fixture_with(name, 100_000)
}

fn fixture_with(name: &str, memory_budget: u64) -> Fixture {
    let dir = std::env::temp_dir().join(format!("canopy-http-assets-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let assets = Arc::new(AssetStore::open_with_memory(&dir, memory_budget).expect("asset store"));
    let small: Vec<u8> = (0..10_000u32).map(|i| (i % 251) as u8).collect();
    let large: Vec<u8> = (0..1_000_000u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 24) as u8)
        .collect();
    let a = assets.put("trees", "small", "ctree", &small).expect("put");
    let b = assets.put("trees", "large", "ctree", &large).expect("put");
    let scenes = Arc::new(SqliteStore::in_memory().expect("db"));
    let (state, _stop) = AppState::new(assets, scenes, HttpConfig::default());
    Fixture {
        app: router(state),
        dir,
        small: (a.url(), small, a.etag.clone()),
        large: (b.url(), large, b.etag.clone()),
    }
}

async fn send(app: &axum::Router, method: &str, uri: &str, headers: &[(&str, &str)]) -> (Response<Body>, Vec<u8>) {
    let mut req = Request::builder().method(method).uri(uri);
    for (k, v) in headers {
        req = req.header(*k, *v);
    }
    let resp = app
        .clone()
        .oneshot(req.body(Body::empty()).expect("request"))
        .await
        .expect("infallible");
    let (parts, body) = resp.into_parts();
    let bytes = axum::body::to_bytes(body, usize::MAX).await.expect("body").to_vec();
    (Response::from_parts(parts, Body::empty()), bytes)
}

fn header<'a>(r: &'a Response<Body>, name: &str) -> &'a str {
    r.headers().get(name).and_then(|v| v.to_str().ok()).unwrap_or("")
}

/// Splits a `multipart/byteranges` body into `(Content-Range, data)` parts.
fn parse_multipart(content_type: &str, body: &[u8]) -> Vec<(String, Vec<u8>)> {
    let boundary = content_type.split("boundary=").nth(1).expect("boundary");
    let delim = format!("--{boundary}");
    let mut parts = Vec::new();
    let mut rest = body;
    loop {
        let at = find(rest, delim.as_bytes()).expect("delimiter");
        rest = &rest[at + delim.len()..];
        if rest.starts_with(b"--") {
            break;
        }
        let head_end = find(rest, b"\r\n\r\n").expect("part head");
        let head = std::str::from_utf8(&rest[..head_end]).expect("utf8");
        let range = head
            .lines()
            .find_map(|l| l.strip_prefix("Content-Range: "))
            .expect("Content-Range")
            .to_string();
        let (a, b) = range
            .trim_start_matches("bytes ")
            .split('/')
            .next()
            .and_then(|r| r.split_once('-'))
            .expect("range");
        let len = b.parse::<usize>().expect("n") - a.parse::<usize>().expect("n") + 1;
        let data = rest[head_end + 4..head_end + 4 + len].to_vec();
        rest = &rest[head_end + 4 + len..];
        assert!(
            rest.starts_with(b"\r\n--"),
            "part data must be followed by CRLF and the delimiter"
        );
        parts.push((range, data));
    }
    parts
}

fn find(h: &[u8], n: &[u8]) -> Option<usize> {
    h.windows(n.len()).position(|w| w == n)
}

#[tokio::test]
async fn full_get_and_head_carry_caching_and_cors_headers() {
    let f = fixture("full");
    let (url, data, etag) = &f.small;
    let (r, body) = send(&f.app, "GET", url, &[]).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert!(&body == data);
    assert_eq!(header(&r, "etag"), etag);
    assert!(etag.starts_with('"') && !etag.starts_with("W/"));
    assert_eq!(header(&r, "cache-control"), "public, max-age=31536000, immutable");
    assert_eq!(header(&r, "accept-ranges"), "bytes");
    assert_eq!(header(&r, "access-control-allow-origin"), "*");
    assert!(header(&r, "access-control-expose-headers").contains("Content-Range"));
    assert_eq!(header(&r, "content-length"), data.len().to_string());
    let (h, body) = send(&f.app, "HEAD", url, &[("range", "bytes=0-0")]).await;
    assert_eq!(h.status(), StatusCode::OK, "Range is ignored on HEAD");
    assert!(body.is_empty());
    assert_eq!(header(&h, "content-length"), data.len().to_string());
    assert_eq!(header(&h, "etag"), etag);
    // The URL names the bytes: its hash part is the start of the SHA-256 in the ETag.
    let hash16 = url
        .rsplit('/')
        .next()
        .and_then(|f| f.split('.').nth(1))
        .expect("hash in url");
    assert!(etag.trim_matches('"').starts_with(hash16));
}

#[tokio::test]
async fn single_open_ended_and_suffix_ranges() {
    let f = fixture("single");
    let (url, data, _) = &f.small;
    let n = data.len();
    for (range, start, end) in [
        ("bytes=0-99", 0, 100),
        ("bytes=9990-", 9990, n),
        ("bytes=-10", n - 10, n),
        ("bytes=-999999", 0, n),
        ("bytes=5000-999999", 5000, n),
        ("BYTES=1-1", 1, 2),
        ("Bytes=10-19, 20-29", 10, 30),
        ("bytes=0-9,5-14", 0, 15),
        ("bytes=20000-,100-100", 100, 101),
    ] {
        let (r, body) = send(&f.app, "GET", url, &[("range", range)]).await;
        assert_eq!(r.status(), StatusCode::PARTIAL_CONTENT, "{range}");
        assert!(body == data[start..end], "{range}");
        assert_eq!(
            header(&r, "content-range"),
            format!("bytes {start}-{}/{n}", end - 1),
            "{range}"
        );
        assert_eq!(header(&r, "content-length"), (end - start).to_string());
        assert!(!header(&r, "content-type").starts_with("multipart"));
    }
}

#[tokio::test]
async fn several_ranges_come_back_as_multipart_byteranges() {
    let f = fixture("multi");
    let (url, data, _) = &f.large;
    let n = data.len();
    let (r, body) = send(
        &f.app,
        "GET",
        url,
        &[("range", "bytes=500000-500099,0-9,-5,100000-100000")],
    )
    .await;
    assert_eq!(r.status(), StatusCode::PARTIAL_CONTENT);
    let ct = header(&r, "content-type");
    assert!(ct.starts_with("multipart/byteranges; boundary="), "{ct}");
    assert_eq!(header(&r, "content-length"), body.len().to_string());
    let parts = parse_multipart(ct, &body);
    let want = [(0, 10), (100_000, 100_001), (500_000, 500_100), (n - 5, n)];
    assert_eq!(parts.len(), want.len());
    for ((cr, bytes), (a, b)) in parts.iter().zip(want) {
        assert_eq!(cr, &format!("bytes {a}-{}/{n}", b - 1));
        assert!(bytes == &data[a..b]);
    }
}

#[tokio::test]
async fn large_responses_stream_the_right_bytes() {
    let f = fixture("stream");
    let (url, data, _) = &f.large;
    let (r, body) = send(&f.app, "GET", url, &[]).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert!(&body == data);
    let (r, body) = send(&f.app, "GET", url, &[("range", "bytes=1-700000,900000-999998")]).await;
    let parts = parse_multipart(header(&r, "content-type"), &body);
    assert!(parts[0].1 == data[1..700_001]);
    assert!(parts[1].1 == data[900_000..999_999]);
}

#[tokio::test]
async fn invalid_range_headers_are_ignored() {
    let f = fixture("invalid");
    let (url, data, _) = &f.small;
    for range in [
        "bytes=5-1",
        "bytes=abc",
        "bytes=",
        "bytes=1-2-3",
        "pages=1-2",
        "bytes 0-1",
        "bytes=0-1;x",
        "bytes=--1",
    ] {
        let (r, body) = send(&f.app, "GET", url, &[("range", range)]).await;
        assert_eq!(r.status(), StatusCode::OK, "{range}");
        assert!(&body == data, "{range}");
    }
}

#[tokio::test]
async fn unsatisfiable_ranges_give_416_with_the_length() {
    let f = fixture("416");
    let (url, data, _) = &f.small;
    for range in [
        "bytes=10000-",
        "bytes=20000-30000",
        "bytes=-0",
        "bytes=10000-10000,99999-",
    ] {
        let (r, body) = send(&f.app, "GET", url, &[("range", range)]).await;
        assert_eq!(r.status(), StatusCode::RANGE_NOT_SATISFIABLE, "{range}");
        assert_eq!(header(&r, "content-range"), format!("bytes */{}", data.len()));
        assert!(body.is_empty());
    }
}

#[tokio::test]
async fn conditional_requests() {
    let f = fixture("cond");
    let (url, data, etag) = &f.small;
    let weak = format!("W/{etag}");
    for inm in [etag.as_str(), "*", weak.as_str(), &format!("\"other\", {etag}")] {
        let (r, body) = send(&f.app, "GET", url, &[("if-none-match", inm)]).await;
        assert_eq!(r.status(), StatusCode::NOT_MODIFIED, "{inm}");
        assert!(body.is_empty());
        assert_eq!(header(&r, "etag"), etag);
        assert_eq!(header(&r, "cache-control"), "public, max-age=31536000, immutable");
    }
    let (r, _) = send(&f.app, "GET", url, &[("if-none-match", "\"other\"")]).await;
    assert_eq!(r.status(), StatusCode::OK);
    // If-Range: the range applies only when the strong validator matches.
    let (r, body) = send(&f.app, "GET", url, &[("range", "bytes=0-3"), ("if-range", etag)]).await;
    assert_eq!(r.status(), StatusCode::PARTIAL_CONTENT);
    assert!(body == data[..4]);
    for ir in ["\"other\"", weak.as_str(), "Tue, 15 Nov 1994 08:12:31 GMT"] {
        let (r, body) = send(&f.app, "GET", url, &[("range", "bytes=0-3"), ("if-range", ir)]).await;
        assert_eq!(r.status(), StatusCode::OK, "{ir}");
        assert!(&body == data);
    }
}

#[tokio::test]
async fn abuse_is_bounded() {
    let f = fixture("abuse");
    let (url, data, _) = &f.large;
    let n = data.len();
    // Many overlapping ranges: merged into one.
    let many: Vec<String> = (0..MAX_RANGE_SPECS).map(|i| format!("{}-{}", i, i + 5000)).collect();
    let (r, body) = send(&f.app, "GET", url, &[("range", &format!("bytes={}", many.join(",")))]).await;
    assert_eq!(r.status(), StatusCode::PARTIAL_CONTENT);
    assert!(body == data[..MAX_RANGE_SPECS - 1 + 5001], "one merged range");
    // Many tiny ranges with gaps below the coalesce gap: one part, never more than the file.
    let tiny: Vec<String> = (0..MAX_RANGE_SPECS).map(|i| format!("{0}-{0}", i * 200)).collect();
    let (r, body) = send(&f.app, "GET", url, &[("range", &format!("bytes={}", tiny.join(",")))]).await;
    assert_eq!(r.status(), StatusCode::PARTIAL_CONTENT);
    assert!(!header(&r, "content-type").starts_with("multipart"));
    assert!(body.len() <= n);
    // Tiny ranges just above the gap: multipart, yet the body stays within the file's size plus
    // one part header and the closing delimiter.
    let step = COALESCE_GAP as usize + 2;
    let spread: Vec<String> = (0..MAX_RANGE_SPECS).map(|i| format!("{0}-{0}", i * step)).collect();
    let (r, body) = send(&f.app, "GET", url, &[("range", &format!("bytes={}", spread.join(",")))]).await;
    assert_eq!(r.status(), StatusCode::PARTIAL_CONTENT);
    let parts = parse_multipart(header(&r, "content-type"), &body);
    assert_eq!(parts.len(), MAX_RANGE_SPECS);
    let span = (MAX_RANGE_SPECS - 1) * step + 1;
    assert!(
        body.len() <= span + COALESCE_GAP as usize + 64,
        "{} bytes for a {span}-byte span",
        body.len()
    );
    // More specs than the limit: the header is ignored, the file is sent once.
    let over: Vec<String> = (0..=MAX_RANGE_SPECS).map(|i| format!("{0}-{0}", i * step)).collect();
    let (r, body) = send(&f.app, "GET", url, &[("range", &format!("bytes={}", over.join(",")))]).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(body.len(), n);
}

#[tokio::test]
async fn preflight_and_unknown_paths() {
    let f = fixture("misc");
    let (url, _, _) = &f.small;
    let (r, _) = send(
        &f.app,
        "OPTIONS",
        url,
        &[
            ("origin", "http://example.com"),
            ("access-control-request-method", "GET"),
        ],
    )
    .await;
    assert_eq!(r.status(), StatusCode::NO_CONTENT);
    assert!(header(&r, "access-control-allow-headers").contains("Range"));
    assert!(header(&r, "access-control-allow-methods").contains("GET"));
    for path in [
        "/assets/trees/nope.0123456789abcdef.ctree",
        "/assets/../canopy.db",
        "/assets/",
        "/assets/trees",
    ] {
        let (r, _) = send(&f.app, "GET", path, &[]).await;
        assert_eq!(r.status(), StatusCode::NOT_FOUND, "{path}");
    }
    let (r, body) = send(&f.app, "GET", "/healthz", &[]).await;
    assert_eq!(r.status(), StatusCode::OK);
    assert_eq!(body, b"ok\n");
    let (_, body) = send(&f.app, "GET", "/metrics", &[]).await;
    let text = String::from_utf8(body).expect("utf8");
    // "/assets/" has no file part and falls through to the generic 404.
    assert!(
        text.contains("canopy_http_requests_total{route=\"assets\",status=\"4xx\"} 3"),
        "{text}"
    );
    assert!(
        text.contains("canopy_http_requests_total{route=\"other\",status=\"4xx\"} 1"),
        "{text}"
    );
    assert!(text.contains("# TYPE canopy_http_request_duration_seconds histogram"));
    assert!(text.contains("canopy_live_viewers 0"));
}

#[tokio::test]
async fn memory_and_disk_answer_byte_for_byte_alike() {
    let disk = fixture_with("disk", 0);
    let memory = fixture_with("memory", u64::MAX);
    let cases: &[&[(&str, &str)]] = &[
        &[],
        &[("range", "bytes=0-0")],
        &[("range", "bytes=100-16483")],
        &[("range", "bytes=-500")],
        &[("range", "bytes=999000-")],
        &[("range", "bytes=0-99,5000-5999,9000-")],
        &[(
            "range",
            "bytes=0-2047,65536-67583,131072-133119,262144-264191,524288-526335",
        )],
        &[("range", "bytes=10-20,400000-700000")],
        &[("range", "bytes=2000000-")],
        &[("range", "bytes=5-10"), ("if-range", "\"other\"")],
    ];
    for (url, _, _) in [&disk.small, &disk.large] {
        for &case in cases {
            let (a, ab) = send(&disk.app, "GET", url, case).await;
            let (b, bb) = send(&memory.app, "GET", url, case).await;
            assert_eq!(a.status(), b.status(), "{url} {case:?}");
            for h in [
                "content-length",
                "content-range",
                "etag",
                "cache-control",
                "accept-ranges",
            ] {
                assert_eq!(header(&a, h), header(&b, h), "{h}: {url} {case:?}");
            }
            let (ta, tb) = (header(&a, "content-type"), header(&b, "content-type"));
            if ta.starts_with("multipart/") {
                assert_eq!(parse_multipart(ta, &ab), parse_multipart(tb, &bb), "{url} {case:?}");
            } else {
                assert_eq!(ta, tb);
                assert_eq!(ab, bb, "{url} {case:?}");
            }
            assert_eq!(ab.len().to_string(), header(&a, "content-length"));
        }
    }
}

#[tokio::test]
async fn assets_refuse_writes_with_405_and_allow() {
    let f = fixture("methods");
    let url = &f.small.0;
    for method in ["POST", "PUT", "DELETE", "PATCH"] {
        let (r, body) = send(&f.app, method, url, &[]).await;
        assert_eq!(r.status(), StatusCode::METHOD_NOT_ALLOWED, "{method}");
        assert_eq!(header(&r, "allow"), "GET, HEAD, OPTIONS", "{method}");
        assert_eq!(header(&r, "access-control-allow-origin"), "*", "{method}");
        assert!(body.len() < 100, "{method} answered {} bytes, not an error", body.len());
        // Unknown paths too: the method is refused before the path is looked up.
        let (r, _) = send(&f.app, method, "/assets/trees/none.ctree", &[]).await;
        assert_eq!(
            r.status(),
            StatusCode::METHOD_NOT_ALLOWED,
            "{method} on a missing asset"
        );
    }
    // The read methods still answer.
    let (r, body) = send(&f.app, "GET", url, &[]).await;
    assert_eq!((r.status(), body.len()), (StatusCode::OK, f.small.1.len()));
    let (r, _) = send(&f.app, "HEAD", url, &[]).await;
    assert_eq!(r.status(), StatusCode::OK);
}
