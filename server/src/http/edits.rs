//! Where edits and creations run: threads of their own at a lower CPU priority (nice +10) than
//! the rest of the server. An edit's work (the scene's pack rebuilt, hashed and written) is CPU
//! for milliseconds; on a machine with few cores, reads of other scenes woken meanwhile waited for
//! a core behind it (p99 of a manifest read 7.4 ms under 4 writers of a 50,000-instance scene,
//! 1.6 ms idle: the read's own database work stayed under 2 ms, the rest was waiting to run).
//! At nice +10 the scheduler lets a woken read preempt the edit at once.

use std::sync::LazyLock;

use tokio::sync::{Semaphore, oneshot};

use super::scenes::ApiError;

/// Edits and creations running at once (more wait for a place; each also waits for its scene).
pub const MAX_RUNNING: usize = 64;

/// Nice value of the threads that run edits.
pub const EDIT_NICE: i32 = 10;

static RUNNING: LazyLock<Semaphore> = LazyLock::new(|| Semaphore::new(MAX_RUNNING));

/// Lowers the calling thread's CPU priority (Linux: a thread's own nice value). Failure changes
/// nothing but the priority, so it is only logged.
fn lower_priority() {
    // Linux: `setpriority` on a thread id sets that thread's nice value only.
    let tid = rustix::thread::gettid();
    if let Err(e) = rustix::process::setpriority_process(Some(tid), EDIT_NICE) {
        tracing::debug!(error = %e, "could not lower an edit thread's priority");
    }
}

/// Runs `f` (a store change) on a thread of its own at [`EDIT_NICE`]; at most [`MAX_RUNNING`] at
/// once.
pub async fn run<T: Send + 'static>(f: impl FnOnce() -> Result<T, ApiError> + Send + 'static) -> Result<T, ApiError> {
    let _place = RUNNING.acquire().await.map_err(ApiError::internal)?;
    let (tx, rx) = oneshot::channel();
    std::thread::Builder::new()
        .name("canopy-edit".into())
        .spawn(move || {
            lower_priority();
            let _ = tx.send(f());
        })
        .map_err(ApiError::internal)?;
    rx.await.map_err(ApiError::internal)?
}
