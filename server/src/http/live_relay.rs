//! Presence across replicas: what one replica tells the others of its viewers, and how it reads
//! what they tell it.
//!
//! Contract. A replica relays, per scene with viewers of its own, a [`RelayMsg`] after every
//! publication that changed something of theirs (joins, new poses, leaves) and, every
//! [`ROSTER_EVERY`], its whole roster (every viewer of its own with its last pose). The store
//! carries the payloads ([`crate::store::scenes::SceneStore::relay_presence`]: PostgreSQL's
//! `NOTIFY`, best effort). A receiving replica adds each viewer it is told of as a remote slot,
//! takes a pose that differs from the one it holds, removes the viewers that left, and drops a
//! remote viewer it has not been told of for [`REMOTE_TTL`] (its replica died, lost the database,
//! or a leave was dropped). So a lost payload costs a late pose or a late leave, never a viewer
//! shown for ever. Viewer ids are unique across replicas: a random 20-bit replica tag above a
//! 32-bit counter, below 2^53 so JavaScript reads them exactly.

use std::time::Duration;

use serde::{Deserialize, Serialize};

use super::live::Pose;
use crate::store::scenes::valid_scene_id;

/// How often a replica re-sends its whole roster of a scene.
pub const ROSTER_EVERY: Duration = Duration::from_secs(2);
/// A remote viewer not mentioned for this long is dropped (two rosters missed, plus slack).
pub const REMOTE_TTL: Duration = Duration::from_secs(5);
/// Largest payload: PostgreSQL's `NOTIFY` takes under 8,000 bytes, the replica's id goes first.
pub const MAX_PAYLOAD: usize = 7_000;
/// Most viewers one payload may name (a payload over it is refused as malformed).
const MAX_VIEWERS_PER_MSG: usize = 1_000;

/// One viewer as relayed: its id and, when it changed (or in a roster, when one is known), its
/// pose.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RelayedViewer {
    /// Viewer id (unique across replicas).
    pub id: u64,
    /// Its latest pose.
    pub pose: Option<Pose>,
}

/// One relayed message.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RelayMsg {
    /// Scene id.
    pub scene: String,
    /// Viewers present.
    #[serde(default)]
    pub viewers: Vec<RelayedViewer>,
    /// Viewers that left.
    #[serde(default)]
    pub left: Vec<u64>,
}

/// The payloads telling the other replicas of `viewers` and `left` in `scene`, each at most
/// [`MAX_PAYLOAD`] bytes; none when there is nothing to tell.
pub fn encode(scene: &str, viewers: &[RelayedViewer], left: &[u64]) -> Vec<String> {
    let head = format!("{{\"scene\":{},\"viewers\":[", serde_json::Value::from(scene));
    let mut out = Vec::new();
    let mut cur = head.clone();
    let mut n = 0usize;
    let mut flush = |cur: &mut String, n: &mut usize, tail: &str| {
        cur.push_str(tail);
        out.push(std::mem::replace(cur, head.clone()));
        *n = 0;
    };
    for v in viewers {
        // Finite floats and integers always serialize.
        let Ok(entry) = serde_json::to_string(v) else { continue };
        if n > 0 && cur.len() + entry.len() + 16 > MAX_PAYLOAD {
            flush(&mut cur, &mut n, "]}");
        }
        if n > 0 {
            cur.push(',');
        }
        cur.push_str(&entry);
        n += 1;
    }
    // Leaves go last, in the last message (after any viewer of the same batch).
    let mut left_ids = left.iter().map(u64::to_string).peekable();
    while left_ids.peek().is_some() || n > 0 {
        cur.push_str("],\"left\":[");
        let mut first = true;
        while let Some(id) = left_ids.next_if(|id| cur.len() + id.len() + 3 <= MAX_PAYLOAD) {
            if !first {
                cur.push(',');
            }
            cur.push_str(&id);
            first = false;
        }
        flush(&mut cur, &mut n, "]}");
        if left_ids.peek().is_none() {
            break;
        }
    }
    out
}

/// A relayed message, `None` when malformed: bad JSON, a bad scene id, a pose with a number that
/// is not finite, or too many viewers.
pub fn decode(payload: &str) -> Option<RelayMsg> {
    let msg: RelayMsg = serde_json::from_str(payload).ok()?;
    let finite = |p: &Pose| p.position.iter().chain(&p.orientation).all(|v| v.is_finite());
    let ok = valid_scene_id(&msg.scene)
        && msg.viewers.len() + msg.left.len() <= MAX_VIEWERS_PER_MSG
        && msg.viewers.iter().all(|v| v.pose.as_ref().is_none_or(finite));
    ok.then_some(msg)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn viewer(id: u64) -> RelayedViewer {
        RelayedViewer {
            id,
            pose: Some(Pose {
                position: [id as f32 * 1.5, -2.25, 1e6],
                orientation: [
                    0.0,
                    std::f32::consts::FRAC_1_SQRT_2,
                    0.0,
                    std::f32::consts::FRAC_1_SQRT_2,
                ],
            }),
        }
    }

    #[test]
    fn a_message_round_trips() {
        let viewers = vec![viewer(1), RelayedViewer { id: 2, pose: None }];
        let out = encode("forest-1", &viewers, &[7, 8]);
        assert_eq!(out.len(), 1);
        let msg = decode(&out[0]).expect("valid");
        assert_eq!(
            msg,
            RelayMsg {
                scene: "forest-1".into(),
                viewers,
                left: vec![7, 8]
            }
        );
        assert!(encode("a", &[], &[]).is_empty(), "nothing to tell, nothing sent");
        assert_eq!(decode(&encode("a", &[], &[3])[0]).expect("valid").left, vec![3]);
    }

    #[test]
    fn a_large_roster_splits_under_the_payload_limit_and_loses_nobody() {
        let viewers: Vec<_> = (0..600).map(|k| viewer((1 << 52) - 1 - k)).collect();
        let left: Vec<u64> = (0..900).map(|k| (1 << 52) + k).collect();
        let out = encode("s", &viewers, &left);
        assert!(out.len() > 5, "{} messages", out.len());
        let (mut got_v, mut got_l) = (Vec::new(), Vec::new());
        for p in &out {
            assert!(p.len() <= MAX_PAYLOAD, "{} bytes", p.len());
            let m = decode(p).expect("valid");
            got_v.extend(m.viewers);
            got_l.extend(m.left);
        }
        assert_eq!(got_v, viewers);
        assert_eq!(got_l, left);
    }

    #[test]
    fn malformed_messages_are_refused() {
        for bad in [
            "",
            "{",
            "[]",
            r#"{"viewers":[]}"#,
            r#"{"scene":"Bad Id"}"#,
            r#"{"scene":"a","viewers":[{"id":1,"pose":{"position":[1e99,0,0],"orientation":[0,0,0,1]}}]}"#,
            r#"{"scene":"a","viewers":[{"id":-1,"pose":null}]}"#,
            r#"{"scene":"a","extra":1}"#,
        ] {
            assert_eq!(decode(bad), None, "{bad}");
        }
        let many: Vec<_> = (0..=MAX_VIEWERS_PER_MSG as u64).collect();
        let payload = serde_json::json!({"scene": "a", "left": many}).to_string();
        assert_eq!(decode(&payload), None);
    }
}
