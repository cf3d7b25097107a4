//! Per-scene locks within one process: changes to one scene are made one at a time here (the
//! database decides between processes), changes to different scenes in parallel.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard, Weak};

/// Locks kept before the unused ones are dropped.
const KEPT: usize = 1024;

/// One lock per scene id, created on first use and dropped when no one holds it.
#[derive(Debug, Default)]
pub struct SceneLocks {
    locks: Mutex<HashMap<String, Weak<Mutex<()>>>>,
}

/// Locks `m`, whether or not a holder panicked.
pub fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

impl SceneLocks {
    /// The lock that serialises changes to scene `id` in this process.
    pub fn get(&self, id: &str) -> Arc<Mutex<()>> {
        let mut locks = lock(&self.locks);
        if let Some(l) = locks.get(id).and_then(Weak::upgrade) {
            return l;
        }
        if locks.len() >= KEPT {
            locks.retain(|_, w| w.strong_count() > 0);
        }
        let l = Arc::new(Mutex::new(()));
        locks.insert(id.to_string(), Arc::downgrade(&l));
        l
    }
}
