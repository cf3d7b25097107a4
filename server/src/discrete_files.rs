//! The discrete LOD files of a baked model: the baseline that downloads whole level files, as a
//! glTF viewer with LOD does (levels and thresholds: [`canopy_shared::discrete`]).
//!
//! Contract: from a `.ctree`'s bytes, [`level_files`] makes one `.glb` per level, written as a
//! careful user ships them (quantized, meshopt-compressed: [`export_glb_meshopt`]):
//! - geometry level `k`: the tree at rate [`LEVEL_RATES`]`[k]`, each node's VMI prefix
//!   ([`DecodedTree::to_model`]): exactly the leaves the client draws at that rate, with the bark
//!   of the viewer's variant `k` ([`LEVEL_BARK_MIN_RADII`], [`LEVEL_BARK_SIDES`]);
//! - the billboard level: two crossed vertical quads textured with the atlas's crossed-quad
//!   frames at its top resolution, the PNG bytes embedded as they are in the `.ctree`.
//!
//! They are stored as `trees/<model>-lod<k>-<source>.<hash16>.glb` ([`level_name`]: `source` is
//! the model file's own hash prefix) beside the model, and named in the scene manifest only when
//! every level of that exact model file is there ([`manifest_levels`]). A model without an atlas has no billboard level, so no level files.

use std::collections::HashMap;
use std::sync::Arc;

use canopy_shared::discrete::{
    LEVEL_BARK_MIN_RADII, LEVEL_BARK_SIDES, LEVEL_COUNT, LEVEL_RATES, level_name, parse_level_name,
};
use canopy_shared::format::atlas::{AtlasLayoutKind, AtlasTable};
use canopy_shared::format::directory::SectionKind;
use canopy_shared::format::tree::{DecodedTree, section_bytes};
use canopy_shared::manifest::ManifestFile;
use glam::Vec3;
use rayon::prelude::*;
use serde_json::json;

use crate::export_glb_meshopt::{BarkDetail, export_glb_meshopt_with};
use crate::export_gltf::{ExportError, write_glb};
use crate::store::{Asset, AssetError, AssetStore};

/// Why level files could not be made.
#[derive(Debug, thiserror::Error)]
pub enum LevelError {
    /// The model's file did not decode.
    #[error(transparent)]
    Format(#[from] canopy_shared::format::FormatError),
    /// A level did not export.
    #[error(transparent)]
    Export(#[from] ExportError),
    /// Reading or storing a file failed.
    #[error(transparent)]
    Asset(#[from] AssetError),
    /// Reading a model's file failed.
    #[error("reading {path}: {source}")]
    Read {
        /// The file.
        path: std::path::PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
}

/// The level files of the model in `ctree`, level 0 first; empty when it has no crossed-quad
/// atlas frames (no billboard level to end the ladder with).
pub fn level_files(ctree: &[u8]) -> Result<Vec<Vec<u8>>, LevelError> {
    let tree = DecodedTree::decode(ctree)?;
    let Some(billboard) = billboard_glb(&tree, ctree)? else {
        return Ok(Vec::new());
    };
    let mut out = Vec::with_capacity(LEVEL_COUNT);
    for (k, &rate) in LEVEL_RATES.iter().enumerate() {
        let bark = BarkDetail {
            sides: LEVEL_BARK_SIDES[k],
            min_radius: LEVEL_BARK_MIN_RADII[k],
        };
        out.push(export_glb_meshopt_with(&tree.to_model(rate), bark)?);
    }
    out.push(billboard);
    Ok(out)
}

/// The billboard level: the crossed-quad frames' top-resolution images on two vertical quads
/// through the tree's root, each facing its frame's view direction.
fn billboard_glb(tree: &DecodedTree, ctree: &[u8]) -> Result<Option<Vec<u8>>, LevelError> {
    let Some(entry) = tree.directory.section(SectionKind::BillboardAtlases).copied() else {
        return Ok(None);
    };
    if entry.length == 0 {
        return Ok(None);
    }
    let section = section_bytes(ctree, &entry)?;
    let table = AtlasTable::decode(section, entry.length)?;
    let Some(layout) = table.layouts.iter().find(|l| l.kind == AtlasLayoutKind::CrossedQuads) else {
        return Ok(None);
    };
    let side = 2.0 * table.radius;
    let mut bin: Vec<u8> = Vec::new();
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    let mut images = Vec::new();
    let mut primitives = Vec::new();
    let mut materials = Vec::new();
    let mut push_view = |bin: &mut Vec<u8>, bytes: &[u8], target: Option<u32>| {
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let mut v = json!({ "buffer": 0, "byteOffset": bin.len(), "byteLength": bytes.len() });
        if let Some(t) = target {
            v["target"] = json!(t);
        }
        bin.extend_from_slice(bytes);
        views.push(v);
        views.len() - 1
    };
    for local in 0..layout.frame_count() {
        let frame = layout.first_frame + local;
        let (Some(png), Some(dir), Some(f)) = (
            table.image_bytes(section, frame, 0)?,
            layout.direction(local),
            table.frames.get(frame as usize),
        ) else {
            continue;
        };
        // The image's horizontal axis, seen from the view direction: up × dir points left, so
        // its negation is the image's +u.
        let right = -Vec3::Y.cross(dir).normalize_or_zero();
        let (u0, v0) = (-f.root_u * side, -f.root_v * side);
        let corners = [
            (u0, v0, 0.0, 1.0),
            (u0 + side, v0, 1.0, 1.0),
            (u0 + side, v0 + side, 1.0, 0.0),
            (u0, v0 + side, 0.0, 0.0),
        ];
        let mut pos = Vec::new();
        let mut uv = Vec::new();
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for (u, v, s, t) in corners {
            let p = right * u + Vec3::Y * v;
            lo = lo.min(p);
            hi = hi.max(p);
            pos.extend(p.to_array().iter().flat_map(|c| c.to_le_bytes()));
            uv.extend([s, t].iter().flat_map(|c: &f32| c.to_le_bytes()));
        }
        let idx: Vec<u8> = [0u16, 1, 2, 0, 2, 3].iter().flat_map(|i| i.to_le_bytes()).collect();
        let pv = push_view(&mut bin, &pos, Some(34_962));
        let tv = push_view(&mut bin, &uv, Some(34_962));
        let iv = push_view(&mut bin, &idx, Some(34_963));
        let img = push_view(&mut bin, png, None);
        let a = accessors.len();
        accessors.push(
            json!({ "bufferView": pv, "componentType": 5126, "count": 4, "type": "VEC3",
            "min": lo.to_array(), "max": hi.to_array() }),
        );
        accessors.push(json!({ "bufferView": tv, "componentType": 5126, "count": 4, "type": "VEC2" }));
        accessors.push(json!({ "bufferView": iv, "componentType": 5123, "count": 6, "type": "SCALAR" }));
        images.push(json!({ "bufferView": img, "mimeType": "image/png" }));
        materials.push(json!({
            "name": format!("billboard_{local}"),
            "alphaMode": "MASK",
            "alphaCutoff": 0.5,
            "doubleSided": true,
            "pbrMetallicRoughness": { "baseColorTexture": { "index": images.len() - 1 },
                "metallicFactor": 0.0, "roughnessFactor": 1.0 },
            "extensions": { "KHR_materials_unlit": {} },
        }));
        primitives.push(json!({
            "attributes": { "POSITION": a, "TEXCOORD_0": a + 1 },
            "indices": a + 2,
            "material": materials.len() - 1,
            "mode": 4,
        }));
    }
    if primitives.is_empty() {
        return Ok(None);
    }
    let textures: Vec<_> = (0..images.len()).map(|k| json!({ "source": k })).collect();
    let doc = json!({
        "asset": { "version": "2.0", "generator": "canopy-server discrete_files" },
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{ "nodes": [0] }],
        "nodes": [{ "name": format!("{}-billboard", tree.directory.name), "mesh": 0 }],
        "meshes": [{ "name": tree.directory.name, "primitives": primitives }],
        "materials": materials,
        "textures": textures,
        "images": images,
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{ "byteLength": bin.len() }],
    });
    Ok(Some(write_glb(
        &serde_json::to_vec(&doc).map_err(ExportError::from)?,
        &bin,
    )?))
}

/// The first 16 hex digits of a model file's SHA-256: what its level files' names carry.
fn source_hash(ctree: &Asset) -> &str {
    ctree.sha256.get(..16).unwrap_or(&ctree.sha256)
}

/// Writes the level files of the model file `ctree` (unsynced: the caller syncs the folder).
/// Returns how many were written (0 for a model without an atlas, or a name too long to carry
/// the level and hash).
pub fn store_level_files(assets: &AssetStore, ctree: &Asset) -> Result<usize, LevelError> {
    let bytes = match &ctree.data {
        Some(b) => b.to_vec(),
        None => std::fs::read(&ctree.path).map_err(|source| LevelError::Read {
            path: ctree.path.clone(),
            source,
        })?,
    };
    let source = source_hash(ctree);
    if level_name(ctree.name(), 0, source).len() > MAX_NAME_LEN {
        return Ok(0);
    }
    let files = level_files(&bytes)?;
    for (k, bytes) in files.iter().enumerate() {
        assets.put_unsynced("trees", &level_name(ctree.name(), k as u8, source), "glb", bytes)?;
    }
    Ok(files.len())
}

/// Longest asset name the store takes.
const MAX_NAME_LEN: usize = 64;

/// Level files in `trees/`, by (model, source hash): one per level found.
type LevelIndex = HashMap<(String, String), [Option<Arc<Asset>>; LEVEL_COUNT]>;

fn level_index(assets: &AssetStore) -> LevelIndex {
    let mut out = LevelIndex::new();
    for a in assets.list("trees/") {
        if a.ext() != "glb" || a.rel.matches('/').count() != 1 {
            continue;
        }
        let Some((model, k, source)) = parse_level_name(a.name()) else {
            continue;
        };
        out.entry((model.to_string(), source.to_string())).or_default()[usize::from(k)] = Some(a.clone());
    }
    out
}

/// The manifest entries of the model file `ctree`'s level files, level 0 first: all of them,
/// or none.
fn levels_of(index: &LevelIndex, ctree: &Asset) -> Vec<ManifestFile> {
    let Some(levels) = index.get(&(ctree.name().to_string(), source_hash(ctree).to_string())) else {
        return Vec::new();
    };
    let all: Option<Vec<ManifestFile>> = levels
        .iter()
        .map(|a| {
            a.as_ref().map(|a| ManifestFile {
                url: a.url(),
                sha256: a.sha256.clone(),
                size: a.len,
            })
        })
        .collect();
    all.unwrap_or_default()
}

/// The manifest entries of each model file's level files (see [`levels_of`]), by model name.
pub fn manifest_levels<H: std::hash::BuildHasher>(
    assets: &AssetStore,
    models: &HashMap<String, Arc<Asset>, H>,
) -> HashMap<String, Vec<ManifestFile>> {
    let index = level_index(assets);
    models.iter().map(|(n, a)| (n.clone(), levels_of(&index, a))).collect()
}

/// What [`ensure_level_files`] did.
#[derive(Debug, Default)]
pub struct EnsureReport {
    /// Models that got level files now.
    pub written: usize,
    /// Models whose level files could not be made (a corrupt model file, a full disk), with why:
    /// the rest still get theirs, and these are named in no manifest.
    pub failed: Vec<(String, LevelError)>,
}

/// Writes the level files of every model that lacks them (a data folder baked before they
/// existed), in parallel. `progress(done, total)`.
pub fn ensure_level_files(
    assets: &AssetStore,
    progress: &(dyn Fn(u64, u64) + Sync),
) -> Result<EnsureReport, LevelError> {
    let models = assets.models();
    let index = level_index(assets);
    let todo: Vec<&Arc<Asset>> = models.values().filter(|a| levels_of(&index, a).is_empty()).collect();
    let total = todo.len() as u64;
    let done = std::sync::atomic::AtomicU64::new(0);
    let results: Vec<(String, Result<usize, LevelError>)> = todo
        .par_iter()
        .map(|a| {
            let r = store_level_files(assets, a);
            progress(done.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1, total);
            (a.name().to_string(), r)
        })
        .collect();
    if !todo.is_empty() {
        assets.sync_folder("trees")?;
    }
    let mut report = EnsureReport::default();
    for (name, r) in results {
        match r {
            Ok(0) => {}
            Ok(_) => report.written += 1,
            Err(e) => report.failed.push((name, e)),
        }
    }
    report.failed.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn billboard_level_is_the_last() {
        assert_eq!(usize::from(canopy_shared::discrete::BILLBOARD_LEVEL), LEVEL_COUNT - 1);
    }
}
