//! The HTTP server: range-addressed assets, the scene API, live presence, health and metrics.
//!
//! Routes (see `docs/server.md`):
//! - `GET|HEAD|OPTIONS /assets/{path}`: immutable content-addressed files, by byte range.
//! - `GET|POST /api/scenes`, `GET|DELETE /api/scenes/{id}`, `GET /api/scenes/{id}/manifest`,
//!   `GET|POST /api/scenes/{id}/instances`, `GET /api/scenes/{id}/versions`,
//!   `POST /api/scenes/{id}/pins`, `DELETE /api/scenes/{id}/pins/{version}`,
//!   `GET|PUT|DELETE /api/scenes/{id}/flight-table`, `GET|PUT|DELETE /api/scenes/{id}/terrain`,
//!   `GET /api/scenes/{id}/live` (WebSocket).
//! - `GET /healthz`, `GET /metrics`.

pub mod assets;
pub mod auth;
pub mod conn;
pub mod edits;
pub mod flight_table;
pub mod instances;
pub mod live;
mod live_relay;
pub mod metrics;
pub mod multipart;
pub mod publish;
pub mod quota;
pub mod range;
mod rate_limit;
pub mod scenes;
pub mod terrain;
pub mod versions;

use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::Router;
use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::{HeaderValue, Method, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use tokio::sync::watch;

use crate::store::scenes::Limits;
use crate::store::{AssetStore, SceneStore};

/// Largest API request body (but a terrain upload's, [`terrain::MAX_TERRAIN_BODY`]).
pub const MAX_BODY: usize = 4 << 20;

/// Places for terrain uploads being read and handled ([`terrain::MAX_TERRAIN_UPLOADS`]).
static TERRAIN_UPLOADS: std::sync::LazyLock<tokio::sync::Semaphore> =
    std::sync::LazyLock::new(|| tokio::sync::Semaphore::new(terrain::MAX_TERRAIN_UPLOADS));

/// Tunables of the HTTP layer.
#[derive(Debug, Clone)]
pub struct HttpConfig {
    /// Presence publications a viewer may fall behind before it is closed as too slow.
    pub live_queue: usize,
    /// Interval between a scene's presence publications (stretched under the fan-out cap).
    pub pose_interval: Duration,
    /// Longest a viewer's socket may take to accept one message.
    pub send_timeout: Duration,
    /// Most viewers on one scene.
    pub max_viewers_per_scene: usize,
    /// Longest a request head may take to arrive: from accept on a new connection, from its first
    /// byte on a kept-alive one.
    pub header_timeout: Duration,
    /// Longest an API request body may take to arrive, whole (408 after).
    pub body_timeout: Duration,
    /// Longest a kept-alive connection may wait for its next request.
    pub idle_timeout: Duration,
    /// Longest a response write may make no progress (a client that does not read).
    pub write_timeout: Duration,
    /// Most open connections, WebSockets included (see [`conn`] for what happens at the bound).
    pub max_connections: usize,
    /// Who may create scenes. The default here is open (in-process uses and tests); `serve`
    /// defaults to a creation token.
    pub creation: quota::Creation,
    /// Quotas per owner and version retention.
    pub limits: Limits,
    /// Scene creations per owner and per client address.
    pub create_rate: quota::Rate,
    /// Edits (and pins) per scene and per client address.
    pub edit_rate: quota::Rate,
}

impl Default for HttpConfig {
    fn default() -> Self {
        Self {
            live_queue: 256,
            pose_interval: Duration::from_millis(100),
            send_timeout: Duration::from_secs(5),
            max_viewers_per_scene: 256,
            header_timeout: Duration::from_secs(10),
            body_timeout: Duration::from_secs(30),
            idle_timeout: Duration::from_mins(1),
            write_timeout: Duration::from_mins(1),
            max_connections: conn::default_max_connections(),
            creation: quota::Creation::Open,
            limits: Limits::default(),
            create_rate: quota::Rate::per_minute(10.0),
            edit_rate: quota::Rate::per_second(10.0),
        }
    }
}

/// What every handler shares.
#[derive(Debug)]
pub struct Inner {
    /// The asset files.
    pub assets: Arc<AssetStore>,
    /// The scene database.
    pub scenes: Arc<dyn SceneStore>,
    /// Live viewers.
    pub live: live::Hubs,
    /// Instance lists being streamed.
    pub instance_tables: instances::InstanceTables,
    /// The packs of the scenes edited last, kept for the next edit.
    pub drafts: crate::store::pack_draft::PackDrafts,
    /// Metrics.
    pub metrics: metrics::Metrics,
    /// Multipart boundary of this process.
    pub boundary: Arc<str>,
    /// `multipart/byteranges; boundary=…` as a header value, built once.
    pub multipart_type: HeaderValue,
    /// Scene creations' token buckets.
    pub create_limiter: quota::RateLimiter,
    /// Edits' token buckets.
    pub edit_limiter: quota::RateLimiter,
    /// Tunables.
    pub config: HttpConfig,
    /// Becomes `true` at shutdown (closes WebSockets).
    pub shutdown: watch::Receiver<bool>,
}

/// Cheaply cloneable handle on [`Inner`].
#[derive(Debug, Clone)]
pub struct AppState {
    /// The shared state.
    pub inner: Arc<Inner>,
}

/// Handle that starts the shutdown of live connections.
#[derive(Debug)]
pub struct Shutdown(watch::Sender<bool>);

impl Shutdown {
    /// Tells every WebSocket to close ("going away").
    pub fn trigger(&self) {
        let _ = self.0.send(true);
    }
}

impl AppState {
    /// New state over the given stores.
    pub fn new(assets: Arc<AssetStore>, scenes: Arc<dyn SceneStore>, config: HttpConfig) -> (Self, Shutdown) {
        let (tx, rx) = watch::channel(false);
        let boundary = multipart::new_boundary();
        // The boundary is hex digits: always a valid header value.
        let multipart_type = HeaderValue::from_str(&format!("multipart/byteranges; boundary={boundary}"))
            .unwrap_or_else(|_| HeaderValue::from_static("multipart/byteranges"));
        // Replicas on one store tell each other of their viewers.
        let relay = scenes.shared().then(|| {
            let store = Arc::clone(&scenes);
            live::Relay(Arc::new(move |payload: String| store.relay_presence(payload)))
        });
        let inner = Inner {
            assets,
            scenes,
            live: live::Hubs::new(relay),
            instance_tables: instances::InstanceTables::default(),
            drafts: crate::store::pack_draft::PackDrafts::default(),
            metrics: metrics::Metrics::default(),
            boundary: Arc::from(boundary),
            multipart_type,
            create_limiter: quota::RateLimiter::new(config.create_rate),
            edit_limiter: quota::RateLimiter::new(config.edit_rate),
            config,
            shutdown: rx,
        };
        let inner = Arc::new(inner);
        // Other replicas' edits and deletions reach this replica's live viewers.
        let weak = Arc::downgrade(&inner);
        inner.scenes.watch(Box::new(move |change| {
            let Some(inner) = weak.upgrade() else { return };
            match change {
                crate::store::scenes::SceneChange::Version { scene, version } => {
                    inner.live.notify_version(&scene, version);
                }
                crate::store::scenes::SceneChange::Deleted { scene } => inner.live.notify_deleted(&scene),
                // On the listener's thread, outside the runtime: the store may block here.
                crate::store::scenes::SceneChange::Resync => {
                    for scene in inner.live.watched() {
                        match inner.scenes.get(&scene) {
                            Ok(meta) => inner.live.resync(&scene, meta.map(|m| m.version)),
                            Err(e) => tracing::warn!(scene = %scene, error = %e, "resync after missed notifications"),
                        }
                    }
                }
                crate::store::scenes::SceneChange::Presence { payload } => {
                    let cfg = &inner.config;
                    inner.live.remote(&payload, cfg.live_queue, cfg.pose_interval);
                }
            }
        }));
        (Self { inner }, Shutdown(tx))
    }
}

/// Counts API requests and adds CORS headers to every API response; answers preflights.
async fn api_layer(State(state): State<AppState>, req: Request, next: Next) -> Response {
    if req.method() == Method::OPTIONS {
        return assets::preflight();
    }
    let t0 = Instant::now();
    let route = if req.uri().path().ends_with("/live") {
        metrics::Route::Live
    } else {
        metrics::Route::Api
    };
    let mut r = next.run(req).await;
    assets::cors(r.headers_mut());
    let len = r
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok()?.parse().ok())
        .unwrap_or(0);
    state
        .inner
        .metrics
        .request(route, r.status().as_u16(), len, t0.elapsed());
    r
}

/// Reads an API request's body whole before its handler, within [`MAX_BODY`] (a terrain upload:
/// [`terrain::MAX_TERRAIN_BODY`], at most [`terrain::MAX_TERRAIN_UPLOADS`] at once, held until
/// its answer) and the body timeout, so that a body sent too slowly (408) or too large (413) gets
/// the API's JSON error and the connection is closed (its unread rest would otherwise be parsed as
/// the next request).
async fn read_body(State(state): State<AppState>, req: Request, next: Next) -> Response {
    use http_body::Body as _;
    if req.body().is_end_stream() {
        return next.run(req).await;
    }
    let upload = terrain::is_upload(req.method(), req.uri().path());
    let max = if upload { terrain::MAX_TERRAIN_BODY } else { MAX_BODY };
    let declared = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok()?.parse::<u64>().ok());
    if declared.is_some_and(|n| n > max as u64) {
        return body_error(StatusCode::PAYLOAD_TOO_LARGE, too_large(max));
    }
    let _place = if upload {
        let Ok(p) = TERRAIN_UPLOADS.try_acquire() else {
            let mut r = scenes::ApiError {
                retry_after: Some(1),
                ..scenes::ApiError::new(
                    StatusCode::SERVICE_UNAVAILABLE,
                    "too many terrain uploads at once; try again shortly",
                )
            }
            .into_response();
            r.headers_mut()
                .insert(header::CONNECTION, HeaderValue::from_static("close"));
            return r;
        };
        Some(p)
    } else {
        None
    };
    enum Fault {
        TooLarge,
        Unreadable,
    }
    let (parts, mut body) = req.into_parts();
    let limit = state.inner.config.body_timeout;
    let read = async {
        // What the client declares is not trusted for more than a first allocation.
        let mut out = Vec::with_capacity(declared.map_or(0, |n| n.min(64 << 10) as usize));
        while let Some(frame) = std::future::poll_fn(|cx| std::pin::Pin::new(&mut body).poll_frame(cx)).await {
            let Ok(data) = frame.map_err(|_| Fault::Unreadable)?.into_data() else {
                continue;
            };
            if out.len() + data.len() > max {
                return Err(Fault::TooLarge);
            }
            out.extend_from_slice(&data);
        }
        Ok(out)
    };
    match tokio::time::timeout(limit, read).await {
        Ok(Ok(bytes)) => {
            next.run(Request::from_parts(parts, axum::body::Body::from(bytes)))
                .await
        }
        Ok(Err(Fault::TooLarge)) => body_error(StatusCode::PAYLOAD_TOO_LARGE, too_large(max)),
        Ok(Err(Fault::Unreadable)) => body_error(StatusCode::BAD_REQUEST, "the request body could not be read".into()),
        Err(_) => {
            state.inner.metrics.timeout(metrics::Stage::Body);
            let secs = limit.as_secs_f64();
            body_error(
                StatusCode::REQUEST_TIMEOUT,
                format!("the request body did not arrive within {secs} s"),
            )
        }
    }
}

fn too_large(max: usize) -> String {
    format!("request body over {max} bytes")
}

/// The API's JSON error, closing the connection.
fn body_error(status: StatusCode, message: String) -> Response {
    let mut r = scenes::ApiError::new(status, message).into_response();
    r.headers_mut()
        .insert(header::CONNECTION, HeaderValue::from_static("close"));
    r
}

/// RFC 9112 §3.2: an HTTP/1.1 request without a `Host` header, or with more than one, is answered
/// 400. Applied by [`serve`] on the wire (in-process tests of [`router`] build requests without
/// one).
async fn host_check(req: Request, next: Next) -> Response {
    let hosts = req.headers().get_all(header::HOST).iter().count();
    if req.version() == axum::http::Version::HTTP_11 && hosts != 1 {
        return (
            axum::http::StatusCode::BAD_REQUEST,
            "bad request: an HTTP/1.1 request needs exactly one Host header\n",
        )
            .into_response();
    }
    next.run(req).await
}

/// 200 `ok`; 503 while the scene database cannot be reached (assets are still served).
async fn healthz(State(state): State<AppState>) -> (StatusCode, &'static str) {
    if state.inner.scenes.available() {
        (StatusCode::OK, "ok\n")
    } else {
        (StatusCode::SERVICE_UNAVAILABLE, "scene database unavailable\n")
    }
}

async fn metrics_text(State(state): State<AppState>) -> Response {
    let mut r = state.inner.metrics.render().into_response();
    r.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/plain; version=0.0.4; charset=utf-8"),
    );
    r
}

async fn not_found(State(state): State<AppState>) -> Response {
    state
        .inner
        .metrics
        .request(metrics::Route::Other, 404, 0, Duration::ZERO);
    (axum::http::StatusCode::NOT_FOUND, "not found\n").into_response()
}

/// The router.
pub fn router(state: AppState) -> Router {
    use axum::routing::{any, post};
    let api = Router::new()
        .route("/api/scenes", get(scenes::list).post(scenes::create))
        .route("/api/scenes/{id}", get(scenes::get).delete(scenes::delete))
        .route("/api/scenes/{id}/manifest", get(scenes::manifest))
        .route(
            "/api/scenes/{id}/instances",
            get(scenes::instances).merge(post(scenes::edit)),
        )
        .route("/api/scenes/{id}/versions", get(versions::list))
        .route("/api/scenes/{id}/pins", post(versions::pin))
        .route(
            "/api/scenes/{id}/pins/{version}",
            axum::routing::delete(versions::unpin),
        )
        .route(
            "/api/scenes/{id}/flight-table",
            get(flight_table::get)
                .put(flight_table::put)
                .delete(flight_table::delete),
        )
        .route(
            "/api/scenes/{id}/terrain",
            get(terrain::get)
                .put(terrain::put)
                .delete(terrain::delete)
                .layer(DefaultBodyLimit::max(terrain::MAX_TERRAIN_BODY)),
        )
        .route("/api/scenes/{id}/live", get(live::live))
        .layer(DefaultBodyLimit::max(MAX_BODY))
        .layer(middleware::from_fn_with_state(state.clone(), read_body))
        .layer(middleware::from_fn_with_state(state.clone(), api_layer));
    Router::new()
        .route("/assets/{*path}", any(assets::asset))
        .route("/healthz", get(healthz))
        .route("/metrics", get(metrics_text))
        .merge(api)
        .fallback(not_found)
        .with_state(state)
}

/// Serves `router(state)` on `listener` (with the deadlines and connection bound of [`conn`])
/// until `shutdown` resolves; then closes live viewers and lets requests in flight finish.
pub async fn serve(
    listener: tokio::net::TcpListener,
    state: AppState,
    stop: Shutdown,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let app = router(state.clone()).layer(middleware::from_fn(host_check));
    let signal = async {
        shutdown.await;
        tracing::info!("shutting down: closing viewers, finishing requests in flight");
        stop.trigger();
    };
    conn::serve(listener, app, &state, signal).await;
    // Upgraded sockets are outside the graceful shutdown: wait for their close frames, or
    // returning drops them mid-handshake. A viewer's sends are each bounded by `send_timeout`,
    // and after shutdown it makes at most three: the welcome it may be sending, one broadcast
    // message (its loop may still pick one), and its close frame.
    let wait = state.inner.config.send_timeout.saturating_mul(3);
    if tokio::time::timeout(wait, state.inner.live.all_closed()).await.is_err() {
        tracing::warn!("shutdown: some live viewers did not close in {wait:?}");
    }
    Ok(())
}
