//! Tests of the live hub: coalescing, lag, versions and deletions, limits, and remote viewers
//! (presence relayed by other replicas).

use axum::extract::ws::Message;

use super::socket::*;
use super::*;
use crate::http::rate_limit::RateLimit;

fn hub(max_lag: u64) -> Hub {
    Hub {
        state: Mutex::new(SceneState::default()),
        published: watch::channel(0).0,
        max_lag,
        relay: false,
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

fn relaying_hub() -> Hub {
    Hub { relay: true, ..hub(64) }
}

fn relayed(scene: &str, viewers: &[(u64, Option<Pose>)], left: &[u64]) -> live_relay::RelayMsg {
    live_relay::RelayMsg {
        scene: scene.into(),
        viewers: viewers.iter().map(|&(id, pose)| RelayedViewer { id, pose }).collect(),
        left: left.to_vec(),
    }
}

#[test]
fn remote_viewers_are_told_like_own_ones_and_never_relayed_back() {
    let h = relaying_hub();
    let t0 = Instant::now();
    let (_, mut a_seen) = h.join(1);
    h.publish(false);
    h.wake(1, &mut a_seen).expect("in time");
    // Viewer 9 of another replica joins with a pose: a join and a presence for viewer 1.
    assert!(!h.remote(&relayed("s", &[(9, Some(pose(3.0)))], &[]), t0));
    assert_eq!(h.publish(false), 1, "one remote pose to one own viewer");
    let a = texts(&h.wake(1, &mut a_seen).expect("in time"));
    assert_eq!(a[0], json!({"type": "join", "viewer": 9}));
    assert_eq!(a[1]["type"], "presence");
    assert_eq!(a[1]["pose"]["position"], json!([3.0, 0.0, 0.0]));
    // A roster repeating the same pose publishes nothing.
    h.remote(&relayed("s", &[(9, Some(pose(3.0)))], &[]), t0);
    assert_eq!(h.publish(false), 0);
    // A newcomer's welcome lists the remote viewer with its pose.
    let (others, _) = h.join(2);
    assert!(others.contains(&json!({"viewer": 9, "pose": pose(3.0)})), "{others:?}");
    // The outbox holds own viewers only: 1 joined, 2 joined; never 9.
    h.pose(1, pose(5.0));
    h.publish(false);
    let out = h.take_outbox(false);
    let ids: Vec<u64> = out.viewers.iter().map(|v| v.id).collect();
    assert_eq!(ids, vec![1, 2, 1], "{:?}", out.viewers);
    assert_eq!(out.viewers[2].pose, Some(pose(5.0)));
    assert!(h.take_outbox(false).viewers.is_empty(), "taken once");
    // A roster: every own viewer with its last pose.
    let mut roster: Vec<_> = h
        .take_outbox(true)
        .viewers
        .into_iter()
        .map(|v| (v.id, v.pose))
        .collect();
    roster.sort_by_key(|v| v.0);
    assert_eq!(roster, vec![(1, Some(pose(5.0))), (2, None)]);
    // A remote message never touches an own viewer of the same id.
    h.remote(&relayed("s", &[(1, Some(pose(-1.0)))], &[1]), t0);
    assert_eq!(h.lock().slots[&1].pose, Some(pose(5.0)));
    assert!(h.lock().slots.contains_key(&1));
    // The remote viewer leaves: a leave for viewer 1.
    h.wake(1, &mut a_seen).expect("in time");
    h.remote(&relayed("s", &[], &[9]), t0);
    h.publish(false);
    let a = texts(&h.wake(1, &mut a_seen).expect("in time"));
    assert!(a.contains(&json!({"type": "leave", "viewer": 9})), "{a:?}");
}

#[test]
fn a_remote_viewer_not_heard_of_expires_and_an_empty_scene_says_so() {
    let h = relaying_hub();
    let t0 = Instant::now();
    h.remote(&relayed("s", &[(9, None), (10, None)], &[]), t0);
    // 10 is mentioned again later; 9 is not.
    h.remote(&relayed("s", &[(10, None)], &[]), t0 + REMOTE_TTL);
    assert!(!h.expire(t0 + REMOTE_TTL + Duration::from_millis(1)));
    assert_eq!(h.lock().slots.keys().copied().collect::<Vec<_>>(), vec![10]);
    assert!(
        h.expire(t0 + 2 * REMOTE_TTL + Duration::from_millis(2)),
        "empty once 10 expires"
    );
    // Own viewers never expire.
    h.join(1);
    assert!(!h.expire(t0 + 10 * REMOTE_TTL));
}

#[test]
fn viewer_ids_carry_the_replica_tag() {
    let lone = Hubs::new(None);
    assert_eq!((lone.new_viewer_id(), lone.new_viewer_id()), (1, 2));
    let replica = Hubs::new(Some(Relay(Arc::new(|_| {}))));
    let id = replica.new_viewer_id();
    assert!(id >> 32 >= 1 && id < 1 << 53, "{id:#x}");
    assert_eq!(id & 0xffff_ffff, 1);
}

#[test]
fn a_version_is_told_once_and_never_one_the_viewers_know() {
    let hubs = Hubs::new(None);
    let h = Arc::new(hub(64));
    hubs.map().insert("s".into(), Arc::clone(&h));
    assert_eq!(hubs.watched(), vec!["s".to_string()]);
    let (_, mut seen) = h.join(1);
    // The first viewer joined at version 3 (as `run_viewer` records it).
    h.lock().known_version = Some(3);
    h.publish(false);
    h.wake(1, &mut seen).expect("in time");
    // A resync reading version 3 again tells nothing; 4 is told once, however often it is read.
    hubs.notify_version("s", 3);
    assert!(h.wake(1, &mut seen).expect("in time").msgs.is_empty());
    for _ in 0..2 {
        hubs.notify_version("s", 4);
    }
    let w = h.wake(1, &mut seen).expect("in time");
    assert_eq!(texts(&w).iter().filter(|m| m["type"] == "version").count(), 1);
    assert_eq!(texts(&w)[0]["version"], 4);
    hubs.notify_version("s", 4);
    assert!(h.wake(1, &mut seen).expect("in time").msgs.is_empty());
}

/// Hubs of a relaying replica made on a runtime (as the server makes them), and what they relay.
fn relaying_hubs() -> (tokio::runtime::Runtime, Hubs, Arc<Mutex<Vec<String>>>) {
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let sent = Arc::new(Mutex::new(Vec::new()));
    let to = Arc::clone(&sent);
    let relay = Relay(Arc::new(move |p| to.lock().expect("lock").push(p)));
    let hubs = {
        let _on = rt.enter();
        Hubs::new(Some(relay))
    };
    (rt, hubs, sent)
}

#[test]
fn another_replicas_viewer_is_kept_from_a_plain_thread_for_a_scene_with_no_viewer_here() {
    let (_rt, hubs, _) = relaying_hubs();
    let msg = relayed("s", &[(7 << 32 | 1, Some(pose(1.0)))], &[]);
    let payload = serde_json::to_string(&msg).expect("JSON");
    // The store's listener thread is not a runtime thread.
    std::thread::scope(|t| {
        t.spawn(|| hubs.remote(&payload, 64, Duration::from_millis(100)));
    });
    assert_eq!(hubs.viewers("s"), 1);
    // A viewer joining now finds it in its welcome.
    let (_, others, _) = hubs.join("s", 9, 1, 64, Duration::from_millis(100)).expect("hub");
    assert_eq!(others.len(), 1);
    assert_eq!(others[0]["viewer"], 7u64 << 32 | 1);
}

#[test]
fn the_last_own_viewers_leave_is_relayed_though_its_hub_is_dropped() {
    let (_rt, hubs, sent) = relaying_hubs();
    let (hub, _, _) = hubs.join("s", 5, 1, 64, Duration::from_millis(100)).expect("hub");
    hubs.leave("s", &hub, 5);
    assert!(hubs.watched().is_empty(), "the empty hub is dropped");
    let msgs: Vec<_> = sent
        .lock()
        .expect("lock")
        .iter()
        .map(|p| live_relay::decode(p).expect("valid"))
        .collect();
    assert!(msgs.iter().any(|m| m.scene == "s" && m.left == vec![5]), "{msgs:?}");
}

#[test]
fn a_resync_tells_a_newer_version_once_and_an_older_one_as_a_deletion() {
    let (_rt, hubs, _) = relaying_hubs();
    // Two viewers read the scene at versions 6 and 5: 6 is still news to the second.
    let (hub, _, mut a) = hubs.join("s", 1, 6, 64, Duration::from_millis(100)).expect("hub");
    let (_, _, mut b) = hubs.join("s", 2, 5, 64, Duration::from_millis(100)).expect("hub");
    hub.publish(false);
    hub.wake(1, &mut a).expect("in time");
    hub.wake(2, &mut b).expect("in time");
    hubs.resync("s", Some(6));
    let told = texts(&hub.wake(2, &mut b).expect("in time"));
    assert!(
        told.iter().any(|m| m["type"] == "version" && m["version"] == 6),
        "{told:?}"
    );
    hubs.resync("s", Some(6));
    assert!(hub.wake(2, &mut b).expect("in time").msgs.is_empty(), "told once");
    // Version 2 after 6: the scene was deleted and made again while notifications were lost.
    hubs.resync("s", Some(2));
    assert!(hub.wake(1, &mut a).expect("in time").deleted);
}

#[test]
fn other_replicas_cannot_make_a_scene_hold_more_than_the_remote_bound() {
    let h = relaying_hub();
    let t0 = Instant::now();
    let ids: Vec<u64> = (1..=MAX_REMOTE_VIEWERS as u64 + 500).map(|n| 3 << 32 | n).collect();
    for chunk in ids.chunks(1000) {
        let viewers: Vec<_> = chunk.iter().map(|&id| (id, None)).collect();
        h.remote(&relayed("s", &viewers, &[]), t0);
    }
    assert_eq!(h.lock().slots.len(), MAX_REMOTE_VIEWERS);
    // Own viewers still join.
    h.join(1);
    assert_eq!(h.lock().slots.len(), MAX_REMOTE_VIEWERS + 1);
}
