//! The instance lists of the scenes edited last, kept between edits so that an edit does not read
//! its whole scene back from the database first (30 ms of a one-instance edit on a 50,000-instance
//! scene). An entry serves only the exact version (and scene incarnation) it was made at, so a
//! stale one is never used: it is simply read again.

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};

use super::scenes::Instance;

/// Instances kept in all (about 80 bytes each: 32 MB).
pub const RECENT_INSTANCES: usize = 400_000;

#[derive(Debug)]
struct Entry {
    id: String,
    version: u64,
    created_unix: u64,
    list: Arc<Vec<Instance>>,
}

/// Most recently edited first; bounded by the instances held.
#[derive(Debug, Default)]
pub struct Recent {
    entries: Mutex<VecDeque<Entry>>,
}

impl Recent {
    fn lock(&self) -> std::sync::MutexGuard<'_, VecDeque<Entry>> {
        self.entries.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// Scene `id`'s instances at `version` of the scene made at `created_unix`, if kept.
    pub fn get(&self, id: &str, version: u64, created_unix: u64) -> Option<Arc<Vec<Instance>>> {
        self.lock()
            .iter()
            .find(|e| e.id == id && e.version == version && e.created_unix == created_unix)
            .map(|e| e.list.clone())
    }

    /// Takes scene `id`'s instances at `version` of the scene made at `created_unix`, if kept: the
    /// caller owns them (an edit changes them in place) and puts back what it commits.
    pub fn take(&self, id: &str, version: u64, created_unix: u64) -> Option<Arc<Vec<Instance>>> {
        let mut entries = self.lock();
        let at = entries
            .iter()
            .position(|e| e.id == id && e.version == version && e.created_unix == created_unix)?;
        entries.remove(at).map(|e| e.list)
    }

    /// Keeps scene `id`'s instances at `version` (after the commit that made it), in place of any
    /// older entry of the scene.
    pub fn put(&self, id: &str, version: u64, created_unix: u64, list: Arc<Vec<Instance>>) {
        let mut entries = self.lock();
        entries.retain(|e| e.id != id);
        if list.len() > RECENT_INSTANCES {
            return;
        }
        entries.push_front(Entry {
            id: id.to_string(),
            version,
            created_unix,
            list,
        });
        let mut held = 0;
        entries.retain(|e| {
            held += e.list.len();
            held <= RECENT_INSTANCES
        });
    }

    /// Drops scene `id`'s entry (the scene was deleted).
    pub fn forget(&self, id: &str) {
        self.lock().retain(|e| e.id != id);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn list(n: usize) -> Arc<Vec<Instance>> {
        Arc::new(
            (0..n as u32)
                .map(|id| Instance {
                    id,
                    model: "m".into(),
                    position: [0.0; 3],
                    rotation: 0.0,
                    scale: 1.0,
                })
                .collect(),
        )
    }

    #[test]
    fn only_the_exact_version_is_served_and_the_total_is_bounded() {
        let r = Recent::default();
        r.put("a", 3, 100, list(10));
        assert_eq!(r.get("a", 3, 100).map(|l| l.len()), Some(10));
        assert!(r.get("a", 2, 100).is_none());
        assert!(r.get("a", 3, 101).is_none(), "another scene of the same id");
        assert!(r.take("a", 3, 100).is_some());
        assert!(r.get("a", 3, 100).is_none(), "taken");
        r.put("a", 3, 100, list(10));
        r.put("a", 4, 100, list(11));
        assert!(r.get("a", 3, 100).is_none());
        r.put("b", 1, 100, list(RECENT_INSTANCES - 5));
        assert!(r.get("a", 4, 100).is_none(), "the oldest goes past the bound");
        assert!(r.get("b", 1, 100).is_some());
        r.forget("b");
        assert!(r.get("b", 1, 100).is_none());
    }
}
