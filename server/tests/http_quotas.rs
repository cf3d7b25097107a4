//! In-process tests of who may create scenes, the quotas, the rate limits, pins and version
//! retention through the API (issue 23): every refusal is the API's JSON error and changes nothing.

use std::net::IpAddr;
use std::path::PathBuf;
use std::sync::Arc;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use canopy_server::demo::{bake_and_store, synthetic_model};
use canopy_server::http::quota::{Creation, Peer, Rate};
use canopy_server::http::{AppState, HttpConfig, router};
use canopy_server::store::scenes::Limits;
use canopy_server::store::{AssetStore, SqliteStore};
use serde_json::{Value, json};
use tower::ServiceExt;

struct Fixture {
    app: axum::Router,
    dir: PathBuf,
    model: String,
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn fixture(name: &str, config: HttpConfig) -> Fixture {
    let dir = std::env::temp_dir().join(format!("canopy-http-quotas-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let assets = Arc::new(AssetStore::open(&dir).expect("asset store"));
    let scenes = Arc::new(SqliteStore::in_memory().expect("db"));
    let (state, _stop) = AppState::new(assets, scenes, config);
    let model = bake_and_store(&state, &synthetic_model(0)).expect("bake");
    Fixture {
        app: router(state),
        dir,
        model,
    }
}

struct Reply {
    status: StatusCode,
    json: Value,
    retry_after: Option<u64>,
    location: Option<String>,
}

async fn call(
    app: &axum::Router,
    method: &str,
    uri: &str,
    token: Option<&str>,
    ip: &str,
    body: Option<&Value>,
) -> Reply {
    let mut req = Request::builder().method(method).uri(uri);
    if let Some(t) = token {
        req = req.header("authorization", format!("Bearer {t}"));
    }
    if body.is_some() {
        req = req.header("content-type", "application/json");
    }
    let mut req = req
        .body(body.map_or_else(Body::empty, |b| Body::from(b.to_string())))
        .expect("request");
    req.extensions_mut().insert(Peer(ip.parse::<IpAddr>().expect("ip")));
    let resp = app.clone().oneshot(req).await.expect("infallible");
    let status = resp.status();
    let retry_after = resp
        .headers()
        .get("retry-after")
        .and_then(|v| v.to_str().ok()?.parse().ok());
    let location = resp
        .headers()
        .get("content-location")
        .and_then(|v| Some(v.to_str().ok()?.to_string()));
    let bytes = axum::body::to_bytes(resp.into_body(), usize::MAX).await.expect("body");
    Reply {
        status,
        json: serde_json::from_slice(&bytes).unwrap_or(Value::Null),
        retry_after,
        location,
    }
}

fn scene(id: &str, model: &str, n: usize) -> Value {
    let instances: Vec<Value> = (0..n)
        .map(|k| json!({"model": model, "position": [k as f32 % 90.0, 0.0, 1.0]}))
        .collect();
    json!({"id": id, "name": id, "public": false, "bounds": {"min": [0.0, 0.0], "max": [100.0, 100.0]}, "instances": instances})
}

fn assert_error(r: &Reply, status: StatusCode, contains: &str) {
    assert_eq!(r.status, status, "{}", r.json);
    let e = r.json["error"].as_str().unwrap_or_default();
    assert!(e.contains(contains), "{e:?} lacks {contains:?}");
}

#[tokio::test]
async fn creation_needs_a_server_token_and_counts_against_its_quota() {
    let f = fixture(
        "tokens",
        HttpConfig {
            creation: Creation::tokens(&["alpha", "beta"]),
            limits: Limits {
                max_scenes: 2,
                max_instances: 5,
                ..Limits::default()
            },
            ..HttpConfig::default()
        },
    );
    let ip = "10.0.0.1";
    let r = call(&f.app, "POST", "/api/scenes", None, ip, Some(&scene("a", &f.model, 1))).await;
    assert_error(&r, StatusCode::UNAUTHORIZED, "creation token");
    let r = call(
        &f.app,
        "POST",
        "/api/scenes",
        Some("gamma"),
        ip,
        Some(&scene("a", &f.model, 1)),
    )
    .await;
    assert_error(&r, StatusCode::FORBIDDEN, "not a creation token");
    let r = call(
        &f.app,
        "POST",
        "/api/scenes",
        Some("alpha"),
        ip,
        Some(&scene("a", &f.model, 6)),
    )
    .await;
    assert_error(&r, StatusCode::FORBIDDEN, "quota");
    for id in ["a", "b"] {
        let r = call(
            &f.app,
            "POST",
            "/api/scenes",
            Some("alpha"),
            ip,
            Some(&scene(id, &f.model, 1)),
        )
        .await;
        assert_eq!(r.status, StatusCode::CREATED, "{}", r.json);
    }
    let r = call(
        &f.app,
        "POST",
        "/api/scenes",
        Some("alpha"),
        ip,
        Some(&scene("c", &f.model, 1)),
    )
    .await;
    assert_error(&r, StatusCode::FORBIDDEN, "quota: this owner has 2 scenes");
    // Another token has its own quota.
    let r = call(
        &f.app,
        "POST",
        "/api/scenes",
        Some("beta"),
        ip,
        Some(&scene("c", &f.model, 1)),
    )
    .await;
    assert_eq!(r.status, StatusCode::CREATED, "{}", r.json);
    let w = r.json["write_token"].as_str().expect("write").to_string();
    // Instances per scene, through edits.
    let adds: Vec<Value> = (0..5)
        .map(|_| json!({"model": f.model, "position": [1.0, 0.0, 1.0]}))
        .collect();
    let r = call(
        &f.app,
        "POST",
        "/api/scenes/c/instances",
        Some(&w),
        ip,
        Some(&json!({"add": adds})),
    )
    .await;
    assert_error(&r, StatusCode::FORBIDDEN, "at most 5 instances");
    let r = call(&f.app, "GET", "/api/scenes/c", Some(&w), ip, None).await;
    assert_eq!(
        (r.json["version"].as_u64(), r.json["instance_count"].as_u64()),
        (Some(1), Some(1))
    );
    // Deleting frees a place in the quota.
    assert_eq!(
        call(&f.app, "DELETE", "/api/scenes/c", Some(&w), ip, None).await.status,
        StatusCode::NO_CONTENT
    );
    let r = call(
        &f.app,
        "POST",
        "/api/scenes",
        Some("beta"),
        ip,
        Some(&scene("c", &f.model, 1)),
    )
    .await;
    assert_eq!(r.status, StatusCode::CREATED, "{}", r.json);
}

#[tokio::test]
async fn creations_and_edits_are_rate_limited_per_key_and_address() {
    let f = fixture(
        "rates",
        HttpConfig {
            create_rate: Rate {
                per_s: 1.0 / 60.0,
                burst: 3.0,
            },
            edit_rate: Rate { per_s: 0.5, burst: 4.0 },
            ..HttpConfig::default()
        },
    );
    // Open mode: the owner is the address.
    for k in 0..3 {
        let r = call(
            &f.app,
            "POST",
            "/api/scenes",
            None,
            "10.0.0.1",
            Some(&scene(&format!("s{k}"), &f.model, 1)),
        )
        .await;
        assert_eq!(r.status, StatusCode::CREATED, "{}", r.json);
    }
    let r = call(
        &f.app,
        "POST",
        "/api/scenes",
        None,
        "10.0.0.1",
        Some(&scene("s3", &f.model, 1)),
    )
    .await;
    assert_error(&r, StatusCode::TOO_MANY_REQUESTS, "too many scene creations");
    assert!(matches!(r.retry_after, Some(59..=60)), "{:?}", r.retry_after);
    assert_eq!(
        call(&f.app, "GET", "/api/scenes/s3", None, "10.0.0.1", None)
            .await
            .status,
        StatusCode::NOT_FOUND
    );
    // Another address is not limited by the first one's creations; another host in the same
    // IPv6 /64 is the same address.
    let r = call(
        &f.app,
        "POST",
        "/api/scenes",
        None,
        "10.0.0.2",
        Some(&scene("s3", &f.model, 1)),
    )
    .await;
    assert_eq!(r.status, StatusCode::CREATED, "{}", r.json);
    let w = r.json["write_token"].as_str().expect("write").to_string();
    for k in 0..3 {
        let r = call(
            &f.app,
            "POST",
            "/api/scenes",
            None,
            &format!("2001:db8::{k}"),
            Some(&scene(&format!("v{k}"), &f.model, 1)),
        )
        .await;
        assert_eq!(r.status, StatusCode::CREATED, "{}", r.json);
    }
    let r = call(
        &f.app,
        "POST",
        "/api/scenes",
        None,
        "2001:db8::ffff",
        Some(&scene("v3", &f.model, 1)),
    )
    .await;
    assert_eq!(r.status, StatusCode::TOO_MANY_REQUESTS);
    // Edits: four at once, then refused with Retry-After; a request without the token spends
    // nothing of the scene's.
    let add = json!({"add": [{"model": f.model, "position": [2.0, 0.0, 2.0]}]});
    for _ in 0..6 {
        let r = call(
            &f.app,
            "POST",
            "/api/scenes/s3/instances",
            Some("wrong"),
            "10.9.9.9",
            Some(&add),
        )
        .await;
        assert_eq!(r.status, StatusCode::FORBIDDEN);
    }
    for k in 0..4 {
        let r = call(
            &f.app,
            "POST",
            "/api/scenes/s3/instances",
            Some(&w),
            &format!("10.1.0.{k}"),
            Some(&add),
        )
        .await;
        assert_eq!(r.status, StatusCode::OK, "{}", r.json);
    }
    let r = call(
        &f.app,
        "POST",
        "/api/scenes/s3/instances",
        Some(&w),
        "10.1.0.9",
        Some(&add),
    )
    .await;
    assert_error(&r, StatusCode::TOO_MANY_REQUESTS, "too many edits");
    assert!(matches!(r.retry_after, Some(1..=2)), "{:?}", r.retry_after);
    let r = call(&f.app, "GET", "/api/scenes/s3", Some(&w), "10.0.0.2", None).await;
    assert_eq!(r.json["version"].as_u64(), Some(5));
}

#[tokio::test]
async fn old_versions_are_pruned_with_their_files_and_pins_keep_them() {
    let f = fixture(
        "retention",
        HttpConfig {
            limits: Limits {
                keep_versions: 2,
                max_pins: 1,
                ..Limits::default()
            },
            ..HttpConfig::default()
        },
    );
    let ip = "10.0.0.1";
    let r = call(&f.app, "POST", "/api/scenes", None, ip, Some(&scene("g", &f.model, 3))).await;
    assert_eq!(r.status, StatusCode::CREATED, "{}", r.json);
    let w = r.json["write_token"].as_str().expect("write").to_string();
    let r = call(&f.app, "POST", "/api/scenes/g/pins", Some(&w), ip, None).await;
    assert_eq!((r.status, r.json["pinned"].clone()), (StatusCode::OK, json!([1])));
    for k in 0..6 {
        let mv = json!({"move": [{"id": 1, "position": [k as f32, 0.0, 3.0]}]});
        let r = call(&f.app, "POST", "/api/scenes/g/instances", Some(&w), ip, Some(&mv)).await;
        assert_eq!(r.status, StatusCode::OK, "{}", r.json);
    }
    let r = call(&f.app, "GET", "/api/scenes/g/versions", Some(&w), ip, None).await;
    let kept: Vec<u64> = r.json["versions"]
        .as_array()
        .expect("versions")
        .iter()
        .map(|v| v["version"].as_u64().expect("n"))
        .collect();
    assert_eq!(kept, vec![1, 6, 7]);
    // Pruned files are deleted once the answer is sent: wait for that (bounded).
    let ls = || -> Vec<String> {
        std::fs::read_dir(f.dir.join("scenes/g"))
            .expect("ls")
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect()
    };
    let t0 = std::time::Instant::now();
    while ls().len() > 8 && t0.elapsed() < std::time::Duration::from_secs(10) {
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    let files = ls();
    // Per kept version a pack index (the first version's pack and manifest also whole: later
    // manifests live in their version rows), and the tile blobs their indexes name: here one
    // tile per version, each move changing it.
    let (tiles, rest): (Vec<&String>, Vec<&String>) = files
        .iter()
        .partition(|n| std::path::Path::new(n).extension().is_some_and(|e| e == "ctile"));
    assert_eq!((rest.len(), tiles.len()), (5, 3), "{files:?}");
    for v in [1, 6, 7] {
        assert!(files.iter().any(|n| n.starts_with(&format!("v{v}."))), "{files:?}");
    }
    let r = call(&f.app, "GET", "/api/scenes/g/manifest?version=3", Some(&w), ip, None).await;
    assert_eq!(r.status, StatusCode::NOT_FOUND);
    let r = call(&f.app, "GET", "/api/scenes/g/manifest?version=1", Some(&w), ip, None).await;
    assert_eq!(r.status, StatusCode::OK);
    // A first version's manifest has a static copy; a later one is named by the API's URL.
    let copy = r.location.expect("content-location");
    let name = copy.rsplit('/').next().expect("file");
    assert!(
        copy.starts_with("/assets/scenes/g/v1.") && files.iter().any(|n| n == name),
        "{copy}"
    );
    let r = call(&f.app, "GET", "/api/scenes/g/manifest?version=7", Some(&w), ip, None).await;
    assert_eq!(r.location.as_deref(), Some("/api/scenes/g/manifest?version=7"));
    assert!(
        !files
            .iter()
            .any(|n| n.starts_with("v7.") && std::path::Path::new(n).extension().is_some_and(|e| e == "json")),
        "{files:?}"
    );
    // Pins are bounded, need the write token, name kept versions.
    assert_error(
        &call(
            &f.app,
            "POST",
            "/api/scenes/g/pins",
            Some(&w),
            ip,
            Some(&json!({"version": 7})),
        )
        .await,
        StatusCode::FORBIDDEN,
        "pinned versions",
    );
    assert_error(
        &call(
            &f.app,
            "POST",
            "/api/scenes/g/pins",
            Some(&w),
            ip,
            Some(&json!({"version": 3})),
        )
        .await,
        StatusCode::NOT_FOUND,
        "no version 3",
    );
    assert_eq!(
        call(&f.app, "POST", "/api/scenes/g/pins", None, ip, None).await.status,
        StatusCode::UNAUTHORIZED
    );
    assert_error(
        &call(&f.app, "DELETE", "/api/scenes/g/pins/x", Some(&w), ip, None).await,
        StatusCode::BAD_REQUEST,
        "positive integer",
    );
    let r = call(&f.app, "DELETE", "/api/scenes/g/pins/1", Some(&w), ip, None).await;
    assert_eq!((r.status, r.json["pinned"].clone()), (StatusCode::OK, json!([])));
    // Unpinned, version 1 goes with the next edit.
    let mv = json!({"move": [{"id": 2, "position": [9.0, 0.0, 9.0]}]});
    assert_eq!(
        call(&f.app, "POST", "/api/scenes/g/instances", Some(&w), ip, Some(&mv))
            .await
            .status,
        StatusCode::OK
    );
    let r = call(&f.app, "GET", "/api/scenes/g/versions", Some(&w), ip, None).await;
    assert_eq!(r.json["versions"].as_array().map(Vec::len), Some(2));
    let v1_left = || ls().iter().any(|n| n.starts_with("v1."));
    let t0 = std::time::Instant::now();
    while v1_left() && t0.elapsed() < std::time::Duration::from_secs(10) {
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    assert!(!v1_left());
}
