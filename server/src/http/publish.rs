//! Publishing scene versions: a version's instance pack (per tile, from the pack draft of the
//! version before when one is held) and manifest, written before the store commits the version
//! ([`publish`]); the store change that makes the version, with the deletion of what a refused
//! publish wrote and of the files retention pruned ([`apply_version_then`]: an edit, or a terrain
//! set or removed).
//!
//! With a terrain ([`Changes::terrain`]), the pack places each instance at the terrain's height
//! plus its stored y, and the manifest names the terrain file; the file is listed among the
//! version's files (garbage collection keeps it while a kept version names it) and its size counts
//! in the version's bytes. Without one, the pack and manifest are byte for byte those of flat
//! ground.

use std::sync::Arc;

use canopy_shared::manifest::{
    MANIFEST_FORMAT, MANIFEST_VERSION, Manifest, ManifestBounds, ManifestModel, ManifestPack,
};

use super::AppState;
use super::scenes::ApiError;
use crate::store::assets::AssetStore;
use crate::store::gc;
use crate::store::pack_draft::PackDraft;
use crate::store::scenes::{
    Changes, EditBatch, Edited, Instance, Limits, Publish, Published, SceneMeta, SceneStore, StoreError,
};
use crate::store::tiles;
use crate::terrain::{Ground, ground};

/// Builds and writes a version's pack and manifest; returns what it wrote and the version's
/// pack draft. `base` is the draft of the version before, if held: a small edit then re-encodes
/// only the tiles it touched ([`PackDraft::apply`]).
pub fn publish(
    assets: &AssetStore,
    base: Option<PackDraft>,
    meta: &SceneMeta,
    list: &[Instance],
    changes: &Changes,
) -> Result<(Published, PackDraft), StoreError> {
    publish_on(assets, base, meta, list, changes, None)
}

/// [`publish`], where `known` is a terrain already decoded (the one a terrain change just wrote):
/// the version's terrain is taken from it or from `base`'s when it is the same file, else read
/// from its file.
pub fn publish_on(
    assets: &AssetStore,
    base: Option<PackDraft>,
    meta: &SceneMeta,
    list: &[Instance],
    changes: &Changes,
    known: Option<&Arc<Ground>>,
) -> Result<(Published, PackDraft), StoreError> {
    let pe = |e: &dyn std::fmt::Display| StoreError::Publish(e.to_string());
    let ground = match changes.terrain.as_deref() {
        None => None,
        Some(json) => {
            let held: Vec<&Arc<Ground>> = base
                .as_ref()
                .and_then(PackDraft::ground)
                .into_iter()
                .chain(known)
                .collect();
            Some(ground::load(assets, json, &held).map_err(|e| pe(&e))?)
        }
    };
    let draft = match base {
        Some(d) => d.apply_on(meta.version, &meta.bounds, ground.clone(), changes, list),
        None => PackDraft::build_on(meta.version, &meta.bounds, list, ground.clone()),
    }
    .map_err(|e| pe(&e))?;
    let known = assets.models();
    let mut levels = crate::discrete_files::manifest_levels(assets, &known);
    let mut models = Vec::with_capacity(draft.names().len());
    for n in draft.names() {
        let a = known
            .get(n)
            .ok_or_else(|| StoreError::Invalid(format!("unknown model {n:?}")))?;
        models.push(ManifestModel {
            name: n.clone(),
            url: a.url(),
            sha256: a.sha256.clone(),
            size: a.len,
            levels: levels.remove(n).unwrap_or_default(),
        });
    }
    let dir = format!("scenes/{}", meta.id);
    let stem = format!("v{}", meta.version);
    // Per tile: only the tiles this version changed are new files. A first version is written
    // whole as well, so a static copy of the assets folder holds it.
    let written = tiles::publish_draft(assets, &dir, &stem, &draft, meta.version == 1).map_err(|e| pe(&e))?;
    let (pack_asset, tiles, tables_len) = (written.pack, written.tiles, written.tables_len);
    let manifest = Manifest {
        format: MANIFEST_FORMAT.into(),
        format_version: MANIFEST_VERSION,
        scene: meta.id.clone(),
        name: meta.name.clone(),
        version: meta.version,
        bounds: ManifestBounds {
            min: meta.bounds.min,
            max: meta.bounds.max,
        },
        instance_count: list.len() as u64,
        models,
        pack: ManifestPack {
            url: pack_asset.url(),
            sha256: pack_asset.sha256.clone(),
            size: pack_asset.len,
            tables_len,
        },
        tiles,
        terrain: ground.as_ref().map(|g| g.terrain.clone()),
    };
    let text = manifest.to_json().map_err(|e| pe(&e))?;
    let mut files = vec![pack_asset.rel.clone(), written.index.rel.clone()];
    if let Some(g) = &ground {
        files.push(g.rel().to_string());
    }
    // A first version's manifest is an asset too, so a static copy of DATA/assets holds each
    // scene's first version whole; later versions' manifests live in their version rows only
    // (one file fewer to create, sync and delete per edit).
    if meta.version == 1 {
        let manifest_asset = assets
            .put_unsynced(&dir, &format!("v{}", meta.version), "json", text.as_bytes())
            .map_err(|e| pe(&e))?;
        files.push(manifest_asset.rel.clone());
    }
    // Every rename durable before the store commits the version that names them.
    assets.sync_folder(&dir).map_err(|e| pe(&e))?;
    // Tile blobs are not listed: versions share them, and they live while an index names them.
    let published = Published {
        bytes: pack_asset.len + text.len() as u64 + ground.as_ref().map_or(0, |g| g.terrain.size),
        files,
        manifest: text,
    };
    Ok((published, draft))
}

/// Deletes the files of publishes whose version the store did not commit (a refusal, a lost
/// compare-and-swap), unless the version kept under that number is the same (same files).
pub fn discard(state: &AppState, scene: &str, written: &[(u64, Published)]) {
    if state.inner.assets.is_shared() {
        // Another replica may be committing a version with these very files (same content, same
        // names): the periodic sweep deletes them once no kept version names them, after its
        // grace.
        return;
    }
    for (v, p) in written {
        match state.inner.scenes.manifest(scene, Some(*v)) {
            Ok(Some(m)) if m == p.manifest => {}
            Ok(_) => {
                // A terrain file may be the one the kept version names: left to the sweep.
                for f in p.files.iter().filter(|f| !ground::is_terrain_file(f)) {
                    if let Err(e) = state.inner.assets.remove(f) {
                        tracing::warn!(file = %f, error = %e, "could not delete an uncommitted version's file");
                    }
                }
            }
            // Left for the periodic sweep.
            Err(e) => tracing::warn!(scene, error = %e, "could not check an uncommitted version"),
        }
    }
}

/// Applies a validated batch through the store, deleting what a refused publish wrote and the
/// files of the versions the retention pruned; returns the scene at its new version and the ids of
/// the added instances.
pub fn apply_edit(
    state: &AppState,
    id: &str,
    batch: &EditBatch,
    limits: &Limits,
) -> Result<(SceneMeta, Vec<u32>), ApiError> {
    let (done, cleanup) = apply_edit_then(state, id, batch, limits)?;
    cleanup();
    Ok(done)
}

/// Most unreferenced tile blobs one edit's cleanup deletes, one at a time between the scene's
/// publishes ([`tiles::drop_unreferenced_between`]): the hundreds a bulk edit's pruned version
/// leaves go over the following edits and the periodic sweep.
pub const CLEANUP_TILES: usize = 16;

/// Deletes files nothing names any more (after an edit): run after the answer is sent.
pub type Cleanup = Box<dyn FnOnce() + Send>;

/// [`apply_edit`], with the deletion of pruned versions' files and of (at most [`CLEANUP_TILES`])
/// tile blobs no index names any more left to the returned [`Cleanup`], to run after the answer.
pub fn apply_edit_then(
    state: &AppState,
    id: &str,
    batch: &EditBatch,
    limits: &Limits,
) -> Result<((SceneMeta, Vec<u32>), Cleanup), ApiError> {
    let (n_add, mut added) = (batch.add.len(), Vec::new());
    let (meta, cleanup) = apply_version_then(
        state,
        id,
        None,
        &mut |l| added = l[l.len() - n_add..].iter().map(|i| i.id).collect(),
        &mut |store, publish| store.edit(id, batch, limits, publish),
    )?;
    Ok(((meta, added), cleanup))
}

/// Makes a version of scene `id` through `commit` (a store change given the publisher), with the
/// scene's blob and folder locks held, its pack draft taken and put back; `seen` gets the
/// instance list of each publish. `known` is a terrain already decoded for [`publish_on`].
/// Deletes what uncommitted publishes wrote; leaves the pruned versions' files (and at most
/// [`CLEANUP_TILES`] unreferenced tile blobs) to the returned [`Cleanup`].
pub fn apply_version_then(
    state: &AppState,
    id: &str,
    known: Option<&Arc<Ground>>,
    seen: &mut dyn FnMut(&[Instance]),
    commit: &mut dyn FnMut(&dyn SceneStore, Publish<'_>) -> Result<Edited, StoreError>,
) -> Result<(SceneMeta, Cleanup), ApiError> {
    let mut written = Vec::new();
    // Held until the version commits: the tile blobs this publish reuses must stay.
    let dir = format!("scenes/{id}");
    let blobs = state.inner.assets.blob_lock(&dir);
    let mut guard = blobs.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
    *guard += 1;
    let replicas = state
        .inner
        .assets
        .folder_lock_shared(&dir)
        .map_err(ApiError::internal)?;
    // The draft of the scene's last committed version; one publish may take it (a lost
    // compare-and-swap's retry then builds afresh), and the committed version's goes back.
    let (drafts, mut base, mut made) = (&state.inner.drafts, None, None);
    let result = commit(state.inner.scenes.as_ref(), &mut |m, l, ch| {
        seen(l);
        if made.is_none() {
            base = drafts.take(id, m.created_unix);
        }
        let (p, draft) = publish_on(&state.inner.assets, base.take(), m, l, ch, known)?;
        made = Some((m.created_unix, draft));
        written.push((m.version, p.clone()));
        Ok(p)
    });
    if let (Ok(_), Some((created, draft))) = (&result, made) {
        drafts.put(id, created, draft);
    }
    drop(replicas);
    drop(guard);
    let (scene, assets) = (id.to_string(), state.inner.assets.clone());
    match result {
        Ok(e) => {
            // The last publish is the committed version; earlier ones lost a compare-and-swap.
            written.pop();
            discard(state, id, &written);
            let stray = !written.is_empty();
            let cleanup: Cleanup = Box::new(move || {
                let (mut files, mut bytes) = gc::remove_files(&assets, &e.pruned);
                // Beside other replicas, tile blobs go in the periodic sweep only (it takes the
                // folder's file lock exclusively).
                if (!e.pruned.is_empty() || stray) && !assets.is_shared() {
                    let (f, b) = tiles::drop_unreferenced_between(&assets, &dir, CLEANUP_TILES);
                    (files, bytes) = (files + f, bytes + b);
                }
                if !e.pruned.is_empty() {
                    tracing::debug!(scene, versions = e.pruned.len(), files, bytes, "old versions pruned");
                }
            });
            Ok((e.meta, cleanup))
        }
        Err(err) => {
            discard(state, id, &written);
            if !written.is_empty() && !assets.is_shared() {
                let _blobs = blobs.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
                tiles::drop_unreferenced(&assets, &dir, CLEANUP_TILES);
            }
            Err(err.into())
        }
    }
}
