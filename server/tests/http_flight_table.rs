//! In-process tests of a scene's flight table through the API (`PUT`, `GET`, `DELETE
//! /api/scenes/{id}/flight-table`): the round trip of the normalised table, refusals that change
//! nothing, read access as the manifest's, the edit rate limit, and a database that is away.

use std::path::PathBuf;
use std::sync::Arc;

use axum::body::Body;
use axum::http::{HeaderMap, Request, StatusCode};
use canopy_server::demo::{bake_and_store, synthetic_model};
use canopy_server::http::quota::Rate;
use canopy_server::http::{AppState, HttpConfig, router};
use canopy_server::store::{AssetStore, PostgresStore, SceneStore, SqliteStore};
use canopy_shared::flight_table::{FlightTable, MAX_TABLE_BYTES};
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

fn temp_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("canopy-http-flight-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn fixture_with(name: &str, config: HttpConfig) -> Fixture {
    let dir = temp_dir(name);
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

fn fixture(name: &str) -> Fixture {
    fixture_with(name, HttpConfig::default())
}

struct Reply {
    status: StatusCode,
    headers: HeaderMap,
    body: Vec<u8>,
}

impl Reply {
    fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap_or(Value::Null)
    }

    fn error(&self) -> String {
        self.json()["error"].as_str().unwrap_or_default().to_string()
    }

    fn header(&self, name: &str) -> Option<&str> {
        self.headers.get(name).and_then(|v| v.to_str().ok())
    }
}

/// A request with a bearer token (when given), extra headers, and a JSON body (when given;
/// `Content-Type: application/json` unless `headers` set one).
async fn send(
    app: &axum::Router,
    method: &str,
    uri: &str,
    token: Option<&str>,
    headers: &[(&str, &str)],
    body: Option<String>,
) -> Reply {
    let mut req = Request::builder().method(method).uri(uri);
    if let Some(t) = token {
        req = req.header("authorization", format!("Bearer {t}"));
    }
    if body.is_some() && !headers.iter().any(|(k, _)| k.eq_ignore_ascii_case("content-type")) {
        req = req.header("content-type", "application/json");
    }
    for (k, v) in headers {
        req = req.header(*k, *v);
    }
    let req = req.body(body.map_or_else(Body::empty, Body::from)).expect("request");
    let resp = app.clone().oneshot(req).await.expect("infallible");
    let (parts, body) = resp.into_parts();
    let body = axum::body::to_bytes(body, usize::MAX).await.expect("body").to_vec();
    Reply {
        status: parts.status,
        headers: parts.headers,
        body,
    }
}

/// Creates scene `grove`; returns its write token and (private scenes) read token.
async fn create(f: &Fixture, public: bool) -> (String, Option<String>) {
    let body = json!({
        "name": "Grove", "id": "grove", "public": public,
        "bounds": {"min": [-100.0, -100.0], "max": [100.0, 100.0]},
        "instances": [{"model": f.model, "position": [0.0, 0.0, 0.0]}]
    });
    let r = send(&f.app, "POST", "/api/scenes", None, &[], Some(body.to_string())).await;
    assert_eq!(r.status, StatusCode::CREATED, "{}", r.json());
    let v = r.json();
    (
        v["write_token"].as_str().expect("write token").to_string(),
        v["read_token"].as_str().map(String::from),
    )
}

/// A valid table as `canopy redundancy` might send it (not in the stored form: indented, steps
/// as integers); `top` is its last cell.
fn table(top: u8) -> Value {
    json!({
        "format": "canopy-flight-table", "format_version": 1, "dh_m": 20, "dv_mps": 10,
        "offsets": [[0, 0, 1], [0, 1, top]],
        "policy": {"sigma_m": [100, 250, 500, 1000], "field_deg": 120, "threat_time_s": 2},
        "method": {"metric": "ssim", "threshold": 0.95, "width": 480, "height": 270, "fps": 30,
                   "viewpoints": 2, "ladder": "geometry:150,hemioct:0"}
    })
}

fn pretty(v: &Value) -> String {
    serde_json::to_string_pretty(v).expect("json")
}

/// What the server stores and serves for `v`.
fn normalised(v: &Value) -> Vec<u8> {
    FlightTable::parse(v.to_string().as_bytes())
        .expect("valid")
        .to_json()
        .expect("json")
        .into_bytes()
}

const PATH: &str = "/api/scenes/grove/flight-table";

#[tokio::test]
async fn a_table_put_is_served_back_normalised_until_deleted() {
    let f = fixture("round-trip");
    let (write, _) = create(&f, true).await;
    let r = send(&f.app, "GET", PATH, None, &[], None).await;
    assert_eq!(r.status, StatusCode::NOT_FOUND);
    assert!(r.error().contains("has no flight table"), "{}", r.error());

    let r = send(&f.app, "PUT", PATH, Some(&write), &[], Some(pretty(&table(2)))).await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    assert_eq!(
        r.body,
        normalised(&table(2)),
        "the stored text is the table's compact JSON"
    );
    assert_eq!(r.header("content-type"), Some("application/json"));
    let r = send(&f.app, "GET", PATH, None, &[], None).await;
    assert_eq!(r.status, StatusCode::OK);
    assert_eq!(r.body, normalised(&table(2)), "exactly what was stored");
    assert_eq!(r.header("content-type"), Some("application/json"));
    assert_eq!(r.header("cache-control"), Some("no-cache"));
    let etag = r.header("etag").expect("etag").to_string();
    let r = send(&f.app, "GET", PATH, None, &[("if-none-match", &etag)], None).await;
    assert_eq!(r.status, StatusCode::NOT_MODIFIED);
    assert!(r.body.is_empty());

    // Replaced, and the scene is not versioned by it.
    let r = send(&f.app, "PUT", PATH, Some(&write), &[], Some(table(3).to_string())).await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    let r = send(&f.app, "GET", PATH, None, &[("if-none-match", &etag)], None).await;
    assert_eq!((r.status, r.body), (StatusCode::OK, normalised(&table(3))));
    let r = send(&f.app, "GET", "/api/scenes/grove", None, &[], None).await;
    assert_eq!(r.json()["version"], 1, "setting the table makes no version");

    // Deleted: 204, then 404; deleting none is 204 too.
    for _ in 0..2 {
        let r = send(&f.app, "DELETE", PATH, Some(&write), &[], None).await;
        assert_eq!(r.status, StatusCode::NO_CONTENT);
        let r = send(&f.app, "GET", PATH, None, &[], None).await;
        assert_eq!(r.status, StatusCode::NOT_FOUND);
        assert!(r.error().contains("has no flight table"), "{}", r.error());
    }

    // An unknown scene is a different 404.
    for (method, body) in [("GET", None), ("PUT", Some(table(1).to_string())), ("DELETE", None)] {
        let r = send(&f.app, method, "/api/scenes/nope/flight-table", Some(&write), &[], body).await;
        assert_eq!(r.status, StatusCode::NOT_FOUND, "{method}");
        assert!(
            r.error().contains("not found") && !r.error().contains("flight table"),
            "{method}: {}",
            r.error()
        );
    }

    // Gone with the scene: the same id made again has none.
    let r = send(&f.app, "PUT", PATH, Some(&write), &[], Some(table(1).to_string())).await;
    assert_eq!(r.status, StatusCode::OK);
    let r = send(&f.app, "DELETE", "/api/scenes/grove", Some(&write), &[], None).await;
    assert_eq!(r.status, StatusCode::NO_CONTENT);
    let r = send(&f.app, "GET", PATH, None, &[], None).await;
    assert!(
        r.status == StatusCode::NOT_FOUND && r.error().contains("not found"),
        "{}",
        r.error()
    );
    create(&f, true).await;
    let r = send(&f.app, "GET", PATH, None, &[], None).await;
    assert_eq!(r.status, StatusCode::NOT_FOUND);
    assert!(r.error().contains("has no flight table"), "{}", r.error());
}

#[tokio::test]
async fn refused_tables_and_tokens_change_nothing() {
    let f = fixture("refused");
    let (write, read) = create(&f, false).await;
    let read = read.expect("a private scene's read token");
    let r = send(&f.app, "PUT", PATH, Some(&write), &[], Some(table(2).to_string())).await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    let stored = normalised(&table(2));

    let edit = |f: fn(&mut Value)| {
        let mut t = table(4);
        f(&mut t);
        t.to_string()
    };
    let over = format!("{}{}", table(4), " ".repeat(MAX_TABLE_BYTES));
    let cases: Vec<(Option<&str>, &str, String, StatusCode, &str)> = vec![
        (
            None,
            "application/json",
            table(4).to_string(),
            StatusCode::UNAUTHORIZED,
            "write token",
        ),
        (
            Some("wrong"),
            "application/json",
            table(4).to_string(),
            StatusCode::FORBIDDEN,
            "write token",
        ),
        (
            Some(&read),
            "application/json",
            table(4).to_string(),
            StatusCode::FORBIDDEN,
            "write token",
        ),
        (
            Some(&write),
            "text/plain",
            table(4).to_string(),
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "application/json",
        ),
        (
            Some(&write),
            "application/json",
            "{not json".into(),
            StatusCode::BAD_REQUEST,
            "not valid JSON",
        ),
        (
            Some(&write),
            "application/json",
            String::new(),
            StatusCode::BAD_REQUEST,
            "not valid JSON",
        ),
        (
            Some(&write),
            "application/json",
            edit(|t| t["colour"] = "red".into()),
            StatusCode::BAD_REQUEST,
            "unknown field",
        ),
        (
            Some(&write),
            "application/json",
            edit(|t| t["offsets"] = json!([[0, 0, 1], [0, 1]])),
            StatusCode::BAD_REQUEST,
            "row 1 has 2 speed bands",
        ),
        (
            Some(&write),
            "application/json",
            edit(|t| t["offsets"][0][0] = 5.into()),
            StatusCode::BAD_REQUEST,
            "past the policy's 4 levels",
        ),
        (
            Some(&write),
            "application/json",
            edit(|t| t["dh_m"] = 0.into()),
            StatusCode::BAD_REQUEST,
            "must be finite and positive",
        ),
        (
            Some(&write),
            "application/json",
            edit(|t| t["format_version"] = 2.into()),
            StatusCode::BAD_REQUEST,
            "version 2",
        ),
        (
            Some(&write),
            "application/json",
            over,
            StatusCode::PAYLOAD_TOO_LARGE,
            "over",
        ),
    ];
    for (token, ctype, body, want, msg) in cases {
        let r = send(&f.app, "PUT", PATH, token, &[("content-type", ctype)], Some(body)).await;
        assert_eq!(r.status, want, "{msg}: {}", r.error());
        assert!(r.error().contains(msg), "expected {msg:?} in {:?}", r.error());
        let r = send(&f.app, "GET", PATH, Some(&read), &[], None).await;
        assert_eq!(
            (r.status, &r.body),
            (StatusCode::OK, &stored),
            "after a refused PUT ({msg})"
        );
    }
    let r = send(&f.app, "PUT", PATH, None, &[], Some(table(4).to_string())).await;
    assert_eq!(r.header("www-authenticate"), Some("Bearer"));

    for (token, want) in [
        (None, StatusCode::UNAUTHORIZED),
        (Some("wrong"), StatusCode::FORBIDDEN),
        (Some(read.as_str()), StatusCode::FORBIDDEN),
    ] {
        let r = send(&f.app, "DELETE", PATH, token, &[], None).await;
        assert_eq!(r.status, want, "{token:?}");
    }
    let r = send(&f.app, "GET", PATH, Some(&write), &[], None).await;
    assert_eq!((r.status, r.body), (StatusCode::OK, stored), "still there");
}

#[tokio::test]
async fn a_private_scenes_table_is_read_as_its_manifest_is() {
    let f = fixture("private");
    let (write, read) = create(&f, false).await;
    let read = read.expect("read token");
    let r = send(&f.app, "PUT", PATH, Some(&write), &[], Some(table(1).to_string())).await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    let read_q = format!("?token={read}");
    let cases = [
        (None, "", StatusCode::UNAUTHORIZED),
        (Some("wrong"), "", StatusCode::FORBIDDEN),
        (Some(read.as_str()), "", StatusCode::OK),
        (Some(write.as_str()), "", StatusCode::OK),
        (None, read_q.as_str(), StatusCode::OK),
    ];
    for (token, query, want) in cases {
        let manifest = send(
            &f.app,
            "GET",
            &format!("/api/scenes/grove/manifest{query}"),
            token,
            &[],
            None,
        )
        .await;
        let table = send(&f.app, "GET", &format!("{PATH}{query}"), token, &[], None).await;
        assert_eq!(manifest.status, want, "manifest with {token:?} {query}");
        assert_eq!(table.status, want, "table with {token:?} {query}");
        if want != StatusCode::OK {
            assert_eq!(table.error(), manifest.error());
        }
    }
}

#[tokio::test]
async fn table_changes_spend_the_scenes_edits() {
    let config = HttpConfig {
        edit_rate: Rate {
            per_s: 0.001,
            burst: 2.0,
        },
        ..HttpConfig::default()
    };
    let f = fixture_with("rate", config);
    let (write, _) = create(&f, true).await;
    let r = send(&f.app, "PUT", PATH, Some(&write), &[], Some(table(1).to_string())).await;
    assert_eq!(r.status, StatusCode::OK, "{}", r.error());
    let r = send(&f.app, "DELETE", PATH, Some(&write), &[], None).await;
    assert_eq!(r.status, StatusCode::NO_CONTENT);
    let r = send(&f.app, "PUT", PATH, Some(&write), &[], Some(table(2).to_string())).await;
    assert_eq!(r.status, StatusCode::TOO_MANY_REQUESTS, "{}", r.error());
    assert!(r.header("retry-after").is_some());
    let batch = json!({"add": [{"model": f.model, "position": [1.0, 0.0, 1.0]}]}).to_string();
    let r = send(
        &f.app,
        "POST",
        "/api/scenes/grove/instances",
        Some(&write),
        &[],
        Some(batch),
    )
    .await;
    assert_eq!(
        r.status,
        StatusCode::TOO_MANY_REQUESTS,
        "the same bucket as instance edits"
    );
    // Reads are not edits.
    let r = send(&f.app, "GET", PATH, None, &[], None).await;
    assert_eq!(r.status, StatusCode::NOT_FOUND);
}

/// Not a `tokio::test`: the PostgreSQL driver (blocking) opens outside any runtime, as `serve`
/// does.
#[test]
fn a_database_that_is_away_answers_503_with_retry_after() {
    // A port nothing listens on (bound, then closed).
    let port = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("port")
        .port();
    let scenes = PostgresStore::open(&format!("postgres://canopy@127.0.0.1:{port}/canopy")).expect("starts");
    assert!(!scenes.available());
    let dir = temp_dir("away");
    let assets = Arc::new(AssetStore::open(&dir).expect("asset store"));
    let (state, _stop) = AppState::new(assets, Arc::new(scenes), HttpConfig::default());
    let app = router(state);
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    for (method, body) in [("GET", None), ("PUT", Some(table(1).to_string())), ("DELETE", None)] {
        let r = rt.block_on(send(&app, method, PATH, Some("token"), &[], body));
        assert_eq!(r.status, StatusCode::SERVICE_UNAVAILABLE, "{method}: {}", r.error());
        assert_eq!(r.header("retry-after"), Some("1"), "{method}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
