//! The viewer's presence thread: it keeps the scene's WebSocket (`/api/scenes/ID/live`), sends
//! this viewer's pose at most every [`POSE_INTERVAL`] and collects the others' poses.

use std::collections::HashMap;
use std::sync::mpsc::Receiver;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use canopy_client::stream::Camera;
use glam::Vec3;

/// Poses sent at most this often.
pub const POSE_INTERVAL: Duration = Duration::from_millis(200);

/// Others' positions by viewer id, with when each was last heard of.
pub type Presence = Arc<Mutex<HashMap<String, (Vec3, Instant)>>>;

/// Starts the presence thread on `url`: others' poses go into `presence`, this viewer's latest
/// pose from `poses` goes out.
pub fn spawn_presence(url: String, presence: Presence, poses: Receiver<Camera>) {
    use futures_util::{SinkExt, StreamExt};
    use tokio_tungstenite::tungstenite::Message;
    std::thread::spawn(move || {
        let Ok(rt) = tokio::runtime::Builder::new_current_thread().enable_all().build() else {
            return;
        };
        rt.block_on(async move {
            let Ok((ws, _)) = tokio_tungstenite::connect_async(url.as_str()).await else {
                return;
            };
            let (mut sink, mut stream) = ws.split();
            let mut tick = tokio::time::interval(POSE_INTERVAL);
            loop {
                tokio::select! {
                    msg = stream.next() => {
                        let Some(Ok(Message::Text(t))) = msg else {
                            if msg.is_none() { return; }
                            continue;
                        };
                        apply_presence(&presence, t.as_str());
                    }
                    _ = tick.tick() => {
                        let mut latest = None;
                        while let Ok(c) = poses.try_recv() {
                            latest = Some(c);
                        }
                        if let Some(c) = latest {
                            let q = glam::Quat::from_euler(glam::EulerRot::YXZ, -c.yaw, c.pitch, 0.0);
                            let msg = serde_json::json!({
                                "type": "pose",
                                "position": c.eye.to_array(),
                                "orientation": q.to_array(),
                            });
                            if sink.send(Message::Text(msg.to_string().into())).await.is_err() {
                                return;
                            }
                        }
                    }
                }
            }
        });
    });
}

/// Applies one server message to the presence map (unknown messages are ignored). Messages are
/// the server's (`server/src/http/live.rs`): `welcome` lists `viewers` as `{viewer, pose}`,
/// `presence` carries `{viewer, pose: {position, orientation}}`, `leave` a `viewer`.
fn apply_presence(presence: &Presence, text: &str) {
    let Ok(mut p) = presence.lock() else { return };
    apply_presence_to(&mut p, text, Instant::now());
}

fn apply_presence_to(p: &mut HashMap<String, (Vec3, Instant)>, text: &str, now: Instant) {
    let Ok(v) = serde_json::from_str::<serde_json::Value>(text) else {
        return;
    };
    let pos = |v: &serde_json::Value| -> Option<Vec3> {
        let a = v.get("pose")?.get("position")?.as_array()?;
        let c = |i: usize| a.get(i).and_then(serde_json::Value::as_f64).map(|x| x as f32);
        let p = Vec3::new(c(0)?, c(1)?, c(2)?);
        p.is_finite().then_some(p)
    };
    let id = |v: &serde_json::Value| v.get("viewer").map(ToString::to_string);
    match v.get("type").and_then(|t| t.as_str()) {
        Some("presence") => {
            if let (Some(i), Some(x)) = (id(&v), pos(&v)) {
                p.insert(i, (x, now));
            }
        }
        Some("leave") => {
            if let Some(i) = id(&v) {
                p.remove(&i);
            }
        }
        Some("welcome") => {
            for o in v.get("viewers").and_then(|o| o.as_array()).into_iter().flatten() {
                if let (Some(i), Some(x)) = (id(o), pos(o)) {
                    p.insert(i, (x, now));
                }
            }
        }
        _ => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presence_follows_the_servers_messages() {
        let mut p = HashMap::new();
        let now = Instant::now();
        apply_presence_to(
            &mut p,
            r#"{"type":"welcome","viewer":7,"viewers":[{"viewer":3,"pose":{"position":[1,2,3],"orientation":[0,0,0,1]}},{"viewer":4,"pose":null}]}"#,
            now,
        );
        assert_eq!(p.len(), 1);
        assert_eq!(p["3"].0, Vec3::new(1.0, 2.0, 3.0));
        apply_presence_to(
            &mut p,
            r#"{"type":"presence","viewer":4,"pose":{"position":[5,6,7],"orientation":[0,0,0,1]}}"#,
            now,
        );
        assert_eq!(p["4"].0, Vec3::new(5.0, 6.0, 7.0));
        apply_presence_to(&mut p, r#"{"type":"leave","viewer":3}"#, now);
        assert!(!p.contains_key("3"));
        // Bad input changes nothing.
        for bad in [
            "not json",
            r#"{"type":"presence","viewer":9,"pose":{"position":["x",1,2]}}"#,
            r#"{"type":"presence"}"#,
        ] {
            apply_presence_to(&mut p, bad, now);
        }
        assert_eq!(p.len(), 1);
    }
}
