//! `GET /api/scenes/{id}/live`: one WebSocket per viewer carrying presence (camera poses) and
//! edit notifications.
//!
//! Messages are JSON text frames. Client → server: `{"type":"pose","position":[x,y,z],
//! "orientation":[x,y,z,w]}`. Server → client: `welcome` (own id, scene version, other viewers'
//! poses), `join`, `leave`, `presence` (another viewer's pose), `version` (an edit published a new
//! version), `deleted`.
//!
//! Bounds: every scene has one broadcast queue of `live_queue` messages shared by its viewers; a
//! viewer that falls behind by more than that, or whose socket does not take a message within
//! `send_timeout`, is closed with code 1008 and a reason, so a slow viewer never grows the
//! server's memory. Poses are forwarded at most once per `pose_interval` per viewer (the latest
//! wins); a viewer sending more than [`MAX_CLIENT_MSGS_PER_S`] messages a second is closed.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use axum::extract::ws::{CloseFrame, Message, WebSocket, WebSocketUpgrade};
use axum::extract::{Path, RawQuery, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use serde_json::json;
use tokio::sync::{Notify, broadcast};

use super::AppState;
use super::scenes::{ApiError, read_access};

/// Largest client message, bytes.
pub const MAX_CLIENT_MSG: usize = 4096;
/// Most client messages per second before the viewer is closed.
pub const MAX_CLIENT_MSGS_PER_S: u32 = 100;
/// Close code for a viewer that broke a limit (policy violation).
pub const CLOSE_POLICY: u16 = 1008;
/// Close code when the server shuts down ("going away").
pub const CLOSE_GOING_AWAY: u16 = 1001;

/// A camera pose.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Camera position, metres.
    pub position: [f32; 3],
    /// Camera orientation quaternion x, y, z, w.
    pub orientation: [f32; 4],
}

#[derive(Debug, Deserialize)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
enum ClientMsg {
    Pose { position: [f32; 3], orientation: [f32; 4] },
}

#[derive(Debug)]
struct Msg {
    from: u64,
    text: String,
    close_after: bool,
}

/// One scene's live state.
#[derive(Debug)]
struct Hub {
    tx: broadcast::Sender<Arc<Msg>>,
    poses: Mutex<HashMap<u64, Option<Pose>>>,
}

/// Every scene's live state.
#[derive(Debug, Default)]
pub struct Hubs {
    by_scene: Mutex<HashMap<String, Arc<Hub>>>,
    next_viewer: AtomicU64,
    /// Accepted upgrades whose viewer task has not finished, so shutdown can wait for their
    /// close frames before the runtime (and every socket) is dropped.
    open: Arc<OpenViewers>,
}

#[derive(Debug, Default)]
struct OpenViewers {
    count: AtomicUsize,
    none_left: Notify,
}

/// Held for one viewer from its upgrade to the end of its task.
#[derive(Debug)]
struct OpenViewer(Arc<OpenViewers>);

impl Drop for OpenViewer {
    fn drop(&mut self) {
        if self.0.count.fetch_sub(1, Ordering::AcqRel) == 1 {
            self.0.none_left.notify_waiters();
        }
    }
}

impl Hubs {
    fn open_viewer(&self) -> OpenViewer {
        self.open.count.fetch_add(1, Ordering::AcqRel);
        OpenViewer(Arc::clone(&self.open))
    }

    /// Resolves once every accepted viewer's task has finished (after shutdown, once each has
    /// been sent its close frame).
    pub async fn all_closed(&self) {
        loop {
            // Created before the check: `notify_waiters` reaches it even before it is polled.
            let none_left = self.open.none_left.notified();
            if self.open.count.load(Ordering::Acquire) == 0 {
                return;
            }
            none_left.await;
        }
    }

    fn hub(&self, scene: &str, queue: usize) -> Arc<Hub> {
        let mut m = self.by_scene.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        m.entry(scene.to_string())
            .or_insert_with(|| {
                Arc::new(Hub {
                    tx: broadcast::channel(queue.max(1)).0,
                    poses: Mutex::new(HashMap::new()),
                })
            })
            .clone()
    }

    fn existing(&self, scene: &str) -> Option<Arc<Hub>> {
        self.by_scene
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .get(scene)
            .cloned()
    }

    /// Viewers connected to a scene.
    pub fn viewers(&self, scene: &str) -> usize {
        self.existing(scene).map_or(0, |h| {
            h.poses.lock().unwrap_or_else(std::sync::PoisonError::into_inner).len()
        })
    }

    fn send(&self, scene: &str, text: String, close_after: bool) {
        if let Some(h) = self.existing(scene) {
            // No receivers is fine.
            let _ = h.tx.send(Arc::new(Msg {
                from: 0,
                text,
                close_after,
            }));
        }
    }

    /// Tells a scene's viewers that a new version was published.
    pub fn notify_version(&self, scene: &str, version: u64) {
        let text = json!({
            "type": "version",
            "version": version,
            "manifest": format!("/api/scenes/{scene}/manifest?version={version}"),
        });
        self.send(scene, text.to_string(), false);
    }

    /// Tells a scene's viewers it was deleted, and closes them.
    pub fn notify_deleted(&self, scene: &str) {
        self.send(scene, json!({"type": "deleted"}).to_string(), true);
    }

    fn leave(&self, scene: &str, hub: &Hub, viewer: u64) {
        let empty = {
            let mut p = hub.poses.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            p.remove(&viewer);
            p.is_empty()
        };
        let _ = hub.tx.send(Arc::new(Msg {
            from: viewer,
            text: json!({"type": "leave", "viewer": viewer}).to_string(),
            close_after: false,
        }));
        if empty {
            let mut m = self.by_scene.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            // Drop the hub unless someone joined meanwhile.
            if m.get(scene).is_some_and(|h| {
                h.poses
                    .lock()
                    .unwrap_or_else(std::sync::PoisonError::into_inner)
                    .is_empty()
            }) {
                m.remove(scene);
            }
        }
    }
}

/// The WebSocket endpoint.
pub async fn live(
    State(state): State<AppState>,
    Path(id): Path<String>,
    RawQuery(query): RawQuery,
    headers: HeaderMap,
    ws: WebSocketUpgrade,
) -> Result<Response, ApiError> {
    let meta = read_access(&state, &id, &headers, query.as_deref()).await?;
    let cfg = &state.inner.config;
    if state.inner.live.viewers(&id) >= cfg.max_viewers_per_scene {
        return Err(ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            format!("scene {id} has the maximum of {} viewers", cfg.max_viewers_per_scene),
        ));
    }
    let version = meta.version;
    let open = state.inner.live.open_viewer();
    Ok(ws
        .max_message_size(MAX_CLIENT_MSG)
        .max_frame_size(MAX_CLIENT_MSG)
        .on_upgrade(move |socket| async move {
            run_viewer(state, id, version, socket).await;
            drop(open);
        })
        .into_response())
}

async fn close(socket: &mut WebSocket, code: u16, reason: &str, timeout: std::time::Duration) {
    let frame = CloseFrame {
        code,
        reason: reason.into(),
    };
    let _ = tokio::time::timeout(timeout, socket.send(Message::Close(Some(frame)))).await;
}

async fn run_viewer(state: AppState, scene: String, version: u64, mut socket: WebSocket) {
    let inner = &state.inner;
    let cfg = &inner.config;
    let hubs = &inner.live;
    let viewer = hubs.next_viewer.fetch_add(1, Ordering::Relaxed) + 1;
    let hub = hubs.hub(&scene, cfg.live_queue);
    let mut rx = hub.tx.subscribe();
    let others: Vec<_> = {
        let mut p = hub.poses.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let others = p.iter().map(|(v, pose)| json!({"viewer": v, "pose": pose})).collect();
        p.insert(viewer, None);
        others
    };
    inner.metrics.viewers(1);
    tracing::info!(scene = %scene, viewer, "viewer joined");
    let _ = hub.tx.send(Arc::new(Msg {
        from: viewer,
        text: json!({"type": "join", "viewer": viewer}).to_string(),
        close_after: false,
    }));
    let welcome = json!({"type": "welcome", "viewer": viewer, "scene": scene, "version": version, "viewers": others});
    let mut shutdown = inner.shutdown.clone();
    let mut tick = tokio::time::interval(cfg.pose_interval);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut pending: Option<Pose> = None;
    let (mut window_start, mut window_count) = (tokio::time::Instant::now(), 0u32);
    let reason = if tokio::time::timeout(cfg.send_timeout, socket.send(Message::Text(welcome.to_string().into())))
        .await
        .is_ok()
    {
        loop {
            tokio::select! {
                m = socket.recv() => {
                    let text = match m {
                        Some(Ok(Message::Text(t))) => t,
                        Some(Ok(Message::Binary(_))) => break Some("binary messages are not accepted"),
                        Some(Ok(Message::Ping(_) | Message::Pong(_))) => continue,
                        Some(Ok(Message::Close(_)) | Err(_)) | None => break None,
                    };
                    let now = tokio::time::Instant::now();
                    if now.duration_since(window_start).as_secs() >= 1 {
                        (window_start, window_count) = (now, 0);
                    }
                    window_count += 1;
                    if window_count > MAX_CLIENT_MSGS_PER_S {
                        break Some("too many messages");
                    }
                    match serde_json::from_str::<ClientMsg>(text.as_str()) {
                        Ok(ClientMsg::Pose { position, orientation }) if position.iter().chain(&orientation).all(|v| v.is_finite()) => {
                            pending = Some(Pose { position, orientation });
                        }
                        _ => break Some("invalid message: expected {\"type\":\"pose\",\"position\":[x,y,z],\"orientation\":[x,y,z,w]} with finite numbers"),
                    }
                }
                _ = tick.tick() => {
                    if let Some(p) = pending.take() {
                        hub.poses.lock().unwrap_or_else(std::sync::PoisonError::into_inner).insert(viewer, Some(p));
                        let text = json!({"type": "presence", "viewer": viewer, "pose": p}).to_string();
                        let _ = hub.tx.send(Arc::new(Msg { from: viewer, text, close_after: false }));
                    }
                }
                m = rx.recv() => match m {
                    Ok(m) => {
                        if m.from == viewer {
                            continue;
                        }
                        match tokio::time::timeout(cfg.send_timeout, socket.send(Message::Text(m.text.clone().into()))).await {
                            Ok(Ok(())) if m.close_after => break Some("scene deleted"),
                            Ok(Ok(())) => {}
                            Ok(Err(_)) => break None,
                            Err(_) => {
                                inner.metrics.dropped_slow();
                                break Some("viewer too slow: a message was not taken in time; reconnect");
                            }
                        }
                    }
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        inner.metrics.dropped_slow();
                        tracing::warn!(scene = %scene, viewer, missed = n, "dropping slow viewer");
                        break Some("viewer too slow: fell behind the scene's message queue; reconnect");
                    }
                    Err(broadcast::error::RecvError::Closed) => break None,
                },
                _ = shutdown.changed() => {
                    close(&mut socket, CLOSE_GOING_AWAY, "server shutting down", cfg.send_timeout).await;
                    break None;
                }
            }
        }
    } else {
        None
    };
    if let Some(reason) = reason {
        close(&mut socket, CLOSE_POLICY, reason, cfg.send_timeout).await;
    }
    hubs.leave(&scene, &hub, viewer);
    inner.metrics.viewers(-1);
    tracing::info!(scene = %scene, viewer, reason = reason.unwrap_or("closed"), "viewer left");
}
