//! A scene's kept versions and their pins: `GET /api/scenes/{id}/versions` (read access),
//! `POST /api/scenes/{id}/pins` with `{"version": N}` (the current one when absent) and
//! `DELETE /api/scenes/{id}/pins/{version}` (write token; counted as edits by the rate limit).
//!
//! A pinned version is kept whatever the retention (at most `Limits::max_pins` per scene); an
//! unpinned one goes at the next edit or collection if the retention no longer keeps it.

use axum::body::Bytes;
use axum::extract::{Path, RawQuery, State};
use axum::http::HeaderMap;
use axum::response::{IntoResponse, Response};
use axum::{Extension, Json};
use serde::Deserialize;
use serde_json::json;

use super::AppState;
use super::quota::Peer;
use super::scenes::{ApiError, blocking, parse_json, rate, read_access, write_access};

/// `GET /api/scenes/{id}/versions`: `{"versions": [{version, created_unix, bytes, pinned}]}`,
/// oldest first, and the retention that applies.
pub async fn list(
    State(state): State<AppState>,
    Path(id): Path<String>,
    RawQuery(q): RawQuery,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    read_access(&state, &id, &headers, q.as_deref()).await?;
    let store = state.inner.scenes.clone();
    let versions = blocking(move || Ok(store.versions(&id)?)).await?;
    let l = &state.inner.config.limits;
    Ok(Json(json!({
        "versions": versions,
        "retention": {"keep_versions": l.keep_versions, "keep_days": l.keep_secs as f64 / 86_400.0, "max_pins": l.max_pins},
    }))
    .into_response())
}

/// `POST /api/scenes/{id}/pins` body.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct PinRequest {
    /// The version; the current one when absent.
    #[serde(default)]
    version: Option<u64>,
}

async fn set_pin(
    state: AppState,
    id: String,
    peer: Option<Extension<Peer>>,
    headers: &HeaderMap,
    version: Option<u64>,
    pin: bool,
) -> Result<Response, ApiError> {
    write_access(&state, &id, headers).await?;
    rate(
        &state.inner.edit_limiter,
        "edits",
        &format!("scene:{id}"),
        peer.map(|Extension(p)| p),
    )?;
    let st = state.clone();
    let pinned = blocking(move || Ok(st.inner.scenes.pin(&id, version, pin, &st.inner.config.limits)?)).await?;
    Ok(Json(json!({ "pinned": pinned })).into_response())
}

/// `POST /api/scenes/{id}/pins`: pins a version → `{"pinned": [versions]}`.
pub async fn pin(
    State(state): State<AppState>,
    Path(id): Path<String>,
    peer: Option<Extension<Peer>>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Response, ApiError> {
    let req: PinRequest = if body.is_empty() {
        PinRequest::default()
    } else {
        parse_json(&headers, &body)?
    };
    set_pin(state, id, peer, &headers, req.version, true).await
}

/// `DELETE /api/scenes/{id}/pins/{version}`: unpins it → `{"pinned": [versions]}`.
pub async fn unpin(
    State(state): State<AppState>,
    Path((id, version)): Path<(String, String)>,
    peer: Option<Extension<Peer>>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let version: u64 = version.parse().map_err(|_| {
        ApiError::new(
            axum::http::StatusCode::BAD_REQUEST,
            "the version must be a positive integer",
        )
    })?;
    set_pin(state, id, peer, &headers, Some(version), false).await
}
