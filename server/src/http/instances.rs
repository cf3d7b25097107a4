//! `GET /api/scenes/{id}/instances` as a streamed body (issue 23): the JSON is written a few
//! hundred instances at a time, only as the connection takes them, from one compact copy of the
//! version's instances shared by every response streaming it. A client that does not read costs
//! its connection's buffers, not the list; the write deadline (`conn.rs`) then drops it.

use std::collections::HashMap;
use std::convert::Infallible;
use std::pin::Pin;
use std::sync::{Arc, Mutex, PoisonError, Weak};
use std::task::{Context, Poll};

use axum::body::Body;
use axum::http::{HeaderValue, header};
use axum::response::Response;
use bytes::Bytes;
use http_body::Frame;

use super::scenes::ApiError;
use crate::store::SceneStore;
use crate::store::scenes::{InstanceRow, InstanceTable, SceneMeta};

/// Instances serialised per body frame (about 40 KB of JSON).
pub const CHUNK_ROWS: usize = 256;

/// Frames produced in one go before the task yields, so one long list does not hold a worker
/// thread while other connections wait.
const FRAMES_PER_POLL: u32 = 8;

/// The instance tables being streamed, by scene: one copy per version however many responses
/// read it, freed when the last of them ends.
#[derive(Debug, Default)]
pub struct InstanceTables {
    held: Mutex<HashMap<String, Weak<InstanceTable>>>,
    /// One load at a time: they all wait on the store's connection anyway, and a burst of
    /// requests for one scene then loads it once.
    loading: tokio::sync::Mutex<()>,
}

impl InstanceTables {
    fn lookup(&self, scene: &SceneMeta) -> Option<Arc<InstanceTable>> {
        let held = self.held.lock().unwrap_or_else(PoisonError::into_inner);
        held.get(&scene.id)?
            .upgrade()
            .filter(|t| t.created_unix == scene.created_unix && t.version >= scene.version)
    }

    /// The instances of `scene` at its version or later (an edit may have landed since the caller
    /// read it; the table says which version it holds).
    pub async fn get(&self, store: Arc<dyn SceneStore>, scene: &SceneMeta) -> Result<Arc<InstanceTable>, ApiError> {
        if let Some(t) = self.lookup(scene) {
            return Ok(t);
        }
        let _one = self.loading.lock().await;
        if let Some(t) = self.lookup(scene) {
            return Ok(t);
        }
        let sid = scene.id.clone();
        let table = tokio::task::spawn_blocking(move || store.instance_table(&sid))
            .await
            .map_err(ApiError::internal)??;
        let table = Arc::new(table);
        let mut held = self.held.lock().unwrap_or_else(PoisonError::into_inner);
        held.retain(|_, t| t.strong_count() > 0);
        held.insert(scene.id.clone(), Arc::downgrade(&table));
        Ok(table)
    }

    /// Forgets a deleted scene's table (responses streaming it keep their copy).
    pub async fn forget(&self, id: &str) {
        // After any load in flight, which may have read the scene before it was deleted.
        let _one = self.loading.lock().await;
        self.held.lock().unwrap_or_else(PoisonError::into_inner).remove(id);
    }
}

/// The response: `{"instances":[{id, model, position, rotation, scale}…],"version":N}`, byte for
/// byte what `Json(json!({"version", "instances"}))` wrote before (keys sorted, `f32`s written as
/// the `f64`s `serde_json::Value` holds), with chunked transfer encoding.
pub fn response(table: Arc<InstanceTable>) -> Response {
    let mut r = Response::new(Body::new(InstancesBody::new(table)));
    r.headers_mut()
        .insert(header::CONTENT_TYPE, HeaderValue::from_static("application/json"));
    r
}

/// The streamed body over a shared table.
#[derive(Debug)]
pub struct InstancesBody {
    table: Arc<InstanceTable>,
    /// Each model name as a JSON string.
    models: Vec<Vec<u8>>,
    /// Next row to write; `None` before the opening bracket.
    next: Option<usize>,
    done: bool,
    frames: u32,
}

impl InstancesBody {
    /// A body that writes `table`.
    pub fn new(table: Arc<InstanceTable>) -> Self {
        let models = table
            .models
            .iter()
            .map(|m| serde_json::to_vec(m).unwrap_or_else(|_| b"\"\"".to_vec()))
            .collect();
        Self {
            table,
            models,
            next: None,
            done: false,
            frames: 0,
        }
    }

    fn chunk(&mut self) -> Bytes {
        let rows = &self.table.rows;
        let start = self.next.unwrap_or(0);
        let end = (start + CHUNK_ROWS).min(rows.len());
        let mut out = Vec::with_capacity((end - start) * 160 + 32);
        if self.next.is_none() {
            out.extend_from_slice(b"{\"instances\":[");
        }
        for (k, r) in rows[start..end].iter().enumerate() {
            if start + k > 0 {
                out.push(b',');
            }
            write_row(&mut out, r, &self.models);
        }
        self.next = Some(end);
        if end == rows.len() {
            out.extend_from_slice(b"],\"version\":");
            json(&mut out, &self.table.version);
            out.push(b'}');
            self.done = true;
        }
        Bytes::from(out)
    }
}

/// Appends `v` as JSON (writing into a `Vec` cannot fail; numbers and strings always serialise).
fn json<T: serde::Serialize + ?Sized>(out: &mut Vec<u8>, v: &T) {
    let _ = serde_json::to_writer(&mut *out, v);
}

fn write_row(out: &mut Vec<u8>, r: &InstanceRow, models: &[Vec<u8>]) {
    out.extend_from_slice(b"{\"id\":");
    json(out, &r.id);
    out.extend_from_slice(b",\"model\":");
    out.extend_from_slice(models.get(r.model as usize).map_or(b"\"\"", |m| m));
    out.extend_from_slice(b",\"position\":[");
    for (k, v) in r.position.iter().enumerate() {
        if k > 0 {
            out.push(b',');
        }
        json(out, &f64::from(*v));
    }
    out.extend_from_slice(b"],\"rotation\":");
    json(out, &f64::from(r.rotation));
    out.extend_from_slice(b",\"scale\":");
    json(out, &f64::from(r.scale));
    out.push(b'}');
}

impl http_body::Body for InstancesBody {
    type Data = Bytes;
    type Error = Infallible;

    fn poll_frame(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Option<Result<Frame<Bytes>, Infallible>>> {
        let this = self.get_mut();
        if this.done {
            return Poll::Ready(None);
        }
        // hyper asks for the next frame only while its write buffer has room, so an unread
        // connection stops the stream here; a fast one still lets other tasks run in between.
        this.frames += 1;
        if this.frames > FRAMES_PER_POLL {
            this.frames = 0;
            cx.waker().wake_by_ref();
            return Poll::Pending;
        }
        Poll::Ready(Some(Ok(Frame::data(this.chunk()))))
    }

    fn is_end_stream(&self) -> bool {
        self.done
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::scenes::Instance;
    use http_body::Body as _;

    /// The body, collected frame by frame.
    fn collect(table: InstanceTable) -> (Vec<u8>, usize) {
        let mut body = InstancesBody::new(Arc::new(table));
        let mut cx = Context::from_waker(std::task::Waker::noop());
        let (mut out, mut frames) = (Vec::new(), 0);
        loop {
            match Pin::new(&mut body).poll_frame(&mut cx) {
                Poll::Ready(Some(Ok(f))) => {
                    out.extend_from_slice(f.data_ref().map_or(&[][..], |d| &d[..]));
                    frames += 1;
                }
                Poll::Ready(None) => return (out, frames),
                Poll::Pending => {}
            }
        }
    }

    #[test]
    fn streamed_list_is_byte_for_byte_the_old_serialisation() {
        let models = ["oak", "birch \"silver\"\u{e9}", "pine"];
        let mut rows = Vec::new();
        let mut list = Vec::new();
        // Awkward floats (not exact in f32, tiny, huge, negative zero) and gaps in the ids.
        for k in 0..3000u32 {
            let f = k as f32;
            let r = InstanceRow {
                id: 1 + k * 3,
                model: k % 3,
                position: [f * 0.1 - 150.3, -0.0, 1e-7 * f - 42.42],
                rotation: f * 0.001 * std::f32::consts::PI,
                scale: 0.7 + (k % 7) as f32 * 0.1,
            };
            list.push(Instance {
                id: r.id,
                model: models[r.model as usize].to_string(),
                position: r.position,
                rotation: r.rotation,
                scale: r.scale,
            });
            rows.push(r);
        }
        let table = InstanceTable {
            version: 17,
            created_unix: 0,
            models: models.iter().map(ToString::to_string).collect(),
            rows,
        };
        let old = serde_json::to_vec(&serde_json::json!({ "version": 17, "instances": list })).expect("json");
        let (new, frames) = collect(table);
        assert_eq!(String::from_utf8_lossy(&new), String::from_utf8_lossy(&old));
        assert_eq!(frames, 3000usize.div_ceil(CHUNK_ROWS));
        // Empty and one-instance lists.
        for n in [0usize, 1] {
            let t = InstanceTable {
                version: 1,
                created_unix: 0,
                models: vec!["oak".into()],
                rows: (0..n)
                    .map(|_| InstanceRow {
                        id: 1,
                        model: 0,
                        position: [1.5, 0.0, -2.0],
                        rotation: 0.0,
                        scale: 1.0,
                    })
                    .collect(),
            };
            let l: Vec<Instance> = t
                .rows
                .iter()
                .map(|r| Instance {
                    id: r.id,
                    model: "oak".into(),
                    position: r.position,
                    rotation: r.rotation,
                    scale: r.scale,
                })
                .collect();
            let old = serde_json::to_vec(&serde_json::json!({ "version": 1, "instances": l })).expect("json");
            assert_eq!(collect(t).0, old);
        }
    }
}
