//! Interoperability: nginx serving `DATA/assets` as a plain static host answers byte ranges with
//! the same bytes as Canopy, so the asset folder can be copied to any CDN or bucket.

use canopy_e2e::net::{HttpResponse, Nginx, Server, get_range, http, multipart_parts};
use canopy_e2e::scratch;

fn parts(r: &HttpResponse) -> Vec<(u64, u64, Vec<u8>)> {
    let ct = r.header("content-type").expect("content-type");
    if ct.starts_with("multipart/byteranges") {
        multipart_parts(ct, &r.body)
    } else {
        let cr = r.header("content-range").expect("content-range");
        let (a, b) = cr
            .trim_start_matches("bytes ")
            .split('/')
            .next()
            .and_then(|r| r.split_once('-'))
            .expect("range");
        vec![(a.parse().expect("a"), b.parse().expect("b"), r.body.clone())]
    }
}

#[test]
fn nginx_serves_the_same_bytes_from_the_asset_folder() {
    let dir = scratch("serve-nginx");
    let data = dir.join("data");
    let s = Server::start(&data, &["--demo-synthetic", "2", "--demo-trees", "300"]);
    let Some(ng) = Nginx::start(&data.join("assets"), &dir.join("nginx")) else {
        return;
    };
    let m = http(s.addr, "GET", "/api/scenes/demo/manifest", &[], None).json();
    let mut urls: Vec<String> = m["models"]
        .as_array()
        .expect("models")
        .iter()
        .filter_map(|m| m["url"].as_str().map(String::from))
        .collect();
    urls.push(m["pack"]["url"].as_str().expect("pack").to_string());
    let manifest_copy = http(s.addr, "GET", "/api/scenes/demo/manifest", &[], None);
    urls.push(
        manifest_copy
            .header("content-location")
            .expect("static manifest URL")
            .to_string(),
    );
    assert!(urls.len() >= 4);
    // Assets are read-only on both: a write method is refused with 405, never answered with the
    // file (the real binary, beside the router's own test in server/tests/http_assets.rs).
    for method in ["POST", "PUT", "DELETE"] {
        let (c, n) = (
            http(s.addr, method, &urls[0], &[], Some(b"x")),
            http(ng.addr, method, &urls[0], &[], Some(b"x")),
        );
        assert_eq!((c.status, n.status), (405, 405), "{method} {}", urls[0]);
        assert_eq!(c.header("allow"), Some("GET, HEAD, OPTIONS"), "{method}");
    }
    for url in &urls {
        let (c, n) = (
            http(s.addr, "GET", url, &[], None),
            http(ng.addr, "GET", url, &[], None),
        );
        assert_eq!((c.status, n.status), (200, 200), "{url}");
        assert!(c.body == n.body, "{url}: full bodies differ");
        let len = c.body.len();
        let ranges = [
            "bytes=0-63".to_string(),
            "bytes=10-".to_string(),
            "bytes=-20".to_string(),
            format!("bytes=0-{}", len * 2),
            // Far apart, in order: both servers answer with two parts.
            format!("bytes=0-15,{}-{}", len - 16, len - 1),
        ];
        for range in &ranges {
            let (c, n) = (get_range(s.addr, url, range), get_range(ng.addr, url, range));
            assert_eq!((c.status, n.status), (206, 206), "{url} {range}");
            assert_eq!(parts(&c), parts(&n), "{url} {range}");
        }
        let past = format!("bytes={len}-");
        let (c, n) = (get_range(s.addr, url, &past), get_range(ng.addr, url, &past));
        assert_eq!((c.status, n.status), (416, 416));
        assert_eq!(c.header("content-range"), n.header("content-range"));
        let (c, n) = (
            http(s.addr, "HEAD", url, &[], None),
            http(ng.addr, "HEAD", url, &[], None),
        );
        assert_eq!(c.header("content-length"), n.header("content-length"));
    }
}
