//! Garbage collection of scene files: what retention prunes, and what nothing names any more.
//!
//! Contract: a file under `DATA/assets/scenes/` is deleted only when no version the store keeps
//! names it and it is older than the grace period (an edit or creation in flight has written its
//! files but not yet committed the version that names them; they are young). Pruned versions'
//! files are deleted at once by [`remove_files`] (the store has already dropped their rows, and a
//! version number is never made twice). Run at start (grace 0: nothing is in flight) and
//! periodically (`serve --gc-interval-s`). Tile blobs ([`super::tiles`]) are named by pack indexes,
//! not versions: one is deleted when no pack index in its folder names it, at any age, under the
//! folder's blob lock (no publish can be reusing it meanwhile); in a folder shared by replicas
//! also under the folder's file lock, held exclusively ([`AssetStore::try_folder_lock_exclusive`]).

use std::collections::{HashMap, HashSet};
use std::time::{Duration, SystemTime};

use super::assets::AssetStore;
use super::scenes::{Limits, Pruned, SceneStore, StoreError};

/// How old an unreferenced file must be before a periodic sweep deletes it: far longer than any
/// publish takes between writing its files and committing its version.
pub const GRACE: Duration = Duration::from_mins(10);

/// What one collection did.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Collected {
    /// Versions pruned by the retention.
    pub versions: usize,
    /// Files deleted.
    pub files: usize,
    /// Bytes those files took.
    pub bytes: u64,
}

/// Deletes pruned versions' files but terrain files (left to [`sweep`]); returns (files, bytes). Failures are logged, not returned: the
/// next sweep retries.
pub fn remove_files(assets: &AssetStore, pruned: &[Pruned]) -> (usize, u64) {
    let (mut n, mut bytes) = (0, 0);
    // A terrain file is shared by the versions from the one that set it on: the sweep deletes it
    // once no kept version names it.
    for rel in pruned
        .iter()
        .flat_map(|p| &p.files)
        .filter(|f| !crate::terrain::ground::is_terrain_file(f))
    {
        let len = std::fs::metadata(assets.root().join(rel)).map_or(0, |m| m.len());
        match assets.remove(rel) {
            Ok(true) => {
                n += 1;
                bytes += len;
            }
            Ok(false) => {}
            Err(e) => tracing::warn!(file = %rel, error = %e, "could not delete a pruned version's file"),
        }
    }
    (n, bytes)
}

/// Applies the retention to every scene, deletes the pruned versions' files, then sweeps.
pub fn collect(
    assets: &AssetStore,
    scenes: &dyn SceneStore,
    limits: &Limits,
    now_unix: u64,
    grace: Duration,
) -> Result<Collected, StoreError> {
    let pruned = scenes.prune(limits, now_unix)?;
    let (files, bytes) = remove_files(assets, &pruned);
    let swept = sweep(assets, scenes, grace)?;
    Ok(Collected {
        versions: pruned.len(),
        files: files + swept.files,
        bytes: bytes + swept.bytes,
    })
}

/// Deletes files under `scenes/` that no kept version names and that are older than `grace`:
/// lost races, versions pruned while their files could not be deleted, folders of deleted scenes,
/// temporary files.
pub fn sweep(assets: &AssetStore, scenes: &dyn SceneStore, grace: Duration) -> Result<Collected, StoreError> {
    let kept: HashMap<String, HashSet<String>> = scenes
        .files()?
        .into_iter()
        .map(|s| (s.id, s.files.into_iter().collect()))
        .collect();
    let root = assets.root().join("scenes");
    let mut out = Collected::default();
    let Ok(dirs) = std::fs::read_dir(&root) else {
        return Ok(out);
    };
    let now = SystemTime::now();
    for dir in dirs.flatten() {
        let Some(id) = dir.file_name().to_str().map(String::from) else {
            continue;
        };
        if !dir.path().is_dir() {
            continue;
        }
        let names = kept.get(&id);
        let Ok(files) = std::fs::read_dir(dir.path()) else {
            continue;
        };
        let folder = format!("scenes/{id}");
        let blobs = assets.blob_lock(&folder);
        let _blobs = blobs.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        // Beside other replicas, tile blobs go only while no publish anywhere holds the folder
        // (then every index a publish wrote is on disk: read them all); if one does, next time.
        let (_exclusive, tiles) = if assets.is_shared() {
            match assets.try_folder_lock_exclusive(&folder) {
                Ok(Some(f)) => {
                    assets.rescan(&folder);
                    (Some(f), super::tiles::referenced(assets, &folder))
                }
                _ => (None, None),
            }
        } else {
            (None, super::tiles::referenced(assets, &folder))
        };
        let mut left = 0;
        for f in files.flatten() {
            let Some(name) = f.file_name().to_str().map(String::from) else {
                left += 1;
                continue;
            };
            let rel = format!("scenes/{id}/{name}");
            let meta = f.metadata().ok();
            let old = meta
                .as_ref()
                .and_then(|m| m.modified().ok())
                .is_some_and(|t| now.duration_since(t).unwrap_or_default() >= grace);
            let named = names.is_some_and(|n| n.contains(&rel));
            let (named, old) = if name.ends_with(&format!(".{}", super::tiles::TILE_EXT)) {
                (tiles.as_ref().is_none_or(|t| t.contains(&rel)), true)
            } else {
                (named, old)
            };
            if named || !old || !meta.as_ref().is_some_and(std::fs::Metadata::is_file) {
                left += 1;
                continue;
            }
            match assets.remove(&rel) {
                Ok(_) => {
                    out.files += 1;
                    out.bytes += meta.map_or(0, |m| m.len());
                }
                Err(e) => {
                    left += 1;
                    tracing::warn!(file = %rel, error = %e, "could not delete an unreferenced file");
                }
            }
        }
        if left == 0 && names.is_none() {
            // A deleted scene's folder, now empty (a new scene of that id would recreate it).
            let _ = std::fs::remove_dir(dir.path());
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::SqliteStore;
    use crate::store::scenes::{Bounds, EditBatch, NewInstance, NewScene, Published, SceneAuth};

    #[test]
    fn pruned_and_unnamed_files_go_named_and_young_ones_stay() {
        let dir = std::env::temp_dir().join(format!("canopy-gc-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let assets = AssetStore::open(&dir).expect("assets");
        let store = SqliteStore::in_memory().expect("db");
        let limits = Limits {
            keep_versions: 2,
            ..Limits::default()
        };
        let mut publish = |m: &crate::store::scenes::SceneMeta,
                           _: &[crate::store::scenes::Instance],
                           _: &crate::store::scenes::Changes| {
            let a = assets
                .put(
                    "scenes/a",
                    &format!("v{}", m.version),
                    "cpack",
                    format!("pack {}", m.version).as_bytes(),
                )
                .map_err(|e| StoreError::Publish(e.to_string()))?;
            Ok(Published {
                manifest: "{}".into(),
                bytes: a.len,
                files: vec![a.rel.clone()],
            })
        };
        let scene = NewScene {
            id: "a".into(),
            name: "A".into(),
            public: true,
            bounds: Bounds {
                min: [0.0, 0.0],
                max: [10.0, 10.0],
            },
            auth: SceneAuth {
                write_hash: [1; 32],
                read_hash: None,
            },
            owner: String::new(),
            terrain: None,
        };
        store.create(&scene, &[], &limits, &mut publish).expect("create");
        let add = EditBatch {
            add: vec![NewInstance {
                model: "m".into(),
                position: [1.0, 0.0, 1.0],
                rotation: 0.0,
                scale: 1.0,
            }],
            ..EditBatch::default()
        };
        let mut removed = 0;
        for _ in 0..5 {
            let e = store.edit("a", &add, &limits, &mut publish).expect("edit");
            removed += remove_files(&assets, &e.pruned).0;
        }
        assert_eq!(removed, 4, "versions 1 to 4 pruned");
        assert_eq!(assets.list("scenes/a/").len(), 2);
        // A lost race's file, a deleted scene's folder, a temporary file: young, they stay.
        let stray = assets.put("scenes/a", "v6", "cpack", b"lost race").expect("stray");
        assets.put("scenes/gone", "v1", "cpack", b"orphan").expect("orphan");
        std::fs::write(dir.join("scenes/a/.tmp-v7-1-0123456789abcdef"), b"tmp").expect("tmp");
        let young = sweep(&assets, &store, Duration::from_mins(10)).expect("sweep");
        assert_eq!(young.files, 0);
        let all = sweep(&assets, &store, Duration::ZERO).expect("sweep");
        assert_eq!(all.files, 3);
        assert!(assets.get(&stray.rel).is_none());
        assert!(!dir.join("scenes/gone").exists());
        let left: Vec<String> = std::fs::read_dir(dir.join("scenes/a"))
            .expect("ls")
            .flatten()
            .map(|e| e.file_name().to_string_lossy().into_owned())
            .collect();
        assert_eq!(left.len(), 2, "{left:?}");
        assert_eq!(store.files().expect("files")[0].files.len(), 2);
        let _ = std::fs::remove_dir_all(&dir);
    }
}
