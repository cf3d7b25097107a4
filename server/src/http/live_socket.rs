//! The WebSocket side of the live endpoint: the upgrade, one task per viewer, frames in and
//! batches out, closes (the contract is in the parent module's doc comment).

use axum::extract::ws::{CloseFrame, Message, Utf8Bytes, WebSocket, WebSocketUpgrade};
use axum::extract::{Path, RawQuery, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use futures_util::SinkExt;
use serde_json::json;

use super::super::AppState;
use super::super::rate_limit::RateLimit;
use super::super::scenes::{ApiError, read_access};
use super::{CLOSE_GOING_AWAY, CLOSE_POLICY, ClientMsg, Duration, MAX_CLIENT_MSG, MAX_REASON, Pose};

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
    // Frames over the limit fail in the WebSocket layer as soon as their header is read, and
    // come back from `recv` as an error that the viewer task answers with a 1008 close.
    Ok(ws
        .max_message_size(MAX_CLIENT_MSG)
        .max_frame_size(MAX_CLIENT_MSG)
        .on_upgrade(move |socket| async move {
            run_viewer(state, id, version, socket).await;
            drop(open);
        })
        .into_response())
}

/// Why a viewer's task ends.
#[derive(Debug, PartialEq, Eq)]
pub(super) enum End {
    /// The peer closed, or the transport failed: nothing more to send.
    Gone,
    /// Close with 1001 (shutdown).
    GoingAway,
    /// Close with 1008 and this reason.
    Policy(String),
}

/// The close reason for an error from the WebSocket layer, `None` when the transport failed
/// (then no close frame can be delivered). Cut to [`MAX_REASON`] bytes on a char boundary.
pub(super) fn frame_error_reason(e: &(dyn std::error::Error + 'static)) -> Option<String> {
    let mut cause = Some(e);
    while let Some(c) = cause {
        if c.is::<std::io::Error>() {
            return None;
        }
        cause = c.source();
    }
    Some(clip_reason(format!("invalid frame: {e}")))
}

pub(super) fn clip_reason(mut s: String) -> String {
    if s.len() > MAX_REASON {
        let mut end = MAX_REASON;
        while !s.is_char_boundary(end) {
            end -= 1;
        }
        s.truncate(end);
    }
    s
}

/// Counts client frames in whole-second windows.
/// What one received frame means for the viewer: a pose, nothing, or the end.
pub(super) fn on_frame(m: Option<Result<Message, axum::Error>>, limit: &mut RateLimit) -> Result<Option<Pose>, End> {
    let m = match m {
        Some(Ok(Message::Close(_))) | None => return Err(End::Gone),
        Some(Err(e)) => return Err(frame_error_reason(&e).map_or(End::Gone, End::Policy)),
        Some(Ok(m)) => m,
    };
    // Every frame counts, control frames included: a ping flood costs a pong each.
    if !limit.admit() {
        return Err(End::Policy("too many messages".into()));
    }
    let text = match m {
        Message::Text(t) => t,
        Message::Binary(_) => return Err(End::Policy("binary messages are not accepted".into())),
        Message::Ping(_) | Message::Pong(_) | Message::Close(_) => return Ok(None),
    };
    match serde_json::from_str::<ClientMsg>(text.as_str()) {
        Ok(ClientMsg::Pose { position, orientation }) if position.iter().chain(&orientation).all(|v| v.is_finite()) => {
            Ok(Some(Pose { position, orientation }))
        }
        _ => Err(End::Policy(
            "invalid message: expected {\"type\":\"pose\",\"position\":[x,y,z],\"orientation\":[x,y,z,w]} with finite numbers"
                .into(),
        )),
    }
}

/// Writes `msgs` with one flush at the end, all within `timeout`.
async fn send_batch(socket: &mut WebSocket, msgs: Vec<Utf8Bytes>, timeout: Duration) -> Result<(), End> {
    let write = async {
        for m in msgs {
            socket.feed(Message::Text(m)).await?;
        }
        socket.flush().await
    };
    match tokio::time::timeout(timeout, write).await {
        Ok(Ok(())) => Ok(()),
        Ok(Err(_)) => Err(End::Gone),
        Err(_) => Err(End::Policy(format!(
            "viewer too slow: its socket did not take one update within {timeout:?}; reconnect"
        ))),
    }
}

async fn close(socket: &mut WebSocket, code: u16, reason: String, timeout: Duration) {
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
    let viewer = hubs.new_viewer_id();
    // Viewer tasks run on the runtime: a hub can always be made here.
    let Some((hub, others, mut seen)) = hubs.join(&scene, viewer, version, cfg.live_queue, cfg.pose_interval) else {
        return;
    };
    // The first wake-up sends whatever was published after the join's snapshot (`seen`).
    let mut published = hub.published.subscribe();
    published.mark_changed();
    inner.metrics.viewers(1);
    tracing::info!(scene = %scene, viewer, "viewer joined");
    let welcome = json!({"type": "welcome", "viewer": viewer, "scene": scene, "version": version, "viewers": others});
    let mut shutdown = inner.shutdown.clone();
    let mut limit = RateLimit::new();
    let end = match send_batch(&mut socket, vec![welcome.to_string().into()], cfg.send_timeout).await {
        Err(end) => end,
        Ok(()) => loop {
            tokio::select! {
                m = socket.recv() => match on_frame(m, &mut limit) {
                    Ok(Some(pose)) => hub.pose(viewer, pose),
                    Ok(None) => {}
                    Err(end) => break end,
                },
                changed = published.changed() => {
                    if changed.is_err() {
                        break End::Gone;
                    }
                    let wake = match hub.wake(viewer, &mut seen) {
                        Ok(w) => w,
                        Err(lag) => {
                            inner.metrics.dropped_slow();
                            tracing::warn!(scene = %scene, viewer, lag, "dropping slow viewer");
                            break End::Policy(format!("viewer too slow: fell {lag} updates behind the scene; reconnect"));
                        }
                    };
                    if wake.msgs.is_empty() {
                        continue;
                    }
                    match send_batch(&mut socket, wake.msgs, cfg.send_timeout).await {
                        Ok(()) if wake.deleted => break End::Policy("scene deleted".into()),
                        Ok(()) => {}
                        Err(end) => {
                            if matches!(end, End::Policy(_)) {
                                inner.metrics.dropped_slow();
                                tracing::warn!(scene = %scene, viewer, "dropping slow viewer");
                            }
                            break end;
                        }
                    }
                },
                _ = shutdown.changed() => break End::GoingAway,
            }
        },
    };
    let closing = match &end {
        End::Gone => None,
        End::GoingAway => Some((CLOSE_GOING_AWAY, "server shutting down".to_string())),
        End::Policy(reason) => Some((CLOSE_POLICY, reason.clone())),
    };
    if let Some((code, reason)) = closing {
        close(&mut socket, code, reason, cfg.send_timeout).await;
    }
    hubs.leave(&scene, &hub, viewer);
    inner.metrics.viewers(-1);
    let reason = match &end {
        End::Gone => "closed",
        End::GoingAway => "shutdown",
        End::Policy(r) => r.as_str(),
    };
    tracing::info!(scene = %scene, viewer, reason, "viewer left");
}
