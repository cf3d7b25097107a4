//! `GET /api/scenes/{id}/live`: one WebSocket per viewer carrying presence (camera poses) and
//! edit notifications.
//!
//! Contract. Messages are JSON text frames. Client → server: `{"type":"pose","position":[x,y,z],
//! "orientation":[x,y,z,w]}` (finite numbers). Server → client: `welcome` (own id, scene,
//! version, `viewers`: the others as `{viewer, pose}`, pose `null` until one was published),
//! `join` / `leave` `{viewer}`, `presence` `{viewer, pose}` (another viewer's latest pose),
//! `version` `{version, manifest}` (an edit published a new version), `deleted` (then a close).
//! A viewer never gets its own pose back.
//!
//! How presence sheds load, the way presence servers do it. An arriving pose only overwrites its
//! viewer's slot in the scene (latest wins). A per-scene ticker publishes the slots that changed
//! every `pose_interval`, an interval stretched so that the scene delivers at most
//! [`MAX_FANOUT_PER_S`] poses a second (poses published × other viewers). Each publication wakes
//! every viewer once; the viewer writes, in one flush, the joins, poses and leaves published since
//! its last wake-up (one pose per other viewer, the latest). So the work follows ticks × viewers,
//! never poses received × viewers, and a viewer that is slow to take its messages gets fewer,
//! fuller wake-ups instead of a queue: what the server holds for a viewer is its slot, the one
//! batch being written and what the kernel's socket buffers take.
//!
//! Closes, each of one viewer only, with code 1008 (policy) and a reason: a socket that does not
//! take one wake-up's messages within `send_timeout`, or a viewer more than `live_queue`
//! publications behind ("viewer too slow…", counted in `canopy_live_dropped_slow_total`); more
//! than [`MAX_CLIENT_MSGS_PER_S`] frames a second (a token bucket holding one second's worth),
//! pings, pongs and binary frames included
//! ("too many messages"); a binary frame; a text message that is not a valid pose ("invalid
//! message…"); a frame the WebSocket layer rejects ("invalid frame: …": over [`MAX_CLIENT_MSG`]
//! bytes, invalid UTF-8 in a text frame, unmasked, reserved bits set, a bad control frame); a
//! deleted scene ("scene deleted", after `deleted`). Code 1001 at shutdown. A connection that
//! failed at the transport level (reset, end of stream) just ends.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError, Weak};
use std::time::Duration;

use axum::extract::ws::{CloseFrame, Message, Utf8Bytes, WebSocket, WebSocketUpgrade};
use axum::extract::{Path, RawQuery, State};
use axum::http::{HeaderMap, StatusCode};
use axum::response::{IntoResponse, Response};
use futures_util::SinkExt;
use serde::{Deserialize, Serialize};
use serde_json::json;
use tokio::sync::{Notify, watch};

use super::AppState;
use super::rate_limit::RateLimit;
use super::scenes::{ApiError, read_access};

/// Largest client frame and message, bytes.
pub const MAX_CLIENT_MSG: usize = 4096;
/// Most client frames per second (text, binary, ping, pong) before the viewer is closed.
pub const MAX_CLIENT_MSGS_PER_S: u32 = 100;
/// Most poses one scene delivers per second, summed over its viewers: the fan-out cap. The
/// publication interval stretches past `pose_interval` to keep under it (256 viewers all moving:
/// 65,280 poses a publication, about 4.6 a second).
pub const MAX_FANOUT_PER_S: u64 = 300_000;
/// Close code for a viewer that broke a limit (policy violation).
pub const CLOSE_POLICY: u16 = 1008;
/// Close code when the server shuts down ("going away").
pub const CLOSE_GOING_AWAY: u16 = 1001;
/// Longest close reason: a close frame's payload is at most 125 bytes, 2 of them the code.
const MAX_REASON: usize = 123;

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

/// A `presence` message as sent (field order fixed, so clients can rely on nothing but JSON).
#[derive(Serialize)]
struct PresenceMsg<'a> {
    r#type: &'static str,
    viewer: u64,
    pose: &'a Pose,
}

/// One viewer's place in its scene. Stamps are publication numbers ([`SceneState::seq`]).
#[derive(Debug, Default)]
struct Slot {
    /// The latest pose received since the last publication (latest wins).
    pending: Option<Pose>,
    /// The last published pose.
    pose: Option<Pose>,
    /// Its `presence` message, serialized once and shared by every receiver.
    msg: Option<Utf8Bytes>,
    /// Publication that carried `pose`.
    changed: u64,
    /// Publication that carried this viewer's join.
    joined: u64,
    /// Place in the scene's join order: a viewer is told of the joins after its own only (the
    /// earlier ones were in its welcome).
    order: u64,
}

/// What a scene's viewers share, under one lock. A change made now carries the stamp `seq + 1`
/// and becomes visible when [`Hub::publish`] makes that the current `seq`.
#[derive(Debug, Default)]
struct SceneState {
    /// The last publication.
    seq: u64,
    /// Something awaits publication (a pose, a join, a leave).
    dirty: bool,
    slots: HashMap<u64, Slot>,
    /// Joins so far.
    joins: u64,
    /// Viewers that left: (stamp, viewer), kept for `live_queue` publications.
    left: Vec<(u64, u64)>,
    /// The latest `version` message and its stamp (a viewer needs only the newest).
    version: Option<(u64, Utf8Bytes)>,
    /// Stamp of the deletion.
    deleted: Option<u64>,
}

/// What one wake-up of a viewer has to send.
#[derive(Debug, Default)]
struct Wake {
    msgs: Vec<Utf8Bytes>,
    deleted: bool,
}

/// One scene's live state.
#[derive(Debug)]
struct Hub {
    state: Mutex<SceneState>,
    /// The current publication number; every viewer waits on it.
    published: watch::Sender<u64>,
    /// Publications a viewer may fall behind (the `live_queue` setting).
    max_lag: u64,
}

impl Hub {
    fn lock(&self) -> MutexGuard<'_, SceneState> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Publishes what changed (or, with `force`, a new stamp regardless) and wakes the viewers.
    /// Returns the poses this publication delivers: those published times the other viewers.
    fn publish(&self, force: bool) -> u64 {
        let mut st = self.lock();
        if !st.dirty && !force {
            return 0;
        }
        st.seq += 1;
        let seq = st.seq;
        let mut changed = 0u64;
        for (&viewer, slot) in &mut st.slots {
            if let Some(pose) = slot.pending.take() {
                slot.pose = Some(pose);
                let msg = PresenceMsg {
                    r#type: "presence",
                    viewer,
                    pose: &pose,
                };
                // Finite floats and integers always serialize; a failure would only skip the pose.
                slot.msg = serde_json::to_string(&msg).ok().map(Utf8Bytes::from);
                slot.changed = seq;
                changed += 1;
            }
        }
        let max_lag = self.max_lag;
        st.left.retain(|&(stamp, _)| stamp + max_lag > seq);
        st.dirty = false;
        let receivers = st.slots.len() as u64;
        drop(st);
        self.published.send_replace(seq);
        changed * receivers.saturating_sub(1)
    }

    /// Adds a viewer: the others as listed in its welcome, and the publication it has seen.
    fn join(&self, me: u64) -> (Vec<serde_json::Value>, u64) {
        let mut st = self.lock();
        let others = st
            .slots
            .iter()
            .map(|(v, s)| json!({"viewer": v, "pose": s.pose}))
            .collect();
        let joined = st.seq + 1;
        st.joins += 1;
        let order = st.joins;
        st.slots.insert(
            me,
            Slot {
                joined,
                order,
                ..Slot::default()
            },
        );
        st.dirty = true;
        // Joined after a deletion: the first wake-up must still say so.
        let seen = st.deleted.map_or(st.seq, |d| d - 1);
        (others, seen)
    }

    /// A pose from a viewer: it replaces any not yet published.
    fn pose(&self, me: u64, pose: Pose) {
        let mut st = self.lock();
        if let Some(s) = st.slots.get_mut(&me) {
            s.pending = Some(pose);
            st.dirty = true;
        }
    }

    /// Removes a viewer; whether the scene is now empty.
    fn leave(&self, me: u64) -> bool {
        let mut st = self.lock();
        st.slots.remove(&me);
        let stamp = st.seq + 1;
        st.left.push((stamp, me));
        st.dirty = true;
        st.slots.is_empty()
    }

    /// What viewer `me`, which has seen publication `seen`, must be sent now; `Err(lag)` when it
    /// is more than `max_lag` publications behind (leaves it would need are gone).
    fn wake(&self, me: u64, seen: &mut u64) -> Result<Wake, u64> {
        let st = self.lock();
        let since = *seen;
        if st.seq <= since {
            return Ok(Wake::default());
        }
        let lag = st.seq - since;
        if lag > self.max_lag {
            return Err(lag);
        }
        let mut w = Wake::default();
        let my_order = st.slots.get(&me).map_or(u64::MAX, |s| s.order);
        // Joins, then poses, then leaves: a viewer that joined and left since is only a leave
        // (its slot is gone), and no pose ever follows its viewer's leave.
        for (v, s) in &st.slots {
            if s.order > my_order && s.joined > since {
                w.msgs.push(json!({"type": "join", "viewer": v}).to_string().into());
            }
        }
        for (v, s) in &st.slots {
            if *v != me && s.changed > since {
                w.msgs.extend(s.msg.clone());
            }
        }
        for &(stamp, v) in &st.left {
            if stamp > since && v != me {
                w.msgs.push(json!({"type": "leave", "viewer": v}).to_string().into());
            }
        }
        if let Some((stamp, msg)) = &st.version
            && *stamp > since
        {
            w.msgs.push(msg.clone());
        }
        if st.deleted.is_some_and(|d| d > since) {
            w.msgs.push(Utf8Bytes::from_static(r#"{"type":"deleted"}"#));
            w.deleted = true;
        }
        *seen = st.seq;
        Ok(w)
    }
}

/// Publishes a scene's changes every `interval`, stretched to keep under the fan-out cap, until
/// its hub is gone (every viewer left).
async fn ticker(hub: Weak<Hub>, interval: Duration) {
    let mut wait = interval;
    loop {
        tokio::time::sleep(wait).await;
        let Some(hub) = hub.upgrade() else { return };
        let delivered = hub.publish(false);
        drop(hub);
        wait = interval.max(Duration::from_secs_f64(delivered as f64 / MAX_FANOUT_PER_S as f64));
    }
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

    fn map(&self) -> MutexGuard<'_, HashMap<String, Arc<Hub>>> {
        self.by_scene.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The scene's hub, created (with its ticker) if it has none. Must run on the runtime.
    fn hub(&self, scene: &str, max_lag: usize, interval: Duration) -> Arc<Hub> {
        let mut m = self.map();
        if let Some(h) = m.get(scene) {
            return Arc::clone(h);
        }
        let hub = Arc::new(Hub {
            state: Mutex::new(SceneState::default()),
            published: watch::channel(0).0,
            max_lag: max_lag.max(1) as u64,
        });
        tokio::spawn(ticker(Arc::downgrade(&hub), interval));
        m.insert(scene.to_string(), Arc::clone(&hub));
        hub
    }

    fn existing(&self, scene: &str) -> Option<Arc<Hub>> {
        self.map().get(scene).cloned()
    }

    /// Viewers connected to a scene.
    pub fn viewers(&self, scene: &str) -> usize {
        self.existing(scene).map_or(0, |h| h.lock().slots.len())
    }

    /// Tells a scene's viewers that a new version was published.
    pub fn notify_version(&self, scene: &str, version: u64) {
        let Some(hub) = self.existing(scene) else { return };
        let text = json!({
            "type": "version",
            "version": version,
            "manifest": format!("/api/scenes/{scene}/manifest?version={version}"),
        });
        {
            let mut st = hub.lock();
            let stamp = st.seq + 1;
            st.version = Some((stamp, text.to_string().into()));
        }
        hub.publish(true);
    }

    /// Tells a scene's viewers it was deleted, and closes them.
    pub fn notify_deleted(&self, scene: &str) {
        let Some(hub) = self.existing(scene) else { return };
        {
            let mut st = hub.lock();
            let stamp = st.seq + 1;
            st.deleted = Some(stamp);
        }
        hub.publish(true);
    }

    fn leave(&self, scene: &str, hub: &Hub, viewer: u64) {
        if hub.leave(viewer) {
            let mut m = self.map();
            // Drop the hub unless someone joined meanwhile (its ticker then ends).
            if m.get(scene).is_some_and(|h| h.lock().slots.is_empty()) {
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
enum End {
    /// The peer closed, or the transport failed: nothing more to send.
    Gone,
    /// Close with 1001 (shutdown).
    GoingAway,
    /// Close with 1008 and this reason.
    Policy(String),
}

/// The close reason for an error from the WebSocket layer, `None` when the transport failed
/// (then no close frame can be delivered). Cut to [`MAX_REASON`] bytes on a char boundary.
fn frame_error_reason(e: &(dyn std::error::Error + 'static)) -> Option<String> {
    let mut cause = Some(e);
    while let Some(c) = cause {
        if c.is::<std::io::Error>() {
            return None;
        }
        cause = c.source();
    }
    Some(clip_reason(format!("invalid frame: {e}")))
}

fn clip_reason(mut s: String) -> String {
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
fn on_frame(m: Option<Result<Message, axum::Error>>, limit: &mut RateLimit) -> Result<Option<Pose>, End> {
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
    let viewer = hubs.next_viewer.fetch_add(1, Ordering::Relaxed) + 1;
    let hub = hubs.hub(&scene, cfg.live_queue, cfg.pose_interval);
    // Subscribed before joining, so no publication after the join's snapshot is missed.
    let mut published = hub.published.subscribe();
    let (others, mut seen) = hub.join(viewer);
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

#[cfg(test)]
mod tests {
    use super::*;

    fn hub(max_lag: u64) -> Hub {
        Hub {
            state: Mutex::new(SceneState::default()),
            published: watch::channel(0).0,
            max_lag,
        }
    }

    fn pose(x: f32) -> Pose {
        Pose {
            position: [x, 0.0, 0.0],
            orientation: [0.0, 0.0, 0.0, 1.0],
        }
    }

    fn texts(w: &Wake) -> Vec<serde_json::Value> {
        w.msgs.iter().map(|m| serde_json::from_str(m).expect("JSON")).collect()
    }

    #[test]
    fn poses_coalesce_latest_wins_and_never_echo() {
        let h = hub(64);
        let (_, mut a_seen) = h.join(1);
        let (others, mut b_seen) = h.join(2);
        assert_eq!(others.len(), 1);
        h.publish(false);
        // Both see each other's join only.
        let a = texts(&h.wake(1, &mut a_seen).expect("in time"));
        assert_eq!(a, vec![json!({"type": "join", "viewer": 2})]);
        h.wake(2, &mut b_seen).expect("in time");
        // 50 poses from viewer 2 between two publications: one delivered, the last.
        for k in 0..50 {
            h.pose(2, pose(k as f32));
        }
        assert_eq!(h.publish(false), 1, "one pose times one other viewer");
        let a = texts(&h.wake(1, &mut a_seen).expect("in time"));
        assert_eq!(a.len(), 1);
        assert_eq!(a[0]["type"], "presence");
        assert_eq!(a[0]["viewer"], 2);
        assert_eq!(a[0]["pose"]["position"], json!([49.0, 0.0, 0.0]));
        assert!(h.wake(2, &mut b_seen).expect("in time").msgs.is_empty(), "no echo");
        // Nothing new: no publication, no wake-up.
        assert_eq!(h.publish(false), 0);
        assert_eq!(h.lock().seq, 2);
    }

    #[test]
    fn a_viewer_behind_gets_one_pose_per_viewer_and_no_pose_after_a_leave() {
        let h = hub(64);
        let (_, mut a_seen) = h.join(1);
        h.join(2);
        h.join(3);
        h.publish(false);
        h.wake(1, &mut a_seen).expect("in time");
        // Viewer 1 sleeps through ten publications.
        for k in 0..10 {
            h.pose(2, pose(k as f32));
            h.pose(3, pose(-k as f32));
            h.publish(false);
        }
        h.pose(3, pose(100.0));
        h.leave(3);
        h.publish(false);
        let a = texts(&h.wake(1, &mut a_seen).expect("in time"));
        assert_eq!(
            a,
            vec![
                json!({"type": "presence", "viewer": 2, "pose": {"position": [9.0, 0.0, 0.0], "orientation": [0.0, 0.0, 0.0, 1.0]}}),
                json!({"type": "leave", "viewer": 3}),
            ]
        );
    }

    #[test]
    fn a_viewer_too_far_behind_is_told_so() {
        let h = hub(4);
        let (_, mut a_seen) = h.join(1);
        h.join(2);
        for k in 0..5 {
            h.pose(2, pose(k as f32));
            h.publish(false);
        }
        assert_eq!(h.wake(1, &mut a_seen).err(), Some(5));
        // Tombstones older than the lag bound are gone.
        h.leave(2);
        for _ in 0..5 {
            h.publish(true);
        }
        assert!(h.lock().left.is_empty());
    }

    #[test]
    fn version_and_deletion_reach_every_viewer_once() {
        let h = hub(64);
        let (_, mut a_seen) = h.join(1);
        h.publish(false);
        h.wake(1, &mut a_seen).expect("in time");
        let stamp = h.lock().seq + 1;
        h.lock().version = Some((stamp, Utf8Bytes::from_static(r#"{"type":"version"}"#)));
        h.publish(true);
        let w = h.wake(1, &mut a_seen).expect("in time");
        assert_eq!(texts(&w), vec![json!({"type": "version"})]);
        assert!(!w.deleted);
        assert!(h.wake(1, &mut a_seen).expect("in time").msgs.is_empty());
        let stamp = h.lock().seq + 1;
        h.lock().deleted = Some(stamp);
        h.publish(true);
        assert!(h.wake(1, &mut a_seen).expect("in time").deleted);
        // A viewer joining after the deletion is told on its first wake-up.
        let (_, mut late) = h.join(2);
        let w = h.wake(2, &mut late).expect("in time");
        assert!(w.deleted);
    }

    #[test]
    fn every_frame_counts_towards_the_rate_limit() {
        let mut limit = RateLimit::new();
        let ping = || Some(Ok(Message::Ping(axum::body::Bytes::new())));
        for _ in 0..MAX_CLIENT_MSGS_PER_S {
            assert_eq!(on_frame(ping(), &mut limit), Ok(None));
        }
        assert_eq!(
            on_frame(ping(), &mut limit),
            Err(End::Policy("too many messages".into()))
        );
    }

    #[test]
    fn bad_frames_get_a_policy_close_and_dead_transports_none() {
        let io = std::io::Error::new(std::io::ErrorKind::ConnectionReset, "reset");
        assert_eq!(frame_error_reason(&io), None);
        #[derive(Debug)]
        struct Wrapped(std::io::Error);
        impl std::fmt::Display for Wrapped {
            fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                write!(f, "IO error: {}", self.0)
            }
        }
        impl std::error::Error for Wrapped {
            fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
                Some(&self.0)
            }
        }
        assert_eq!(frame_error_reason(&Wrapped(io)), None);
        let long = std::io::Error::other("x".repeat(300));
        let reason = clip_reason(format!("invalid frame: {long}"));
        assert_eq!(reason.len(), MAX_REASON);
        assert_eq!(clip_reason("é".repeat(100)).len(), 122, "cut on a char boundary");
        let mut limit = RateLimit::new();
        assert_eq!(
            on_frame(Some(Ok(Message::Binary(axum::body::Bytes::new()))), &mut limit),
            Err(End::Policy("binary messages are not accepted".into()))
        );
        let bad = Some(Ok(Message::Text(
            r#"{"type":"pose","position":[1e99,0,0],"orientation":[0,0,0,1]}"#.into(),
        )));
        assert!(matches!(on_frame(bad, &mut limit), Err(End::Policy(r)) if r.starts_with("invalid message")));
    }
}
