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

/// How much nicer than the server the threads that run edits are.
pub const EDIT_NICE: i32 = 10;

static RUNNING: LazyLock<Semaphore> = LazyLock::new(|| Semaphore::new(MAX_RUNNING));

/// Lowers the calling thread's CPU priority (Linux: a thread's own nice value). Failure changes
/// nothing but the priority, so it is only logged.
fn lower_priority() {
    // Linux: `getpriority`/`setpriority` on a thread id read and set that thread's nice value
    // only. Relative, so that a server started nice keeps its edits below its reads.
    let tid = Some(rustix::thread::gettid());
    let set = rustix::process::getpriority_process(tid)
        .and_then(|nice| rustix::process::setpriority_process(tid, (nice + EDIT_NICE).min(19)));
    if let Err(e) = set {
        tracing::debug!(error = %e, "could not lower an edit thread's priority");
    }
}

/// Like [`run`], then, once the answer is on its way, the cleanup `f` returned beside it, on the
/// same thread (files nothing names any more).
pub async fn run_then<T: Send + 'static>(
    f: impl FnOnce() -> Result<(T, super::scenes::Cleanup), ApiError> + Send + 'static,
) -> Result<T, ApiError> {
    run_inner(move |tx: oneshot::Sender<Result<T, ApiError>>| match f() {
        Ok((v, cleanup)) => {
            let _ = tx.send(Ok(v));
            cleanup();
        }
        Err(e) => {
            let _ = tx.send(Err(e));
        }
    })
    .await
}

/// Runs `f` (a store change) on a thread of its own, [`EDIT_NICE`] nicer; at most [`MAX_RUNNING`] at
/// once.
pub async fn run<T: Send + 'static>(f: impl FnOnce() -> Result<T, ApiError> + Send + 'static) -> Result<T, ApiError> {
    run_inner(move |tx: oneshot::Sender<Result<T, ApiError>>| {
        let _ = tx.send(f());
    })
    .await
}

async fn run_inner<T: Send + 'static>(
    job: impl FnOnce(oneshot::Sender<Result<T, ApiError>>) + Send + 'static,
) -> Result<T, ApiError> {
    let _place = RUNNING.acquire().await.map_err(ApiError::internal)?;
    let (tx, rx) = oneshot::channel();
    std::thread::Builder::new()
        .name("canopy-edit".into())
        .spawn(move || {
            lower_priority();
            job(tx);
        })
        .map_err(ApiError::internal)?;
    rx.await.map_err(ApiError::internal)?
}

#[cfg(test)]
mod tests {
    /// The calling thread's nice value, from `/proc/thread-self/stat` (field 19).
    fn nice() -> Option<i32> {
        let stat = std::fs::read_to_string("/proc/thread-self/stat").ok()?;
        stat.rsplit_once(')')?.1.split_whitespace().nth(16)?.parse().ok()
    }

    #[test]
    fn an_edit_thread_is_ten_nicer_than_the_server() {
        let (before, after) = std::thread::spawn(|| {
            let before = nice();
            super::lower_priority();
            (before, nice())
        })
        .join()
        .expect("thread");
        let Some(before) = before else {
            return;
        };
        assert_eq!(after, Some((before + super::EDIT_NICE).min(19)));
        // Only that thread.
        assert_eq!(nice(), Some(before));
    }
}
