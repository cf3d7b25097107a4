//! A scene's flight table (seed 002's visual-redundancy table, `canopy_shared::flight_table`,
//! computed by the client's `canopy redundancy`): `PUT`, `GET` and `DELETE
//! /api/scenes/{id}/flight-table`. A scene property, not versioned: setting it makes no version.
//!
//! `PUT` and `DELETE` need the write token and count as edits for the rate limit; `GET` reads as
//! the manifest does (public scenes open, private ones with a token). A `PUT` body is checked whole
//! ([`FlightTable::parse`]: 400 with its message, 413 over [`MAX_TABLE_BYTES`]) and stored as the
//! table's compact JSON, which both the `PUT` and every later `GET` answer, byte for byte.

use axum::Extension;
use axum::body::Bytes;
use axum::extract::{Path, RawQuery, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use canopy_shared::flight_table::{FlightTable, FlightTableError, MAX_TABLE_BYTES};

use super::AppState;
use super::quota::Peer;
use super::scenes::{ApiError, blocking, json_with_etag, rate, read_access, require_json, write_access};

// The request body bound answers 413 before the handler past `MAX_BODY`; a table over its own
// bound is the same 413 from `FlightTable::parse`, so the two bounds may differ.
const _: () = assert!(
    MAX_TABLE_BYTES <= super::MAX_BODY,
    "a largest table must fit a request body"
);

/// The API's error for a refused table: 413 over the size bound, 400 otherwise.
fn refused(e: &FlightTableError) -> ApiError {
    let status = match e {
        FlightTableError::TooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
        FlightTableError::Json(_) | FlightTableError::Version { .. } | FlightTableError::Invalid(_) => {
            StatusCode::BAD_REQUEST
        }
    };
    ApiError::new(status, e.to_string())
}

/// The table's JSON with its ETag; `no-cache`: a `PUT` replaces it.
fn table_response(text: String, headers: &HeaderMap) -> Response {
    json_with_etag(text, headers, "no-cache")
}

/// The write token's check, then the scene's edit rate limit (after the token, as for instance
/// edits: others cannot spend a scene's edits); returns the scene. Also the terrain's.
pub(super) async fn edit_access(
    state: &AppState,
    id: &str,
    headers: &HeaderMap,
    peer: Option<Extension<Peer>>,
) -> Result<crate::store::scenes::SceneMeta, ApiError> {
    let meta = write_access(state, id, headers).await?;
    rate(
        &state.inner.edit_limiter,
        "edits",
        &format!("scene:{id}"),
        peer.map(|Extension(p)| p),
    )?;
    Ok(meta)
}

/// `GET /api/scenes/{id}/flight-table`: the table, or 404 "scene … has no flight table" (an
/// unknown scene's 404 says "not found").
pub async fn get(
    State(state): State<AppState>,
    Path(id): Path<String>,
    RawQuery(q): RawQuery,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    read_access(&state, &id, &headers, q.as_deref()).await?;
    let store = state.inner.scenes.clone();
    let sid = id.clone();
    let text = blocking(move || Ok(store.flight_table(&sid)?))
        .await?
        .ok_or_else(|| ApiError::new(StatusCode::NOT_FOUND, format!("scene {id:?} has no flight table")))?;
    Ok(table_response(text, &headers))
}

/// `PUT /api/scenes/{id}/flight-table`: checks and stores the table (replacing any) → 200 with
/// the stored JSON. A refused table changes nothing.
pub async fn put(
    State(state): State<AppState>,
    Path(id): Path<String>,
    peer: Option<Extension<Peer>>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Response, ApiError> {
    edit_access(&state, &id, &headers, peer).await?;
    require_json(&headers)?;
    let store = state.inner.scenes.clone();
    let sid = id.clone();
    // Parsing up to 4 MiB of JSON is CPU: on the edit threads, not the async ones.
    let text = super::edits::run(move || {
        let table = FlightTable::parse(&body).map_err(|e| refused(&e))?;
        let text = table.to_json().map_err(ApiError::internal)?;
        store.set_flight_table(&sid, &text)?;
        Ok(text)
    })
    .await?;
    tracing::info!(scene = %id, bytes = text.len(), "flight table stored");
    Ok(table_response(text, &HeaderMap::new()))
}

/// `DELETE /api/scenes/{id}/flight-table`: removes the table → 204 (also when it had none).
pub async fn delete(
    State(state): State<AppState>,
    Path(id): Path<String>,
    peer: Option<Extension<Peer>>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    edit_access(&state, &id, &headers, peer).await?;
    let store = state.inner.scenes.clone();
    let sid = id.clone();
    if blocking(move || Ok(store.clear_flight_table(&sid)?)).await? {
        tracing::info!(scene = %id, "flight table removed");
    }
    Ok(StatusCode::NO_CONTENT.into_response())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refused_tables_are_400_and_oversized_ones_413() {
        let too_large = FlightTableError::TooLarge(MAX_TABLE_BYTES + 1);
        assert_eq!(refused(&too_large).status, StatusCode::PAYLOAD_TOO_LARGE);
        let e = refused(&FlightTable::parse(b"{").expect_err("not JSON"));
        assert_eq!(e.status, StatusCode::BAD_REQUEST);
        assert!(e.message.contains("not valid JSON"), "{}", e.message);
    }
}
