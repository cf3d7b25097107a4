//! A scene's terrain as its versions publish it: the `.cterrain` file, content-addressed in the
//! scene's assets folder (`scenes/<id>/terrain.<hash16>.cterrain`), the manifest's `terrain`
//! object naming it (what the store keeps, as JSON text), and the decoded heightfield that places
//! the instances.
//!
//! Conventions: with a terrain, an instance's stored y is its height above the ground; the pack
//! places it at `height_at(x, z) + y` ([`Ground::lift`]); without one the ground is y = 0 and the
//! stored y is the pack's. A terrain file is shared by every version from the one that set it to
//! the one that replaced it: retention never deletes it with one version; the sweep does, once no
//! kept version names it (`store::gc`).

use std::sync::Arc;

use canopy_shared::manifest::ManifestTerrain;
use canopy_shared::terrain::{Heightfield, TerrainError, decode_tables};

use crate::store::assets::{AssetError, AssetStore};

/// File extension of a terrain.
pub const TERRAIN_EXT: &str = "cterrain";

/// True for a terrain file's path (shared between versions).
pub fn is_terrain_file(rel: &str) -> bool {
    rel.rsplit('/')
        .next()
        .is_some_and(|f| f.starts_with("terrain.") && f.ends_with(&format!(".{TERRAIN_EXT}")))
}

/// A published terrain: its manifest object and its heights.
#[derive(Debug, Clone, PartialEq)]
pub struct Ground {
    /// The manifest's `terrain` object (URL, SHA-256, size, grid, tiles).
    pub terrain: ManifestTerrain,
    /// The decoded heights.
    pub field: Heightfield,
}

/// Why a stored terrain could not be read back.
#[derive(Debug, thiserror::Error)]
pub enum GroundError {
    /// The stored text is not a manifest terrain object.
    #[error("stored terrain: {0}")]
    Json(#[from] serde_json::Error),
    /// Its file is not in the assets.
    #[error("terrain file {0} is missing")]
    Missing(String),
    /// Reading the file failed.
    #[error("reading terrain file {0}: {1}")]
    Read(String, std::io::Error),
    /// The file does not decode, or disagrees with the stored object.
    #[error("terrain file {0}: {1}")]
    Terrain(String, TerrainError),
    /// Writing the file failed.
    #[error(transparent)]
    Asset(#[from] AssetError),
}

impl Ground {
    /// A position with its y taken as the height above the ground: on the terrain.
    pub fn lift(&self, p: [f32; 3]) -> [f32; 3] {
        [p[0], self.field.height_at(p[0], p[2]) + p[1], p[2]]
    }

    /// True when both are the same file.
    pub fn same(&self, other: &Self) -> bool {
        self.terrain.sha256 == other.terrain.sha256
    }

    /// The manifest object as the store keeps it (compact JSON).
    pub fn json(&self) -> Result<String, serde_json::Error> {
        serde_json::to_string(&self.terrain)
    }

    /// The asset path of its file (the URL after `/assets/`).
    pub fn rel(&self) -> &str {
        self.terrain.url.strip_prefix("/assets/").unwrap_or(&self.terrain.url)
    }

    /// Lowest and highest height, metres.
    pub fn height_range(&self) -> [f32; 2] {
        let t = &self.terrain.tiles;
        [
            t.iter().map(|t| t.min_height).fold(f32::INFINITY, f32::min),
            t.iter().map(|t| t.max_height).fold(f32::NEG_INFINITY, f32::max),
        ]
    }
}

/// Writes `field` as scene `scene`'s terrain file (a no-op when that file is there already) and
/// returns it as published.
pub fn store(assets: &AssetStore, scene: &str, field: Heightfield) -> Result<Ground, GroundError> {
    let bytes = field.encode();
    let asset = assets.put(&format!("scenes/{scene}"), "terrain", TERRAIN_EXT, &bytes)?;
    let (grid, tiles) = decode_tables(&bytes).map_err(|e| GroundError::Terrain(asset.rel.clone(), e))?;
    Ok(Ground {
        terrain: ManifestTerrain {
            url: asset.url(),
            sha256: asset.sha256.clone(),
            size: asset.len,
            grid,
            tiles,
        },
        field,
    })
}

/// The ground a stored terrain object names: one of `known` when it is the same file, else read
/// from the assets and decoded (every tile's CRC checked).
pub fn load(assets: &AssetStore, json: &str, known: &[&Arc<Ground>]) -> Result<Arc<Ground>, GroundError> {
    let terrain: ManifestTerrain = serde_json::from_str(json)?;
    if let Some(g) = known.iter().find(|g| g.terrain.sha256 == terrain.sha256) {
        return Ok(Arc::clone(g));
    }
    let rel = terrain.url.strip_prefix("/assets/").unwrap_or(&terrain.url).to_string();
    let asset = assets.get(&rel).ok_or_else(|| GroundError::Missing(rel.clone()))?;
    let bytes = match &asset.data {
        Some(b) => b.to_vec(),
        None => std::fs::read(&asset.path).map_err(|e| GroundError::Read(rel.clone(), e))?,
    };
    let field = Heightfield::decode(&bytes).map_err(|e| GroundError::Terrain(rel.clone(), e))?;
    if field.grid != terrain.grid || asset.sha256 != terrain.sha256 {
        return Err(GroundError::Terrain(
            rel,
            TerrainError::Invalid("the file is not the one the scene names".into()),
        ));
    }
    Ok(Arc::new(Ground { terrain, field }))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_stored_ground_loads_back_and_lifts_positions_onto_it() {
        let dir = std::env::temp_dir().join(format!("canopy-ground-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let assets = AssetStore::open(&dir).expect("assets");
        let field = Heightfield::new([0.0, 0.0], 10.0, [3, 2], &[0.0, 10.0, 20.0, 5.0, 15.0, 25.0]).expect("field");
        let g = store(&assets, "s", field.clone()).expect("store");
        assert!(is_terrain_file(g.rel()), "{}", g.rel());
        assert!(g.rel().starts_with("scenes/s/terrain.") && g.rel().ends_with(".cterrain"));
        assert_eq!(g.terrain.tiles.len(), 1);
        assert_eq!(g.height_range(), [0.0, 25.0]);
        let json = g.json().expect("json");
        let back = load(&assets, &json, &[]).expect("load");
        assert_eq!(*back, g);
        let held = Arc::new(g.clone());
        assert!(Arc::ptr_eq(&load(&assets, &json, &[&held]).expect("known"), &held));
        let p = g.lift([10.0, 2.0, 0.0]);
        assert!((p[1] - 12.0).abs() < 1e-3, "{p:?}");
        assert_eq!(g.lift([20.0, 0.0, 10.0])[1], field.height_at(20.0, 10.0));
        // A file that is gone, or a stored object that is not one, is an error.
        assert!(assets.remove(g.rel()).expect("remove"));
        assert!(matches!(load(&assets, &json, &[]), Err(GroundError::Missing(_))));
        assert!(matches!(load(&assets, "{}", &[]), Err(GroundError::Json(_))));
        assert!(!is_terrain_file("scenes/s/v1.0123456789abcdef.cpack"));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
