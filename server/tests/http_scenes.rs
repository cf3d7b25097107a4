//! In-process tests of the scene API: create, list, get, edit in batches, versions, delete, bad
//! input (which must change nothing) and token checks.

use std::path::PathBuf;
use std::sync::Arc;

use axum::body::Body;
use axum::http::{Request, StatusCode};
use canopy_server::demo::{bake_and_store, synthetic_model};
use canopy_server::http::{AppState, HttpConfig, router};
use canopy_server::store::pack;
use canopy_server::store::{AssetStore, SqliteStore};
use serde_json::{Value, json};
use tower::ServiceExt;

struct Fixture {
    app: axum::Router,
    dir: PathBuf,
    models: Vec<String>,
}

impl Drop for Fixture {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

fn fixture(name: &str) -> Fixture {
    let dir = std::env::temp_dir().join(format!("canopy-http-scenes-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let assets = Arc::new(AssetStore::open(&dir).expect("asset store"));
    let scenes = Arc::new(SqliteStore::in_memory().expect("db"));
    let (state, _stop) = AppState::new(assets, scenes, HttpConfig::default());
    let models = (0..2)
        .map(|k| bake_and_store(&state, &synthetic_model(k)).expect("bake"))
        .collect();
    Fixture {
        app: router(state),
        dir,
        models,
    }
}

async fn call(
    app: &axum::Router,
    method: &str,
    uri: &str,
    token: Option<&str>,
    body: Option<&str>,
) -> (StatusCode, Value, Vec<u8>) {
    let mut req = Request::builder().method(method).uri(uri);
    if let Some(t) = token {
        req = req.header("authorization", format!("Bearer {t}"));
    }
    if body.is_some() {
        req = req.header("content-type", "application/json");
    }
    let req = req
        .body(body.map_or_else(Body::empty, |b| Body::from(b.to_string())))
        .expect("request");
    let resp = app.clone().oneshot(req).await.expect("infallible");
    let status = resp.status();
    let bytes = axum::body::to_bytes(resp.into_body(), usize::MAX)
        .await
        .expect("body")
        .to_vec();
    let json = serde_json::from_slice(&bytes).unwrap_or(Value::Null);
    (status, json, bytes)
}

fn scene_body(models: &[String], public: bool) -> String {
    json!({
        "name": "Grove",
        "id": "grove",
        "public": public,
        "bounds": {"min": [-100.0, -100.0], "max": [100.0, 100.0]},
        "instances": [
            {"model": models[0], "position": [0.0, 0.0, 0.0], "rotation": 1.0, "scale": 1.2},
            {"model": models[1], "position": [50.0, 0.0, -50.0]},
            {"model": models[0], "position": [-90.0, 2.0, 90.0]}
        ]
    })
    .to_string()
}

#[tokio::test]
async fn create_list_get_edit_and_delete() {
    let f = fixture("crud");
    let (s, v, _) = call(&f.app, "POST", "/api/scenes", None, Some(&scene_body(&f.models, true))).await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let token = v["write_token"].as_str().expect("write token").to_string();
    assert!(v.get("read_token").is_none());
    assert_eq!(v["version"], 1);
    assert_eq!(v["instance_count"], 3);
    let (s, v, _) = call(&f.app, "GET", "/api/scenes", None, None).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(v["scenes"][0]["id"], "grove");
    let (s, v, _) = call(&f.app, "GET", "/api/scenes/grove", None, None).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(v["name"], "Grove");

    // The manifest names every asset by URL; the pack is served and decodes to the instances.
    let (s, m1, _) = call(&f.app, "GET", "/api/scenes/grove/manifest", None, None).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(m1["version"], 1);
    assert_eq!(m1["models"].as_array().map(Vec::len), Some(2));
    for m in m1["models"].as_array().expect("models") {
        let url = m["url"].as_str().expect("url");
        assert!(url.starts_with("/assets/trees/"));
        let (s, _, bytes) = call(&f.app, "GET", url, None, None).await;
        assert_eq!(s, StatusCode::OK);
        assert_eq!(bytes.len() as u64, m["size"].as_u64().expect("size"));
    }
    let pack_url = m1["pack"]["url"].as_str().expect("pack url").to_string();
    let (s, _, bytes) = call(&f.app, "GET", &pack_url, None, None).await;
    assert_eq!(s, StatusCode::OK);
    let p = pack::decode(&bytes).expect("pack decodes");
    assert_eq!(p.instances.len(), 3);
    assert_eq!(p.models.len(), 2);
    assert_eq!(m1["tiles"].as_array().map(Vec::len), Some(p.tiles.len()));

    // One batch: add, move, remove -> version 2.
    let batch = json!({
        "add": [{"model": f.models[1], "position": [10.0, 0.0, 10.0]}],
        "move": [{"id": 1, "position": [5.0, 0.0, 5.0], "rotation": 2.0}],
        "remove": [2],
        "base_version": 1
    })
    .to_string();
    let (s, v, _) = call(
        &f.app,
        "POST",
        "/api/scenes/grove/instances",
        Some(&token),
        Some(&batch),
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(v["version"], 2);
    assert_eq!(v["added_ids"], json!([4]));
    let (_, v, _) = call(&f.app, "GET", "/api/scenes/grove/instances", None, None).await;
    let ids: Vec<u64> = v["instances"]
        .as_array()
        .expect("list")
        .iter()
        .filter_map(|i| i["id"].as_u64())
        .collect();
    assert_eq!(ids, vec![1, 3, 4]);
    assert_eq!(v["instances"][0]["position"], json!([5.0, 0.0, 5.0]));
    assert_eq!(v["instances"][0]["rotation"], json!(2.0));

    // The old version is untouched: its manifest and pack are still served.
    let (s, old, _) = call(&f.app, "GET", "/api/scenes/grove/manifest?version=1", None, None).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(old, m1);
    let (s, _, old_bytes) = call(&f.app, "GET", &pack_url, None, None).await;
    assert_eq!(s, StatusCode::OK);
    assert!(old_bytes == bytes);
    let (_, m2, _) = call(&f.app, "GET", "/api/scenes/grove/manifest", None, None).await;
    assert_eq!(m2["version"], 2);
    assert_ne!(m2["pack"]["url"], m1["pack"]["url"]);
    let (s, _, _) = call(&f.app, "GET", "/api/scenes/grove/manifest?version=9", None, None).await;
    assert_eq!(s, StatusCode::NOT_FOUND);

    // Delete needs the token; afterwards the scene is gone.
    let (s, _, _) = call(&f.app, "DELETE", "/api/scenes/grove", None, None).await;
    assert_eq!(s, StatusCode::UNAUTHORIZED);
    let (s, _, _) = call(&f.app, "DELETE", "/api/scenes/grove", Some(&token), None).await;
    assert_eq!(s, StatusCode::NO_CONTENT);
    let (s, _, _) = call(&f.app, "GET", "/api/scenes/grove", None, None).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
    let (s, _, _) = call(&f.app, "GET", &pack_url, None, None).await;
    assert_eq!(s, StatusCode::NOT_FOUND);
}

#[tokio::test]
async fn bad_input_gets_4xx_and_changes_nothing() {
    let f = fixture("bad");
    let (s, v, _) = call(&f.app, "POST", "/api/scenes", None, Some(&scene_body(&f.models, true))).await;
    assert_eq!(s, StatusCode::CREATED);
    let token = v["write_token"].as_str().expect("token").to_string();
    let m = &f.models[0];
    let big: Vec<Value> = (0..10_001)
        .map(|_| json!({"model": m, "position": [0.0, 0.0, 0.0]}))
        .collect();
    let cases: Vec<(String, StatusCode, &str)> = vec![
        ("{not json".into(), StatusCode::BAD_REQUEST, "invalid JSON"),
        (
            json!({"add": [{"model": m, "position": [1000.0, 0.0, 0.0]}]}).to_string(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "outside the scene bounds",
        ),
        (
            json!({"add": [{"model": "nope", "position": [0.0, 0.0, 0.0]}]}).to_string(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "unknown model",
        ),
        (
            json!({"add": [{"model": m, "position": [0.0, 0.0, 0.0], "scale": -1.0}]}).to_string(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "scale",
        ),
        (
            "{\"add\": [{\"model\": \"x\", \"position\": [NaN, 0, 0]}]}".into(),
            StatusCode::BAD_REQUEST,
            "invalid JSON",
        ),
        // Overflows f32: becomes infinite, which is refused.
        (
            json!({"add": [{"model": m, "position": [1e39, 0.0, 0.0]}]}).to_string(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "finite",
        ),
        (
            json!({"add": big}).to_string(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "exceeds the limit",
        ),
        (
            json!({"remove": [99]}).to_string(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "does not exist",
        ),
        (
            json!({"remove": [1, 1]}).to_string(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "more than once",
        ),
        (
            json!({"move": [{"id": 1, "position": [0.0, 0.0, 500.0]}]}).to_string(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "outside",
        ),
        (json!({}).to_string(), StatusCode::UNPROCESSABLE_ENTITY, "empty batch"),
        (
            json!({"remove": [1], "base_version": 7}).to_string(),
            StatusCode::CONFLICT,
            "version",
        ),
        (
            json!({"remove": [1], "colour": "red"}).to_string(),
            StatusCode::BAD_REQUEST,
            "unknown field",
        ),
        // Valid adds followed by one bad one: the whole batch is refused.
        (
            json!({"add": [{"model": m, "position": [0.0, 0.0, 0.0]}, {"model": m, "position": [0.0, 0.0, f32::MAX]}]})
                .to_string(),
            StatusCode::UNPROCESSABLE_ENTITY,
            "outside",
        ),
    ];
    for (body, want, msg) in &cases {
        let (s, v, _) = call(&f.app, "POST", "/api/scenes/grove/instances", Some(&token), Some(body)).await;
        assert_eq!(s, *want, "{msg}: {v}");
        let err = v["error"].as_str().unwrap_or_default();
        assert!(err.contains(msg), "expected {msg:?} in {err:?}");
    }
    let (_, v, _) = call(&f.app, "GET", "/api/scenes/grove", None, None).await;
    assert_eq!(v["version"], 1, "nothing changed");
    assert_eq!(v["instance_count"], 3);

    // Bad scene creations.
    let bad_scenes = [
        json!({"name": "x", "bounds": {"min": [0.0, 0.0], "max": [0.0, 10.0]}}),
        json!({"name": "", "bounds": {"min": [0.0, 0.0], "max": [10.0, 10.0]}}),
        json!({"name": "x", "id": "Bad Id!", "bounds": {"min": [0.0, 0.0], "max": [10.0, 10.0]}}),
        json!({"name": "x", "id": "grove", "bounds": {"min": [0.0, 0.0], "max": [10.0, 10.0]}}),
        json!({"name": "x", "bounds": {"min": [0.0, 0.0], "max": [10.0, 10.0]}, "instances": [{"model": m, "position": [20.0, 0.0, 0.0]}]}),
        json!({"name": "x"}),
    ];
    for b in &bad_scenes {
        let (s, v, _) = call(&f.app, "POST", "/api/scenes", None, Some(&b.to_string())).await;
        assert!(s.is_client_error(), "{b} -> {s} {v}");
        assert!(v["error"].as_str().is_some_and(|e| !e.is_empty()), "{v}");
    }
    let (_, v, _) = call(&f.app, "GET", "/api/scenes", None, None).await;
    assert_eq!(v["scenes"].as_array().map(Vec::len), Some(1));
}

#[tokio::test]
async fn tokens_guard_writes_and_private_reads() {
    let f = fixture("tokens");
    let (s, v, _) = call(&f.app, "POST", "/api/scenes", None, Some(&scene_body(&f.models, false))).await;
    assert_eq!(s, StatusCode::CREATED);
    let write = v["write_token"].as_str().expect("write").to_string();
    let read = v["read_token"]
        .as_str()
        .expect("private scenes get a read token")
        .to_string();
    let (_, v, _) = call(&f.app, "GET", "/api/scenes", None, None).await;
    assert_eq!(
        v["scenes"].as_array().map(Vec::len),
        Some(0),
        "private scenes are not listed"
    );
    for path in [
        "/api/scenes/grove",
        "/api/scenes/grove/manifest",
        "/api/scenes/grove/instances",
    ] {
        let (s, _, _) = call(&f.app, "GET", path, None, None).await;
        assert_eq!(s, StatusCode::UNAUTHORIZED, "{path}");
        let (s, _, _) = call(&f.app, "GET", path, Some("wrong"), None).await;
        assert_eq!(s, StatusCode::FORBIDDEN, "{path}");
        for t in [&read, &write] {
            let (s, _, _) = call(&f.app, "GET", path, Some(t), None).await;
            assert_eq!(s, StatusCode::OK, "{path}");
        }
    }
    let (s, _, _) = call(&f.app, "GET", &format!("/api/scenes/grove?token={read}"), None, None).await;
    assert_eq!(s, StatusCode::OK);
    let batch = json!({"remove": [1]}).to_string();
    let (s, _, _) = call(&f.app, "POST", "/api/scenes/grove/instances", None, Some(&batch)).await;
    assert_eq!(s, StatusCode::UNAUTHORIZED);
    let (s, _, _) = call(&f.app, "POST", "/api/scenes/grove/instances", Some(&read), Some(&batch)).await;
    assert_eq!(s, StatusCode::FORBIDDEN, "a read token cannot write");
    // The write token with its last character changed (to '1' when it already ends in '0': a
    // fixed '0' made this test pass the real token 1 time in 16).
    let last = if write.ends_with('0') { '1' } else { '0' };
    let almost = format!("{}{last}", &write[..write.len() - 1]);
    assert_ne!(almost, write);
    let (s, _, _) = call(
        &f.app,
        "POST",
        "/api/scenes/grove/instances",
        Some(&almost),
        Some(&batch),
    )
    .await;
    assert_eq!(s, StatusCode::FORBIDDEN);
    let (s, v, _) = call(
        &f.app,
        "POST",
        "/api/scenes/grove/instances",
        Some(&write),
        Some(&batch),
    )
    .await;
    assert_eq!(s, StatusCode::OK, "{v}");
    assert_eq!(v["version"], 2);
}

/// `GET` with headers; returns the status, the response headers and the body.
async fn get_with(
    app: &axum::Router,
    uri: &str,
    headers: &[(&str, &str)],
) -> (StatusCode, axum::http::HeaderMap, Vec<u8>) {
    let mut req = Request::builder().method("GET").uri(uri);
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
    (parts.status, parts.headers, bytes)
}

#[tokio::test]
async fn manifest_etag_and_if_none_match() {
    let f = fixture("manifest-etag");
    let (s, v, _) = call(&f.app, "POST", "/api/scenes", None, Some(&scene_body(&f.models, true))).await;
    assert_eq!(s, StatusCode::CREATED);
    let token = v["write_token"].as_str().expect("write token").to_string();
    let current = "/api/scenes/grove/manifest";
    let (s, h, body) = get_with(&f.app, current, &[]).await;
    assert_eq!(s, StatusCode::OK);
    let etag = h["etag"].to_str().expect("etag").to_string();
    assert!(
        etag.starts_with('"') && etag.ends_with('"') && etag.len() == 66,
        "{etag}"
    );
    assert_eq!(
        h["cache-control"], "no-cache",
        "the current manifest changes with edits"
    );

    // A matching tag (strong, weak or in a list) gives 304 with no body; another gives the body.
    for inm in [
        etag.clone(),
        format!("W/{etag}"),
        format!("\"x\", {etag}"),
        "*".to_string(),
    ] {
        let (s, h, b) = get_with(&f.app, current, &[("if-none-match", &inm)]).await;
        assert_eq!(s, StatusCode::NOT_MODIFIED, "{inm}");
        assert!(b.is_empty());
        assert_eq!(h["etag"].to_str().ok(), Some(etag.as_str()));
    }
    let (s, _, b) = get_with(&f.app, current, &[("if-none-match", "\"other\"")]).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(b, body);

    // A pinned version is immutable; after an edit the current manifest's tag changes, the old
    // tag still validates the pinned version.
    let (s, h, _) = get_with(&f.app, &format!("{current}?version=1"), &[("if-none-match", &etag)]).await;
    assert_eq!(s, StatusCode::NOT_MODIFIED);
    assert!(h["cache-control"].to_str().expect("cc").contains("immutable"));
    let edit = json!({"add": [{"model": f.models[0], "position": [1.0, 0.0, 1.0]}]}).to_string();
    let (s, v, _) = call(&f.app, "POST", "/api/scenes/grove/instances", Some(&token), Some(&edit)).await;
    assert_eq!(s, StatusCode::OK, "{v}");
    let (s, h, _) = get_with(&f.app, current, &[("if-none-match", &etag)]).await;
    assert_eq!(s, StatusCode::OK, "the current manifest changed");
    assert_ne!(h["etag"].to_str().ok(), Some(etag.as_str()));
    let (s, h, _) = get_with(&f.app, &format!("{current}?version=1"), &[("if-none-match", &etag)]).await;
    assert_eq!(s, StatusCode::NOT_MODIFIED);
    assert_eq!(h["etag"].to_str().ok(), Some(etag.as_str()));
}

/// A request with the given `Content-Type` (none for `None`).
async fn call_typed(
    app: &axum::Router,
    uri: &str,
    token: Option<&str>,
    content_type: Option<&str>,
    body: &str,
) -> (StatusCode, Value, Option<String>) {
    let mut req = Request::builder().method("POST").uri(uri);
    if let Some(t) = token {
        req = req.header("authorization", format!("Bearer {t}"));
    }
    if let Some(ct) = content_type {
        req = req.header("content-type", ct);
    }
    let req = req.body(Body::from(body.to_string())).expect("request");
    let resp = app.clone().oneshot(req).await.expect("infallible");
    let status = resp.status();
    let ct = resp
        .headers()
        .get("content-type")
        .and_then(|v| v.to_str().ok())
        .map(String::from);
    let bytes = axum::body::to_bytes(resp.into_body(), usize::MAX).await.expect("body");
    (status, serde_json::from_slice(&bytes).unwrap_or(Value::Null), ct)
}

#[tokio::test]
async fn json_bodies_need_a_json_content_type() {
    let f = fixture("ctype");
    // What another site's HTML form can send without a preflight, and nothing at all.
    let forms = [
        Some("text/plain"),
        Some("text/plain; charset=utf-8"),
        Some("application/x-www-form-urlencoded"),
        Some("multipart/form-data; boundary=x"),
        Some("application/jsonx"),
        Some("text/json"),
        None,
    ];
    let body = scene_body(&f.models, true);
    for ct in forms {
        let (s, v, rct) = call_typed(&f.app, "/api/scenes", None, ct, &body).await;
        assert_eq!(s, StatusCode::UNSUPPORTED_MEDIA_TYPE, "{ct:?}: {v}");
        assert!(
            v["error"].as_str().is_some_and(|e| e.contains("application/json")),
            "{v}"
        );
        assert_eq!(rct.as_deref(), Some("application/json"));
    }
    let (s, _, _) = call(&f.app, "GET", "/api/scenes/grove", None, None).await;
    assert_eq!(s, StatusCode::NOT_FOUND, "a refused creation created the scene");
    let (s, v, _) = call_typed(
        &f.app,
        "/api/scenes",
        None,
        Some("Application/JSON ; charset=utf-8"),
        &body,
    )
    .await;
    assert_eq!(s, StatusCode::CREATED, "{v}");
    let token = v["write_token"].as_str().expect("token").to_string();
    let edit = json!({"remove": [1]}).to_string();
    for ct in forms {
        let (s, v, _) = call_typed(&f.app, "/api/scenes/grove/instances", Some(&token), ct, &edit).await;
        assert_eq!(s, StatusCode::UNSUPPORTED_MEDIA_TYPE, "{ct:?}: {v}");
    }
    let (_, v, _) = call(&f.app, "GET", "/api/scenes/grove", None, None).await;
    assert_eq!(
        (v["version"].as_u64(), v["instance_count"].as_u64()),
        (Some(1), Some(3))
    );
    let (s, v, _) = call_typed(
        &f.app,
        "/api/scenes/grove/instances",
        Some(&token),
        Some("application/json;charset=UTF-8"),
        &edit,
    )
    .await;
    assert_eq!((s, v["version"].as_u64()), (StatusCode::OK, Some(2)), "{v}");
}

#[tokio::test]
async fn the_streamed_instance_list_matches_the_old_serialisation() {
    let f = fixture("stream");
    let (s, v, _) = call(&f.app, "POST", "/api/scenes", None, Some(&scene_body(&f.models, true))).await;
    assert_eq!(s, StatusCode::CREATED);
    let token = v["write_token"].as_str().expect("token").to_string();
    // A few thousand instances over several versions, with moves and removes, in several
    // streamed chunks.
    for round in 0..3u32 {
        let add: Vec<Value> = (0..1500u32)
            .map(|k| {
                let t = (round * 1500 + k) as f32;
                json!({
                    "model": f.models[(k % 2) as usize],
                    "position": [t * 0.0131 - 99.9, t * 0.001, 99.9 - t * 0.0173],
                    "rotation": t * 0.37,
                    "scale": 0.7 + (k % 5) as f32 * 0.11
                })
            })
            .collect();
        let batch = json!({"add": add, "move": [{"id": 1, "position": [1.1, 2.2, 3.3]}], "remove": [2 + round]});
        let (s, v, _) = call(
            &f.app,
            "POST",
            "/api/scenes/grove/instances",
            Some(&token),
            Some(&batch.to_string()),
        )
        .await;
        assert_eq!(s, StatusCode::OK, "{v}");
    }
    let (s, v, streamed) = call(&f.app, "GET", "/api/scenes/grove/instances", None, None).await;
    assert_eq!(s, StatusCode::OK);
    assert_eq!(v["version"], 4);
    let list: Vec<canopy_server::store::scenes::Instance> =
        serde_json::from_value(v["instances"].clone()).expect("instances");
    assert_eq!(list.len(), 3 + 4500 - 3);
    assert!(list.windows(2).all(|w| w[0].id < w[1].id));
    // What the handler wrote before it streamed: `Json(json!({"version", "instances"}))`.
    let old = serde_json::to_vec(&json!({ "version": 4, "instances": list })).expect("json");
    assert_eq!(streamed, old);
    // A response not yet read holds the list; a scene deleted and created again under the same
    // id (within the same second) still gets its own list.
    let held = f
        .app
        .clone()
        .oneshot(
            Request::builder()
                .uri("/api/scenes/grove/instances")
                .body(Body::empty())
                .expect("request"),
        )
        .await
        .expect("infallible");
    let (s, _, _) = call(&f.app, "DELETE", "/api/scenes/grove", Some(&token), None).await;
    assert_eq!(s, StatusCode::NO_CONTENT);
    let (s, _, _) = call(&f.app, "POST", "/api/scenes", None, Some(&scene_body(&f.models, true))).await;
    assert_eq!(s, StatusCode::CREATED);
    let (_, v, _) = call(&f.app, "GET", "/api/scenes/grove/instances", None, None).await;
    assert_eq!(
        (v["version"].as_u64(), v["instances"].as_array().map(Vec::len)),
        (Some(1), Some(3))
    );
    let bytes = axum::body::to_bytes(held.into_body(), usize::MAX).await.expect("body");
    assert_eq!(bytes.to_vec(), old);
}
