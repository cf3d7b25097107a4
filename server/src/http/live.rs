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
//! Across replicas (a store other processes share), each scene's ticker also relays its own
//! viewers' joins, poses and leaves, and its roster every few seconds, to the other replicas; what
//! they relay enters the scene as remote viewers, told to this replica's viewers like its own
//! (`live_relay.rs` has that contract).
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
use std::time::{Duration, Instant};

use axum::extract::ws::Utf8Bytes;
use serde::{Deserialize, Serialize};
use serde_json::json;
use tokio::sync::{Notify, watch};

use super::live_relay::{self, REMOTE_TTL, ROSTER_EVERY, RelayedViewer};

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
/// Most viewers of other replicas one scene holds: a bound on what a misbehaving replica can make
/// it keep (legitimately at most the viewer cap, 256 by default, as every replica enforces it).
pub const MAX_REMOTE_VIEWERS: usize = 4096;

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
    /// For a viewer of another replica: when that replica last mentioned it.
    remote: Option<Instant>,
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
    /// The newest version the viewers were told of, or the oldest one a viewer joined at since:
    /// one no newer is not told again (a resync after missed notifications re-reads every
    /// watched scene).
    known_version: Option<u64>,
    /// Stamp of the deletion.
    deleted: Option<u64>,
    /// What this replica's own viewers did since the last relay (only when relaying).
    outbox: Outbox,
}

/// Own viewers' changes not yet relayed to the other replicas.
#[derive(Debug, Default)]
struct Outbox {
    viewers: Vec<RelayedViewer>,
    left: Vec<u64>,
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
    /// Whether own viewers' changes are relayed to other replicas (fills the outbox).
    relay: bool,
}

impl Hub {
    fn lock(&self) -> MutexGuard<'_, SceneState> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Publishes what changed (or, with `force`, a new stamp regardless) and wakes the viewers.
    /// Returns the poses this publication delivers: those published times the other viewers.
    fn publish(&self, force: bool) -> u64 {
        let mut guard = self.lock();
        if !guard.dirty && !force {
            return 0;
        }
        guard.seq += 1;
        let st = &mut *guard;
        let seq = st.seq;
        // Poses changed of own viewers (each goes to the other own viewers) and of remote ones.
        let (mut changed_own, mut changed_remote) = (0u64, 0u64);
        for (&viewer, slot) in &mut st.slots {
            if let Some(pose) = slot.pending.take() {
                if slot.remote.is_some() {
                    changed_remote += 1;
                } else {
                    changed_own += 1;
                }
                if self.relay && slot.remote.is_none() {
                    st.outbox.viewers.push(RelayedViewer {
                        id: viewer,
                        pose: Some(pose),
                    });
                }
                slot.pose = Some(pose);
                let msg = PresenceMsg {
                    r#type: "presence",
                    viewer,
                    pose: &pose,
                };
                // Finite floats and integers always serialize; a failure would only skip the pose.
                slot.msg = serde_json::to_string(&msg).ok().map(Utf8Bytes::from);
                slot.changed = seq;
            }
        }
        let max_lag = self.max_lag;
        st.left.retain(|&(stamp, _)| stamp + max_lag > seq);
        st.dirty = false;
        let receivers = st.slots.values().filter(|s| s.remote.is_none()).count() as u64;
        drop(guard);
        self.published.send_replace(seq);
        changed_own * receivers.saturating_sub(1) + changed_remote * receivers
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
        if self.relay {
            st.outbox.viewers.push(RelayedViewer { id: me, pose: None });
        }
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
        if self.relay {
            st.outbox.left.push(me);
        }
        st.dirty = true;
        st.slots.is_empty()
    }

    /// What another replica relayed of its viewers at `now`: each viewer named is present (added
    /// when new, its pose taken when it differs), each in `left` gone. A viewer of this replica's
    /// own is never touched. Whether the scene is now empty.
    fn remote(&self, msg: &live_relay::RelayMsg, now: Instant) -> bool {
        let mut st = self.lock();
        let mut remote = st.slots.values().filter(|s| s.remote.is_some()).count();
        for v in &msg.viewers {
            if let Some(slot) = st.slots.get_mut(&v.id) {
                if slot.remote.is_none() {
                    continue;
                }
                slot.remote = Some(now);
                if v.pose.is_some() && v.pose != slot.pending.or(slot.pose) {
                    slot.pending = v.pose;
                    st.dirty = true;
                }
                continue;
            }
            if remote >= MAX_REMOTE_VIEWERS {
                continue;
            }
            remote += 1;
            let joined = st.seq + 1;
            st.joins += 1;
            let order = st.joins;
            st.slots.insert(
                v.id,
                Slot {
                    pending: v.pose,
                    joined,
                    order,
                    remote: Some(now),
                    ..Slot::default()
                },
            );
            st.dirty = true;
        }
        for id in &msg.left {
            if st.slots.get(id).is_some_and(|s| s.remote.is_some()) {
                st.slots.remove(id);
                let stamp = st.seq + 1;
                st.left.push((stamp, *id));
                st.dirty = true;
            }
        }
        st.slots.is_empty()
    }

    /// Drops the remote viewers not mentioned within [`REMOTE_TTL`] of `now`; whether the scene is
    /// now empty.
    fn expire(&self, now: Instant) -> bool {
        let mut st = self.lock();
        let stale: Vec<u64> = st
            .slots
            .iter()
            .filter(|(_, s)| {
                s.remote
                    .is_some_and(|heard| now.saturating_duration_since(heard) > REMOTE_TTL)
            })
            .map(|(&v, _)| v)
            .collect();
        for v in stale {
            st.slots.remove(&v);
            let stamp = st.seq + 1;
            st.left.push((stamp, v));
            st.dirty = true;
        }
        st.slots.is_empty()
    }

    /// The changes of own viewers to relay now; with `roster`, also every own viewer and its pose.
    fn take_outbox(&self, roster: bool) -> Outbox {
        let mut st = self.lock();
        let mut out = std::mem::take(&mut st.outbox);
        if roster {
            out.viewers = st
                .slots
                .iter()
                .filter(|(_, s)| s.remote.is_none())
                .map(|(&id, s)| RelayedViewer { id, pose: s.pose })
                .collect();
        }
        out
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
/// its hub is gone (every viewer left). When relaying, also drops remote viewers gone quiet and
/// relays own viewers' changes (and every [`ROSTER_EVERY`] the roster) to the other replicas.
async fn ticker(scenes: Weak<HubMap>, scene: String, hub: Weak<Hub>, interval: Duration, relay: Option<Relay>) {
    let mut wait = interval;
    let mut last_roster = Instant::now();
    loop {
        tokio::time::sleep(wait).await;
        let Some(hub) = hub.upgrade() else { return };
        let now = Instant::now();
        if relay.is_some()
            && hub.expire(now)
            && let Some(scenes) = scenes.upgrade()
        {
            // This iteration still relays what the hub holds.
            let _ = remove_if_empty(&scenes, &scene);
        }
        let delivered = hub.publish(false);
        if let Some(relay) = &relay {
            let roster = now.duration_since(last_roster) >= ROSTER_EVERY;
            if roster {
                last_roster = now;
            }
            let out = hub.take_outbox(roster);
            for payload in live_relay::encode(&scene, &out.viewers, &out.left) {
                (relay.0)(payload);
            }
        }
        drop(hub);
        wait = interval.max(Duration::from_secs_f64(delivered as f64 / MAX_FANOUT_PER_S as f64));
    }
}

/// Every scene's hub, by scene id.
type HubMap = Mutex<HashMap<String, Arc<Hub>>>;

fn lock_map(m: &HubMap) -> MutexGuard<'_, HashMap<String, Arc<Hub>>> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Drops a scene's hub when nobody (own or remote) is in it, and returns it; its ticker then ends.
fn remove_if_empty(scenes: &HubMap, scene: &str) -> Option<Arc<Hub>> {
    let mut m = lock_map(scenes);
    if m.get(scene).is_some_and(|h| h.lock().slots.is_empty()) {
        return m.remove(scene);
    }
    None
}

/// Where a replica's presence payloads go (the scene store's relay).
#[derive(Clone)]
pub struct Relay(pub Arc<dyn Fn(String) + Send + Sync>);

impl std::fmt::Debug for Relay {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("Relay")
    }
}

/// Every scene's live state.
#[derive(Debug, Default)]
pub struct Hubs {
    by_scene: Arc<HubMap>,
    next_viewer: AtomicU64,
    /// High bits of this replica's viewer ids (0 when it relays to nobody).
    tag: u64,
    /// Where own viewers' presence goes, when other replicas share the store.
    relay: Option<Relay>,
    /// The runtime tickers run on (hubs made for remote viewers are made on the store's thread).
    runtime: Option<tokio::runtime::Handle>,
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
    /// Hubs of a replica that relays its viewers' presence through `relay` (or of a lone server,
    /// `None`). Must be made on the runtime when relaying.
    pub fn new(relay: Option<Relay>) -> Self {
        let tag = if relay.is_some() {
            let mut raw = [0u8; 4];
            if getrandom::fill(&mut raw).is_err() {
                // Still differs between replicas with high probability: the clock and the pid.
                let nanos = std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.subsec_nanos());
                raw = (nanos ^ std::process::id().rotate_left(20)).to_le_bytes();
            }
            (u64::from(u32::from_le_bytes(raw)) & 0xf_ffff).max(1)
        } else {
            0
        };
        Self {
            tag,
            relay,
            runtime: tokio::runtime::Handle::try_current().ok(),
            ..Self::default()
        }
    }

    /// A new viewer id: the replica tag above a 32-bit count.
    fn new_viewer_id(&self) -> u64 {
        let n = self.next_viewer.fetch_add(1, Ordering::Relaxed) + 1;
        (self.tag << 32) | (n & 0xffff_ffff)
    }

    /// Takes a presence payload another replica relayed.
    pub fn remote(&self, payload: &str, max_lag: usize, interval: Duration) {
        let Some(msg) = live_relay::decode(payload) else {
            tracing::debug!(payload, "malformed presence relay ignored");
            return;
        };
        // Under the map lock, so the hub cannot be dropped between finding and filling it.
        let mut m = self.map();
        let hub = if msg.viewers.is_empty() {
            m.get(&msg.scene).cloned()
        } else {
            self.hub_in(&mut m, &msg.scene, max_lag, interval)
        };
        let mut removed = None;
        if let Some(hub) = hub
            && hub.remote(&msg, Instant::now())
        {
            removed = m.remove(&msg.scene);
        }
        drop(m);
        if let Some(hub) = removed {
            self.flush(&msg.scene, &hub);
        }
    }

    /// Relays what a dropped hub still held of its own viewers (its ticker will not).
    fn flush(&self, scene: &str, hub: &Hub) {
        if let Some(relay) = &self.relay {
            let out = hub.take_outbox(false);
            for payload in live_relay::encode(scene, &out.viewers, &out.left) {
                (relay.0)(payload);
            }
        }
    }

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
        lock_map(&self.by_scene)
    }

    /// Adds viewer `me`, which read the scene at `version`, to the scene's hub (created if it
    /// has none) under the map lock, so it never joins a hub being dropped: the hub, the others
    /// for its welcome and the publication it has seen. `None` only without a runtime.
    fn join(
        &self,
        scene: &str,
        me: u64,
        version: u64,
        max_lag: usize,
        interval: Duration,
    ) -> Option<(Arc<Hub>, Vec<serde_json::Value>, u64)> {
        let mut m = self.map();
        let hub = self.hub_in(&mut m, scene, max_lag, interval)?;
        let (others, seen) = hub.join(me);
        {
            // The oldest version a viewer holds: a newer one is told even if others know it.
            let mut st = hub.lock();
            st.known_version = Some(st.known_version.map_or(version, |k| k.min(version)));
        }
        drop(m);
        Some((hub, others, seen))
    }

    /// The scene's hub in the locked map, created (with its ticker) if it has none; `None` only
    /// when no runtime is at hand to run a ticker.
    fn hub_in(
        &self,
        m: &mut MutexGuard<'_, HashMap<String, Arc<Hub>>>,
        scene: &str,
        max_lag: usize,
        interval: Duration,
    ) -> Option<Arc<Hub>> {
        if let Some(h) = m.get(scene) {
            return Some(Arc::clone(h));
        }
        let runtime = self
            .runtime
            .clone()
            .or_else(|| tokio::runtime::Handle::try_current().ok())?;
        let hub = Arc::new(Hub {
            state: Mutex::new(SceneState::default()),
            published: watch::channel(0).0,
            max_lag: max_lag.max(1) as u64,
            relay: self.relay.is_some(),
        });
        runtime.spawn(ticker(
            Arc::downgrade(&self.by_scene),
            scene.to_string(),
            Arc::downgrade(&hub),
            interval,
            self.relay.clone(),
        ));
        m.insert(scene.to_string(), Arc::clone(&hub));
        Some(hub)
    }

    fn existing(&self, scene: &str) -> Option<Arc<Hub>> {
        self.map().get(scene).cloned()
    }

    /// Viewers connected to a scene.
    pub fn viewers(&self, scene: &str) -> usize {
        self.existing(scene).map_or(0, |h| h.lock().slots.len())
    }

    /// Tells a scene's viewers that a new version was published (unless they know of it).
    pub fn notify_version(&self, scene: &str, version: u64) {
        let Some(hub) = self.existing(scene) else { return };
        let text = json!({
            "type": "version",
            "version": version,
            "manifest": format!("/api/scenes/{scene}/manifest?version={version}"),
        });
        {
            let mut st = hub.lock();
            if st.known_version.is_some_and(|known| known >= version) {
                return;
            }
            st.known_version = Some(version);
            let stamp = st.seq + 1;
            st.version = Some((stamp, text.to_string().into()));
        }
        hub.publish(true);
    }

    /// The scenes that have viewers here.
    pub fn watched(&self) -> Vec<String> {
        self.map().keys().cloned().collect()
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
        if hub.leave(viewer)
            // Drop the hub unless someone joined meanwhile (its ticker then ends).
            && let Some(hub) = remove_if_empty(&self.by_scene, scene)
        {
            self.flush(scene, &hub);
        }
    }

    /// After notifications may have been missed: the scene's current version as read from the
    /// store (`None`: it is gone). A version older than the viewers know means the scene was
    /// deleted and made again meanwhile: they are told of the deletion.
    pub fn resync(&self, scene: &str, current: Option<u64>) {
        let known = self.existing(scene).and_then(|h| h.lock().known_version);
        match current {
            Some(v) if known.is_none_or(|k| v >= k) => self.notify_version(scene, v),
            _ => self.notify_deleted(scene),
        }
    }
}

#[path = "live_socket.rs"]
mod socket;
pub use socket::live;

#[cfg(test)]
#[path = "live_tests.rs"]
mod tests;
