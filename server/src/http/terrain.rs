//! A scene's terrain: `PUT`, `GET` and `DELETE /api/scenes/{id}/terrain`. Unlike the flight
//! table, a terrain is versioned: setting or removing it publishes a new version of the same
//! instances on the new ground (pack and manifest, `super::publish`), which live viewers learn of
//! as of any edit.
//!
//! `PUT` and `DELETE` need the write token and count as edits for the rate limit; `GET` reads as
//! the manifest does. A `PUT` body is a `.cterrain` file (`application/octet-stream`), a 16-bit
//! grayscale PNG (`image/png`: query `cell=M&heights=MIN:MAX`, optional `origin=X,Z`) or a
//! single-band GeoTIFF (`image/tiff`: optional `cell`, `origin`, and `heights` for u16 samples);
//! `samples=NX,NZ` checks the size of any of them. Another content type is 415, a body over
//! [`MAX_TERRAIN_BODY`] 413, a file the decoder refuses 400 with its message, a terrain that does
//! not overlap the scene's bounds 422. The answer of a `PUT`, and of every later `GET`, is the
//! manifest's `terrain` object (URL, SHA-256, size, grid, tiles) as stored, byte for byte.

use std::sync::Arc;

use axum::Extension;
use axum::body::Bytes;
use axum::extract::{Path, RawQuery, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use canopy_shared::terrain::Heightfield;

use super::AppState;
use super::flight_table::edit_access;
use super::quota::Peer;
use super::scenes::{ApiError, blocking, json_with_etag, read_access};
use crate::store::scenes::{Bounds, Limits};
use crate::terrain::import::{self, HeightmapFormat, ImportOptions};
use crate::terrain::{Ground, ground};

/// Largest terrain upload (a request body of any other route stays within [`super::MAX_BODY`]).
pub const MAX_TERRAIN_BODY: usize = 64 << 20;

/// Terrain uploads read and decoded at once; more are answered 503 with `Retry-After` before their
/// bodies are read (each may take a few hundred MiB while it decodes).
pub const MAX_TERRAIN_UPLOADS: usize = 2;

/// True for the request whose body may be as large as [`MAX_TERRAIN_BODY`].
pub fn is_upload(method: &axum::http::Method, path: &str) -> bool {
    method == axum::http::Method::PUT && path.starts_with("/api/scenes/") && path.ends_with("/terrain")
}

/// What a `PUT` body is, by its one `Content-Type`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Upload {
    Terrain,
    Image(HeightmapFormat),
}

fn upload_kind(headers: &HeaderMap) -> Result<Upload, ApiError> {
    let mut all = headers.get_all(header::CONTENT_TYPE).iter();
    let declared = match (all.next(), all.next()) {
        (Some(v), None) => v.to_str().ok().and_then(|v| v.split(';').next()).map(str::trim),
        _ => None,
    };
    let is = |t: &str| declared.is_some_and(|d| d.eq_ignore_ascii_case(t));
    if is("application/octet-stream") {
        Ok(Upload::Terrain)
    } else if is("image/png") {
        Ok(Upload::Image(HeightmapFormat::Png))
    } else if is("image/tiff") {
        Ok(Upload::Image(HeightmapFormat::Tiff))
    } else {
        Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "the body must be a .cterrain file (Content-Type: application/octet-stream), a 16-bit PNG \
             (image/png) or a GeoTIFF (image/tiff) heightmap",
        ))
    }
}

/// `%XX` escapes decoded (what a client may make of `:` and `,`); `None` when malformed.
fn percent_decode(s: &str) -> Option<String> {
    let b = s.as_bytes();
    let (mut out, mut k) = (Vec::with_capacity(b.len()), 0);
    while k < b.len() {
        if b[k] == b'%' {
            let hex = std::str::from_utf8(b.get(k + 1..k + 3)?).ok()?;
            out.push(u8::from_str_radix(hex, 16).ok()?);
            k += 3;
        } else {
            out.push(if b[k] == b'+' { b' ' } else { b[k] });
            k += 1;
        }
    }
    String::from_utf8(out).ok()
}

/// The import options of the query; 400 for an unknown name or a bad value.
fn options(query: Option<&str>) -> Result<ImportOptions, ApiError> {
    let bad = |m: String| ApiError::new(StatusCode::BAD_REQUEST, m);
    let mut opts = ImportOptions::default();
    for kv in query.unwrap_or("").split('&').filter(|kv| !kv.is_empty()) {
        let (k, v) = kv.split_once('=').unwrap_or((kv, ""));
        let v = percent_decode(v).ok_or_else(|| bad(format!("query parameter {k}: bad percent-encoding")))?;
        if !opts.set(k, &v).map_err(bad)? {
            return Err(bad(format!(
                "unknown query parameter {k:?}: use cell, heights, origin or samples"
            )));
        }
    }
    Ok(opts)
}

/// Decodes an upload into a heightfield: 400 with the decoder's message.
fn decode(kind: Upload, body: &[u8], opts: &ImportOptions) -> Result<Heightfield, ApiError> {
    let bad = |m: String| ApiError::new(StatusCode::BAD_REQUEST, m);
    match kind {
        Upload::Terrain => {
            if opts.cell.is_some() || opts.heights.is_some() || opts.origin.is_some() {
                return Err(bad(
                    "cell, heights and origin apply to heightmap images; a .cterrain file carries its own grid".into(),
                ));
            }
            let field = Heightfield::decode(body).map_err(|e| bad(e.to_string()))?;
            if let Some(want) = opts.samples
                && want != field.grid.samples
            {
                let [nx, nz] = field.grid.samples;
                return Err(bad(format!(
                    "the terrain is {nx} × {nz} samples, expected {} × {}",
                    want[0], want[1]
                )));
            }
            Ok(field)
        }
        Upload::Image(format) => {
            let got = match format {
                HeightmapFormat::Png => import::import_png(body, opts),
                HeightmapFormat::Tiff => import::import_tiff(body, opts),
            };
            got.map(|i| i.field).map_err(|e| bad(e.to_string()))
        }
    }
}

/// 422 unless the terrain's grid overlaps the scene's bounds.
fn check_overlap(field: &Heightfield, bounds: &Bounds) -> Result<(), ApiError> {
    let [x0, z0, x1, z1] = field.grid.bounds().map(f64::from);
    if x1 < bounds.min[0] || x0 > bounds.max[0] || z1 < bounds.min[1] || z0 > bounds.max[1] {
        return Err(ApiError::new(
            StatusCode::UNPROCESSABLE_ENTITY,
            format!(
                "the terrain covers [{x0}, {z0}]..[{x1}, {z1}] (x, z), outside the scene's bounds [{}, {}]..[{}, {}]: \
                 give origin=X,Z",
                bounds.min[0], bounds.min[1], bounds.max[0], bounds.max[1]
            ),
        ));
    }
    Ok(())
}

/// `GET /api/scenes/{id}/terrain`: the terrain object, or 404 "scene … has no terrain" (an
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
    let text = blocking(move || Ok(store.terrain(&sid)?))
        .await?
        .ok_or_else(|| ApiError::new(StatusCode::NOT_FOUND, format!("scene {id:?} has no terrain")))?;
    Ok(json_with_etag(text, &headers, "no-cache"))
}

/// Makes the version that sets (`Some`) or removes the terrain; tells live viewers.
async fn set(state: &AppState, id: &str, ground: Option<Arc<Ground>>) -> Result<u64, ApiError> {
    let (st, sid) = (state.clone(), id.to_string());
    let meta = super::edits::run_then(move || {
        let json = ground
            .as_ref()
            .map(|g| g.json())
            .transpose()
            .map_err(ApiError::internal)?;
        let limits: Limits = st.inner.config.limits;
        super::publish::apply_version_then(&st, &sid, ground.as_ref(), &mut |_| {}, &mut |store, publish| {
            store.set_terrain(&sid, json.as_deref(), &limits, publish)
        })
    })
    .await?;
    state.inner.metrics.edit();
    state.inner.live.notify_version(id, meta.version);
    Ok(meta.version)
}

/// `PUT /api/scenes/{id}/terrain`: checks the file, stores it and publishes a version on it →
/// 200 with the terrain object. A refused upload changes nothing.
pub async fn put(
    State(state): State<AppState>,
    Path(id): Path<String>,
    RawQuery(q): RawQuery,
    peer: Option<Extension<Peer>>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Response, ApiError> {
    let meta = edit_access(&state, &id, &headers, peer).await?;
    let kind = upload_kind(&headers)?;
    let opts = options(q.as_deref())?;
    let (st, sid) = (state.clone(), id.clone());
    // Decoding and encoding up to 16.8 million samples is CPU: on the edit threads.
    let ground = super::edits::run(move || {
        let field = decode(kind, &body, &opts)?;
        check_overlap(&field, &meta.bounds)?;
        // Unnamed until the version commits; a refused version leaves it to the sweep.
        ground::store(&st.inner.assets, &sid, field)
            .map(Arc::new)
            .map_err(ApiError::internal)
    })
    .await?;
    let text = ground.json().map_err(ApiError::internal)?;
    let [nx, nz] = ground.terrain.grid.samples;
    let version = set(&state, &id, Some(ground)).await?;
    tracing::info!(scene = %id, version, samples = nx * nz, "terrain set");
    Ok(json_with_etag(text, &HeaderMap::new(), "no-cache"))
}

/// `DELETE /api/scenes/{id}/terrain`: publishes a version on flat ground → 204; when the scene
/// has no terrain, 204 and no version.
pub async fn delete(
    State(state): State<AppState>,
    Path(id): Path<String>,
    peer: Option<Extension<Peer>>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    edit_access(&state, &id, &headers, peer).await?;
    let store = state.inner.scenes.clone();
    let sid = id.clone();
    if blocking(move || Ok(store.terrain(&sid)?)).await?.is_some() {
        let version = set(&state, &id, None).await?;
        tracing::info!(scene = %id, version, "terrain removed");
    }
    Ok(StatusCode::NO_CONTENT.into_response())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn query_options_are_parsed_and_bad_ones_refused() {
        let o = options(Some("cell=4&heights=-10%3A80.5&origin=-550,-500&samples=276%2C251")).expect("valid");
        assert_eq!(o.cell, Some(4.0));
        assert_eq!(o.heights, Some([-10.0, 80.5]));
        assert_eq!(o.origin, Some([-550.0, -500.0]));
        assert_eq!(o.samples, Some([276, 251]));
        assert_eq!(options(None).expect("none"), ImportOptions::default());
        for bad in [
            "cell=x",
            "cell=inf",
            "heights=5",
            "origin=1;2",
            "samples=2.5,3",
            "samples=-1,3",
            "colour=red",
            "cell=%zz",
        ] {
            let e = options(Some(bad)).expect_err(bad);
            assert_eq!(e.status, StatusCode::BAD_REQUEST, "{bad}");
        }
    }

    #[test]
    fn uploads_are_told_apart_by_content_type() {
        let with = |v: &str| {
            let mut h = HeaderMap::new();
            h.insert(header::CONTENT_TYPE, v.parse().expect("header"));
            upload_kind(&h)
        };
        assert_eq!(with("application/octet-stream").expect("ok"), Upload::Terrain);
        assert_eq!(with("IMAGE/PNG").expect("ok"), Upload::Image(HeightmapFormat::Png));
        assert_eq!(
            with("image/tiff; x=1").expect("ok"),
            Upload::Image(HeightmapFormat::Tiff)
        );
        for t in ["application/json", "image/jpeg", "text/plain"] {
            assert_eq!(with(t).expect_err(t).status, StatusCode::UNSUPPORTED_MEDIA_TYPE);
        }
        assert_eq!(
            upload_kind(&HeaderMap::new()).expect_err("none").status,
            StatusCode::UNSUPPORTED_MEDIA_TYPE
        );
        assert!(is_upload(&axum::http::Method::PUT, "/api/scenes/a/terrain"));
        assert!(!is_upload(&axum::http::Method::PUT, "/api/scenes/a/flight-table"));
        assert!(!is_upload(&axum::http::Method::POST, "/api/scenes/a/terrain"));
    }
}
