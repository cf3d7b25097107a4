//! The scene JSON API under `/api/scenes`.
//!
//! Every error is `{"error": message}` ([`ApiError`]). Creation needs the server's creation token
//! unless it runs open ([`super::quota`]); creations and edits pass token buckets (429 with
//! `Retry-After`), the store enforces the owner's quotas (403) and prunes old versions, whose files
//! are deleted here once the version row is gone.

use axum::body::Bytes;
use axum::extract::{Path, RawQuery, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use serde::Deserialize;
use serde_json::json;

use super::AppState;
use super::auth;
use super::quota::{Peer, RateLimiter, ip_key};
use crate::store::assets::{NAME_HASH_HEX, sha256_hex};

pub use super::publish::{CLEANUP_TILES, Cleanup, apply_edit, apply_edit_then, discard, publish};
use crate::store::scenes::{
    Bounds, EditBatch, Limits, MAX_BATCH, NewInstance, NewScene, SceneAuth, SceneMeta, StoreError, valid_scene_id,
    validate_batch, validate_new,
};
use crate::store::tiles;
use crate::terrain::Ground;

/// An API error: a status and a message, sent as `{"error": message}`.
#[derive(Debug)]
pub struct ApiError {
    /// HTTP status.
    pub status: StatusCode,
    /// What went wrong, for people.
    pub message: String,
    /// Seconds to wait before asking again (`Retry-After`), for 429 and 503.
    pub retry_after: Option<u64>,
}

impl ApiError {
    /// A new error.
    pub fn new(status: StatusCode, message: impl Into<String>) -> Self {
        Self {
            status,
            message: message.into(),
            retry_after: None,
        }
    }

    /// A 429: the request's rate was exceeded; ask again after `wait`.
    pub fn too_many(what: &str, wait: std::time::Duration) -> Self {
        let secs = wait.as_secs().max(1);
        Self {
            retry_after: Some(secs),
            ..Self::new(
                StatusCode::TOO_MANY_REQUESTS,
                format!("too many {what}: try again in {secs} s"),
            )
        }
    }

    pub(super) fn bad(message: impl Into<String>) -> Self {
        Self::new(StatusCode::UNPROCESSABLE_ENTITY, message)
    }

    /// A 500 that logs `e` and tells the client nothing more.
    pub fn internal(e: impl std::fmt::Display) -> Self {
        tracing::error!(error = %e, "internal error");
        Self::new(StatusCode::INTERNAL_SERVER_ERROR, "internal error")
    }
}

impl From<StoreError> for ApiError {
    fn from(e: StoreError) -> Self {
        let status = match &e {
            StoreError::NotFound(_) | StoreError::NoVersion(_) => StatusCode::NOT_FOUND,
            StoreError::Quota(_) => StatusCode::FORBIDDEN,
            StoreError::Exists(_) | StoreError::Conflict { .. } => StatusCode::CONFLICT,
            StoreError::Invalid(_) | StoreError::Limit(_) => StatusCode::UNPROCESSABLE_ENTITY,
            StoreError::Publish(_) | StoreError::Database(_) => return Self::internal(e),
            StoreError::Unavailable(_) => {
                tracing::warn!(error = %e, "scene database unavailable");
                return Self {
                    retry_after: Some(1),
                    ..Self::new(
                        StatusCode::SERVICE_UNAVAILABLE,
                        "the scene database is unavailable; try again shortly",
                    )
                };
            }
        };
        Self::new(status, e.to_string())
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut r = (self.status, Json(json!({ "error": self.message }))).into_response();
        if self.status == StatusCode::UNAUTHORIZED {
            r.headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        if let Some(s) = self.retry_after {
            r.headers_mut().insert(header::RETRY_AFTER, HeaderValue::from(s));
        }
        r
    }
}

/// Takes one request from the buckets of `key` and of the client's address (when known).
pub(super) fn rate(limiter: &RateLimiter, what: &str, key: &str, peer: Option<Peer>) -> Result<(), ApiError> {
    let ip = peer.map(|Peer(ip)| format!("ip:{}", ip_key(ip)));
    // In open mode the owner is the address: one bucket, not two.
    let keys: Vec<&str> = std::iter::once(key)
        .chain(ip.as_deref().filter(|i| *i != key))
        .collect();
    limiter.take(&keys).map_err(|wait| ApiError::too_many(what, wait))
}

/// Runs a blocking store call off the async threads.
pub(super) async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> Result<T, ApiError> + Send + 'static,
) -> Result<T, ApiError> {
    tokio::task::spawn_blocking(f).await.map_err(ApiError::internal)?
}

/// True when the request's one `Content-Type` is `application/json` (any case, parameters such as
/// `charset` allowed).
pub fn is_json(headers: &HeaderMap) -> bool {
    let mut all = headers.get_all(header::CONTENT_TYPE).iter();
    let (Some(v), None) = (all.next(), all.next()) else {
        return false;
    };
    v.to_str().is_ok_and(|v| {
        v.split(';')
            .next()
            .is_some_and(|t| t.trim().eq_ignore_ascii_case("application/json"))
    })
}

/// 415 unless the request's body is declared as JSON ([`is_json`]; see [`parse_json`]).
pub(super) fn require_json(headers: &HeaderMap) -> Result<(), ApiError> {
    if is_json(headers) {
        Ok(())
    } else {
        Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "the body must be JSON sent with Content-Type: application/json",
        ))
    }
}

/// Parses a JSON request body. It must be declared as JSON: another site's HTML form can send
/// `text/plain`, `application/x-www-form-urlencoded` or `multipart/form-data` without a preflight,
/// but not `application/json`.
pub(super) fn parse_json<T: serde::de::DeserializeOwned>(headers: &HeaderMap, body: &[u8]) -> Result<T, ApiError> {
    require_json(headers)?;
    serde_json::from_slice(body).map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, format!("invalid JSON body: {e}")))
}

/// Checks the request may read scene `id` (public, or a valid read or write token) and returns it.
pub async fn read_access(
    state: &AppState,
    id: &str,
    headers: &HeaderMap,
    query: Option<&str>,
) -> Result<SceneMeta, ApiError> {
    let token = auth::presented(headers, query);
    let store = state.inner.scenes.clone();
    let id = id.to_string();
    blocking(move || {
        let not_found = || ApiError::new(StatusCode::NOT_FOUND, format!("scene {id:?} not found"));
        let meta = store.get(&id)?.ok_or_else(not_found)?;
        if meta.public {
            return Ok(meta);
        }
        let a = store.auth(&id)?.ok_or_else(not_found)?;
        let Some(t) = token else {
            return Err(ApiError::new(
                StatusCode::UNAUTHORIZED,
                "this scene is private: send its read or write token as Authorization: Bearer <token>",
            ));
        };
        let ok = auth::matches(Some(&t), &a.write_hash) | a.read_hash.is_some_and(|h| auth::matches(Some(&t), &h));
        if ok {
            Ok(meta)
        } else {
            Err(ApiError::new(
                StatusCode::FORBIDDEN,
                "the token does not grant access to this scene",
            ))
        }
    })
    .await
}

pub(super) async fn write_access(state: &AppState, id: &str, headers: &HeaderMap) -> Result<SceneMeta, ApiError> {
    let token = auth::presented(headers, None);
    let store = state.inner.scenes.clone();
    let id = id.to_string();
    blocking(move || {
        let not_found = || ApiError::new(StatusCode::NOT_FOUND, format!("scene {id:?} not found"));
        let meta = store.get(&id)?.ok_or_else(not_found)?;
        let a = store.auth(&id)?.ok_or_else(not_found)?;
        let Some(t) = token else {
            return Err(ApiError::new(
                StatusCode::UNAUTHORIZED,
                "changing a scene needs its write token as Authorization: Bearer <token>",
            ));
        };
        if auth::matches(Some(&t), &a.write_hash) {
            Ok(meta)
        } else {
            Err(ApiError::new(
                StatusCode::FORBIDDEN,
                "the token is not this scene's write token",
            ))
        }
    })
    .await
}

/// The immutable URL of a version's manifest: for a first version its static copy (an asset),
/// for later ones the API's `?version=N` (their manifests are not written as files).
pub fn manifest_location(scene: &str, version: u64, manifest: &str) -> String {
    if version == 1 {
        format!(
            "/assets/scenes/{scene}/v{version}.{}.json",
            &sha256_hex(manifest.as_bytes())[..NAME_HASH_HEX]
        )
    } else {
        format!("/api/scenes/{scene}/manifest?version={version}")
    }
}

fn describe(m: &SceneMeta, viewers: usize) -> serde_json::Value {
    json!({
        "id": m.id,
        "name": m.name,
        "public": m.public,
        "bounds": m.bounds,
        "version": m.version,
        "instance_count": m.instance_count,
        "created_unix": m.created_unix,
        "viewers": viewers,
        "manifest": format!("/api/scenes/{}/manifest", m.id),
        "live": format!("/api/scenes/{}/live", m.id),
    })
}

/// `GET /api/scenes`: the public scenes.
pub async fn list(State(state): State<AppState>) -> Result<Response, ApiError> {
    let store = state.inner.scenes.clone();
    let all = blocking(move || Ok(store.list()?)).await?;
    let scenes: Vec<_> = all
        .iter()
        .filter(|m| m.public)
        .map(|m| describe(m, state.inner.live.viewers(&m.id)))
        .collect();
    Ok(Json(json!({ "scenes": scenes })).into_response())
}

/// `POST /api/scenes` body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreateScene {
    /// Id; generated when absent.
    #[serde(default)]
    pub id: Option<String>,
    /// Name (1 to 200 characters).
    pub name: String,
    /// Public (default) or private.
    #[serde(default = "yes")]
    pub public: bool,
    /// Ground area.
    pub bounds: Bounds,
    /// First instances.
    #[serde(default)]
    pub instances: Vec<NewInstance>,
}

fn yes() -> bool {
    true
}

/// Creates one of the server's own scenes (no owner, no quota). Used by the demo.
pub fn create_scene(state: &AppState, req: &CreateScene) -> Result<(SceneMeta, String, Option<String>), ApiError> {
    create_scene_on(state, req, None)
}

/// Creates one of the server's own scenes standing on `terrain` from its first version on (its
/// file already written into the scene's folder: `terrain::ground::store`). Used by the demo.
pub fn create_scene_on(
    state: &AppState,
    req: &CreateScene,
    terrain: Option<&std::sync::Arc<Ground>>,
) -> Result<(SceneMeta, String, Option<String>), ApiError> {
    let limits = Limits::unlimited(&state.inner.config.limits);
    create_scene_inner(state, req, "", &limits, terrain)
}

/// Creates a scene for `owner` (whose quotas apply) through the store, publishing its first
/// version; returns it with its write and (private scenes) read tokens.
pub fn create_scene_as(
    state: &AppState,
    req: &CreateScene,
    owner: &str,
    limits: &Limits,
) -> Result<(SceneMeta, String, Option<String>), ApiError> {
    create_scene_inner(state, req, owner, limits, None)
}

fn create_scene_inner(
    state: &AppState,
    req: &CreateScene,
    owner: &str,
    limits: &Limits,
    terrain: Option<&std::sync::Arc<Ground>>,
) -> Result<(SceneMeta, String, Option<String>), ApiError> {
    let id = match &req.id {
        Some(id) if !valid_scene_id(id) => {
            return Err(ApiError::bad("id must be 1 to 64 of a-z 0-9 -"));
        }
        Some(id) => id.clone(),
        None => auth::new_token().map_err(ApiError::internal)?[..12].to_string(),
    };
    let n = req.name.chars().count();
    if n == 0 || n > 200 || req.name.chars().any(char::is_control) {
        return Err(ApiError::bad(
            "name must be 1 to 200 characters without control characters",
        ));
    }
    req.bounds.validate().map_err(ApiError::bad)?;
    if req.instances.len() > MAX_BATCH {
        return Err(ApiError::bad(format!(
            "at most {MAX_BATCH} instances at creation; add more in batches"
        )));
    }
    let known = state.inner.assets.models();
    validate_new(&req.instances, &req.bounds, &|m| known.contains_key(m)).map_err(ApiError::bad)?;
    let write = auth::new_token().map_err(ApiError::internal)?;
    let read = if req.public {
        None
    } else {
        Some(auth::new_token().map_err(ApiError::internal)?)
    };
    let scene = NewScene {
        id,
        name: req.name.clone(),
        public: req.public,
        bounds: req.bounds,
        auth: SceneAuth {
            write_hash: auth::hash_token(&write),
            read_hash: read.as_deref().map(auth::hash_token),
        },
        owner: owner.to_string(),
        terrain: terrain.map(|t| t.json()).transpose().map_err(ApiError::internal)?,
    };
    let mut written = Vec::new();
    let dir = format!("scenes/{}", scene.id);
    let blobs = state.inner.assets.blob_lock(&dir);
    let mut publishing = blobs.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    *publishing += 1;
    let replicas = state
        .inner
        .assets
        .folder_lock_shared(&dir)
        .map_err(ApiError::internal)?;
    let mut made = None;
    let created = state
        .inner
        .scenes
        .create(&scene, &req.instances, limits, &mut |m, l, ch| {
            let (p, draft) = super::publish::publish_on(&state.inner.assets, None, m, l, ch, terrain)?;
            made = Some(draft);
            written.push((m.version, p.clone()));
            Ok(p)
        });
    if let (Ok(meta), Some(draft)) = (&created, made) {
        state.inner.drafts.put(&meta.id, meta.created_unix, draft);
    }
    drop(replicas);
    let meta = created.inspect_err(|_| {
        discard(state, &scene.id, &written);
        if !written.is_empty() && !state.inner.assets.is_shared() {
            tiles::drop_unreferenced(&state.inner.assets, &dir, usize::MAX);
        }
    })?;
    tracing::info!(scene = %meta.id, instances = meta.instance_count, public = meta.public, owner, "scene created");
    Ok((meta, write, read))
}

/// `POST /api/scenes`: with the server's creation token unless creation is open.
pub async fn create(
    State(state): State<AppState>,
    peer: Option<Extension<Peer>>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Response, ApiError> {
    let peer = peer.map(|Extension(p)| p);
    let token = auth::presented(&headers, None);
    let owner = state
        .inner
        .config
        .creation
        .owner(token.as_deref(), peer.map(|Peer(ip)| ip))
        .map_err(|missing| {
            if missing {
                ApiError::new(
                    StatusCode::UNAUTHORIZED,
                    "creating a scene needs this server's creation token as Authorization: Bearer <token>",
                )
            } else {
                ApiError::new(
                    StatusCode::FORBIDDEN,
                    "the token is not a creation token of this server",
                )
            }
        })?;
    rate(&state.inner.create_limiter, "scene creations", &owner, peer)?;
    let req: CreateScene = parse_json(&headers, &body)?;
    let st = state.clone();
    let (meta, write, read) =
        super::edits::run(move || create_scene_as(&st, &req, &owner, &st.inner.config.limits)).await?;
    let mut body = describe(&meta, 0);
    body["write_token"] = json!(write);
    if let Some(r) = read {
        body["read_token"] = json!(r);
    }
    let mut r = (StatusCode::CREATED, Json(body)).into_response();
    if let Ok(v) = HeaderValue::from_str(&format!("/api/scenes/{}", meta.id)) {
        r.headers_mut().insert(header::LOCATION, v);
    }
    Ok(r)
}

/// `GET /api/scenes/{id}`.
pub async fn get(
    State(state): State<AppState>,
    Path(id): Path<String>,
    RawQuery(q): RawQuery,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let meta = read_access(&state, &id, &headers, q.as_deref()).await?;
    Ok(Json(describe(&meta, state.inner.live.viewers(&id))).into_response())
}

/// `DELETE /api/scenes/{id}`.
pub async fn delete(
    State(state): State<AppState>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    write_access(&state, &id, &headers).await?;
    let store = state.inner.scenes.clone();
    let sid = id.clone();
    blocking(move || Ok(store.delete(&sid)?)).await?;
    state.inner.instance_tables.forget(&id).await;
    state.inner.drafts.forget(&id);
    if let Err(e) = state.inner.assets.remove_dir(&format!("scenes/{id}")) {
        tracing::warn!(scene = %id, error = %e, "scene deleted but its files remain");
    }
    state.inner.live.notify_deleted(&id);
    tracing::info!(scene = %id, "scene deleted");
    Ok(StatusCode::NO_CONTENT.into_response())
}

fn version_param(q: Option<&str>) -> Result<Option<u64>, ApiError> {
    let Some(v) = q.and_then(|q| q.split('&').find_map(|kv| kv.strip_prefix("version="))) else {
        return Ok(None);
    };
    v.parse()
        .map(Some)
        .map_err(|_| ApiError::new(StatusCode::BAD_REQUEST, "version must be a positive integer"))
}

/// The `version` of a manifest's text (its other fields skipped, not built).
fn version_of(manifest: &str) -> Option<u64> {
    #[derive(serde::Deserialize)]
    struct Version {
        version: u64,
    }
    serde_json::from_str::<Version>(manifest).ok().map(|v| v.version)
}

/// `GET /api/scenes/{id}/manifest[?version=N]`.
pub async fn manifest(
    State(state): State<AppState>,
    Path(id): Path<String>,
    RawQuery(q): RawQuery,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let meta = read_access(&state, &id, &headers, q.as_deref()).await?;
    let version = version_param(q.as_deref())?;
    let store = state.inner.scenes.clone();
    let sid = id.clone();
    let text = blocking(move || Ok(store.manifest(&sid, version)?))
        .await?
        .ok_or_else(|| {
            ApiError::new(
                StatusCode::NOT_FOUND,
                format!("scene {id:?} has no version {}", version.unwrap_or(meta.version)),
            )
        })?;
    // The current version is read from the text: an edit may have committed since `meta`.
    let v = match version {
        Some(v) => v,
        None => version_of(&text).unwrap_or(meta.version),
    };
    let location = manifest_location(&id, v, &text);
    // A given version never changes; "current" does.
    let cache = if version.is_some() {
        "private, max-age=31536000, immutable"
    } else {
        "no-cache"
    };
    let mut r = json_with_etag(text, &headers, cache);
    let h = r.headers_mut();
    if let Ok(l) = HeaderValue::from_str(&location) {
        h.insert(header::CONTENT_LOCATION, l);
    }
    Ok(r)
}

/// A JSON text with its SHA-256 as `ETag` and `cache` as `Cache-Control`; 304 without the body
/// when `headers` carry a matching `If-None-Match`.
pub(super) fn json_with_etag(text: String, headers: &HeaderMap, cache: &'static str) -> Response {
    let etag = format!("\"{}\"", sha256_hex(text.as_bytes()));
    let not_modified = headers
        .get(header::IF_NONE_MATCH)
        .is_some_and(|h| super::assets::none_match(h.as_bytes(), &etag));
    let mut r = if not_modified {
        StatusCode::NOT_MODIFIED.into_response()
    } else {
        ([(header::CONTENT_TYPE, "application/json")], text).into_response()
    };
    let h = r.headers_mut();
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static(cache));
    if let Ok(e) = HeaderValue::from_str(&etag) {
        h.insert(header::ETAG, e);
    }
    r
}

/// `GET /api/scenes/{id}/instances`: the current instances, streamed ([`super::instances`]).
pub async fn instances(
    State(state): State<AppState>,
    Path(id): Path<String>,
    RawQuery(q): RawQuery,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let meta = read_access(&state, &id, &headers, q.as_deref()).await?;
    let store = state.inner.scenes.clone();
    let table = state.inner.instance_tables.get(store, &meta).await?;
    Ok(super::instances::response(table))
}

/// `POST /api/scenes/{id}/instances`: one batch of adds, moves and removes, as one new version.
pub async fn edit(
    State(state): State<AppState>,
    Path(id): Path<String>,
    peer: Option<Extension<Peer>>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Response, ApiError> {
    let meta = write_access(&state, &id, &headers).await?;
    // After the token check: others cannot spend a scene's edits.
    rate(
        &state.inner.edit_limiter,
        "edits",
        &format!("scene:{id}"),
        peer.map(|Extension(p)| p),
    )?;
    let batch: EditBatch = parse_json(&headers, &body)?;
    let known = state.inner.assets.models();
    validate_batch(&batch, &meta.bounds, &|m| known.contains_key(m)).map_err(ApiError::bad)?;
    let st = state.clone();
    let sid = id.clone();
    let (meta, added) =
        super::edits::run_then(move || apply_edit_then(&st, &sid, &batch, &st.inner.config.limits)).await?;
    state.inner.metrics.edit();
    state.inner.live.notify_version(&id, meta.version);
    tracing::info!(scene = %id, version = meta.version, instances = meta.instance_count, "scene edited");
    let mut body = describe(&meta, state.inner.live.viewers(&id));
    body["added_ids"] = json!(added);
    Ok(Json(body).into_response())
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_manifests_version_is_its_own_field_not_a_names() {
        let text =
            r#"{"format":"canopy-scene","format_version":1,"scene":"s","name":"\"version\":9","version":4,"tiles":[]}"#;
        assert_eq!(super::version_of(text), Some(4));
        assert_eq!(super::version_of("{\"version\":-1}"), None);
        assert_eq!(super::version_of("not json"), None);
    }
}
