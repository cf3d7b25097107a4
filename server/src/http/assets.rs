//! `GET`/`HEAD`/`OPTIONS /assets/{path}`: immutable, content-addressed files by byte range.

use std::time::Instant;

use axum::body::Body;
use axum::extract::{Request, State};
use axum::http::{HeaderMap, HeaderValue, Method, StatusCode, header};
use axum::response::{IntoResponse, Response};
use bytes::Bytes;

use super::AppState;
use super::metrics::Route;
use super::multipart::{Framing, INLINE_MAX, RangeBody, build_inline, closing, multipart_len, part_header};
use super::range::{ByteRange, RangeDecision, evaluate};
use crate::store::Asset;

/// `Cache-Control` of every asset: the URL names the content, so it never changes.
pub const IMMUTABLE: &str = "public, max-age=31536000, immutable";
/// Headers a browser script may read from asset responses.
pub const EXPOSE: &str = "Content-Range, Content-Length, Content-Type, ETag, Accept-Ranges";

/// Adds the CORS headers every response carries.
pub fn cors(h: &mut HeaderMap) {
    h.insert(header::ACCESS_CONTROL_ALLOW_ORIGIN, HeaderValue::from_static("*"));
    h.insert(header::ACCESS_CONTROL_EXPOSE_HEADERS, HeaderValue::from_static(EXPOSE));
}

/// The answer to a CORS preflight.
pub fn preflight() -> Response {
    let mut r = StatusCode::NO_CONTENT.into_response();
    let h = r.headers_mut();
    cors(h);
    h.insert(
        header::ACCESS_CONTROL_ALLOW_METHODS,
        HeaderValue::from_static("GET, HEAD, POST, DELETE, OPTIONS"),
    );
    h.insert(
        header::ACCESS_CONTROL_ALLOW_HEADERS,
        HeaderValue::from_static("Range, If-None-Match, If-Range, Authorization, Content-Type"),
    );
    h.insert(header::ACCESS_CONTROL_MAX_AGE, HeaderValue::from_static("86400"));
    r
}

/// True when an `If-None-Match` value matches `etag` (weak comparison, RFC 9110 §13.1.2).
pub fn none_match(value: &[u8], etag: &str) -> bool {
    let ours = etag.as_bytes();
    value.split(|&b| b == b',').any(|t| {
        let t = t.trim_ascii();
        t == b"*" || t.strip_prefix(b"W/").unwrap_or(t) == ours
    })
}

/// True when an `If-Range` value lets the `Range` apply: it must be our strong entity tag (a date
/// never matches, since assets send no `Last-Modified`).
pub fn if_range_ok(value: &[u8], etag: &str) -> bool {
    value.trim_ascii() == etag.as_bytes()
}

fn status_and_len(r: &Response) -> (u16, u64) {
    let len = http_body::Body::size_hint(r.body()).exact().unwrap_or(0);
    (r.status().as_u16(), len)
}

/// The asset handler.
pub async fn asset(State(state): State<AppState>, req: Request) -> Response {
    let t0 = Instant::now();
    let (resp, ranges) = answer(&state, &req);
    let (status, len) = status_and_len(&resp);
    let m = &state.inner.metrics;
    m.request(
        Route::Assets,
        status,
        if req.method() == Method::HEAD { 0 } else { len },
        t0.elapsed(),
    );
    if let Some(n) = ranges {
        m.ranges(n);
    }
    resp
}

/// Methods an asset answers (`Allow` of a 405).
const ASSET_METHODS: &str = "GET, HEAD, OPTIONS";

/// Headers of every asset response: at most this many are set, so the map never grows.
const HEADER_CAPACITY: usize = 12;

fn header_response(status: StatusCode, a: &Asset) -> Response {
    let mut r = Response::new(Body::empty());
    *r.status_mut() = status;
    let h = r.headers_mut();
    h.reserve(HEADER_CAPACITY);
    cors(h);
    h.insert(header::ACCEPT_RANGES, HeaderValue::from_static("bytes"));
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static(IMMUTABLE));
    h.insert(header::ETAG, a.etag_header.clone());
    r
}

/// `bytes FIRST-LAST/LEN` without going through `format!` and a `String`.
fn content_range(r: ByteRange, total: u64) -> Option<HeaderValue> {
    use std::io::Write as _;
    let mut buf = [0u8; 72];
    let mut w = &mut buf[..];
    write!(w, "bytes {}-{}/{}", r.start, r.end - 1, total).ok()?;
    let n = 72 - w.len();
    HeaderValue::from_bytes(&buf[..n]).ok()
}

fn error(status: StatusCode, msg: &'static str) -> Response {
    let mut r = (status, msg).into_response();
    cors(r.headers_mut());
    r
}

/// Builds the response; also returns the number of ranges served for GETs.
fn answer(state: &AppState, req: &Request) -> (Response, Option<usize>) {
    let method = req.method();
    if method == Method::OPTIONS {
        return (preflight(), None);
    }
    // Assets are read-only: anything but GET, HEAD and OPTIONS is refused, as a static host
    // does (RFC 9110 §15.5.6: 405 with `Allow`), never answered with the file.
    if method != Method::GET && method != Method::HEAD {
        let mut r = error(
            StatusCode::METHOD_NOT_ALLOWED,
            "assets are read-only: GET, HEAD or OPTIONS\n",
        );
        r.headers_mut()
            .insert(header::ALLOW, HeaderValue::from_static(ASSET_METHODS));
        return (r, None);
    }
    let rel = req.uri().path().strip_prefix("/assets/").unwrap_or("");
    let Some(a) = state.inner.assets.get(rel) else {
        return (error(StatusCode::NOT_FOUND, "no such asset\n"), None);
    };
    let headers = req.headers();
    if headers
        .get(header::IF_NONE_MATCH)
        .is_some_and(|v| none_match(v.as_bytes(), &a.etag))
    {
        return (header_response(StatusCode::NOT_MODIFIED, &a), None);
    }
    if method == Method::HEAD {
        let mut r = header_response(StatusCode::OK, &a);
        set_len_type(&mut r, a.len, a.content_type_header.clone());
        return (r, None);
    }
    let decision = match headers.get(header::RANGE) {
        Some(range)
            if headers
                .get(header::IF_RANGE)
                .is_none_or(|v| if_range_ok(v.as_bytes(), &a.etag)) =>
        {
            evaluate(range.as_bytes(), a.len)
        }
        _ => RangeDecision::Full,
    };
    match decision {
        RangeDecision::Unsatisfiable => {
            let mut r = header_response(StatusCode::RANGE_NOT_SATISFIABLE, &a);
            if let Ok(v) = HeaderValue::from_str(&format!("bytes */{}", a.len)) {
                r.headers_mut().insert(header::CONTENT_RANGE, v);
            }
            r.headers_mut().insert(header::CONTENT_LENGTH, HeaderValue::from(0));
            (r, Some(0))
        }
        RangeDecision::Full => (
            body_response(
                state,
                &a,
                StatusCode::OK,
                vec![ByteRange { start: 0, end: a.len }],
                None,
            ),
            Some(0),
        ),
        RangeDecision::Partial(ranges) => {
            let n = ranges.len();
            let r = if n == 1 {
                let first = ranges[0];
                let mut r = body_response(state, &a, StatusCode::PARTIAL_CONTENT, ranges, None);
                if r.status() == StatusCode::PARTIAL_CONTENT
                    && let Some(v) = content_range(first, a.len)
                {
                    r.headers_mut().insert(header::CONTENT_RANGE, v);
                }
                r
            } else {
                let framing = Framing {
                    boundary: state.inner.boundary.clone(),
                    content_type: a.content_type,
                    total: a.len,
                };
                body_response(state, &a, StatusCode::PARTIAL_CONTENT, ranges, Some(framing))
            };
            (r, Some(n))
        }
    }
}

fn set_len_type(r: &mut Response, len: u64, content_type: HeaderValue) {
    let h = r.headers_mut();
    h.insert(header::CONTENT_LENGTH, HeaderValue::from(len));
    h.insert(header::CONTENT_TYPE, content_type);
}

fn body_response(
    state: &AppState,
    a: &Asset,
    status: StatusCode,
    ranges: Vec<ByteRange>,
    framing: Option<Framing>,
) -> Response {
    if let Some(data) = &a.data
        && let Some(r) = from_memory(state, a, data, status, &ranges, framing.as_ref())
    {
        return r;
    }
    let file = match a.open() {
        Ok(f) => f,
        Err(e) => {
            tracing::error!(asset = %a.rel, error = %e, "cannot open asset");
            return error(StatusCode::INTERNAL_SERVER_ERROR, "asset unreadable\n");
        }
    };
    let (len, ctype) = match &framing {
        Some(f) => (
            multipart_len(&f.boundary, f.content_type, &ranges, f.total),
            state.inner.multipart_type.clone(),
        ),
        None => (ranges.iter().map(|r| r.len()).sum(), a.content_type_header.clone()),
    };
    let body = if len <= INLINE_MAX {
        match build_inline(file.as_ref(), &ranges, framing.as_ref(), len as usize) {
            Ok(bytes) => Body::from(bytes),
            Err(e) => {
                tracing::error!(asset = %a.rel, error = %e, "cannot read asset");
                return error(StatusCode::INTERNAL_SERVER_ERROR, "asset unreadable\n");
            }
        }
    } else {
        Body::new(RangeBody::new(file, ranges, framing))
    };
    let mut r = header_response(status, a);
    *r.body_mut() = body;
    set_len_type(&mut r, len, ctype);
    r
}

/// The response from an asset held in memory: a single range is a slice of the shared bytes (no
/// copy, whatever its length); a small multipart body is assembled from slices. `None` sends the
/// request to the file path (large multipart bodies stream from disk).
fn from_memory(
    state: &AppState,
    a: &Asset,
    data: &Bytes,
    status: StatusCode,
    ranges: &[ByteRange],
    framing: Option<&Framing>,
) -> Option<Response> {
    let slice = |r: ByteRange| data.get(r.start as usize..r.end as usize);
    let (body, len, ctype) = match (ranges, framing) {
        ([r], None) => (data.slice_ref(slice(*r)?), r.len(), a.content_type_header.clone()),
        (_, Some(f)) => {
            let len = multipart_len(&f.boundary, f.content_type, ranges, f.total);
            if len > INLINE_MAX {
                return None;
            }
            let mut out = Vec::with_capacity(len as usize);
            for (i, r) in ranges.iter().enumerate() {
                out.extend_from_slice(part_header(&f.boundary, f.content_type, i, *r, f.total).as_bytes());
                out.extend_from_slice(slice(*r)?);
            }
            out.extend_from_slice(closing(&f.boundary).as_bytes());
            (Bytes::from(out), len, state.inner.multipart_type.clone())
        }
        _ => return None,
    };
    let mut r = header_response(status, a);
    *r.body_mut() = Body::from(body);
    set_len_type(&mut r, len, ctype);
    Some(r)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn conditional_matching() {
        let e = "\"abc\"";
        assert!(none_match(b"\"abc\"", e));
        assert!(none_match(b"W/\"abc\"", e));
        assert!(none_match(b"\"x\", \"abc\"", e));
        assert!(none_match(b"*", e));
        assert!(!none_match(b"\"abcd\"", e));
        assert!(if_range_ok(b"\"abc\"", e));
        assert!(!if_range_ok(b"W/\"abc\"", e));
        assert!(!if_range_ok(b"Mon, 01 Jan 2024 00:00:00 GMT", e));
    }
}
