//! The scene manifest (JSON, `docs/scenes.md`): the one schema the server writes when it
//! publishes a scene version and the client reads before it streams one. A client fetches the
//! instance tiles it lists by range from the version's instance pack, only those near the camera.
//!
//! Conventions: ground-plane coordinates are `[x, z]` in metres (y up); URLs are paths under
//! `/assets/`; sizes and offsets are bytes.

use serde::{Deserialize, Serialize};

/// `format` of a scene manifest.
pub const MANIFEST_FORMAT: &str = "canopy-scene";
/// Manifest major version written and read.
pub const MANIFEST_VERSION: u32 = 1;

/// A model the scene uses.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ManifestModel {
    /// Model name (instances refer to it by index in `models`).
    pub name: String,
    /// URL path of its `.ctree` under `/assets/`.
    pub url: String,
    /// SHA-256 of the file (hex).
    pub sha256: String,
    /// File size in bytes.
    pub size: u64,
    /// Its discrete LOD files, level 0 (finest) first ([`crate::discrete`]); empty where the
    /// server has none (a scene published before they existed).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub levels: Vec<ManifestFile>,
}

/// A whole file a manifest names.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ManifestFile {
    /// URL path under `/assets/`.
    pub url: String,
    /// SHA-256 of the file (hex).
    pub sha256: String,
    /// File size in bytes.
    pub size: u64,
}

/// The version's instance pack.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ManifestPack {
    /// URL path of the `.cpack`.
    pub url: String,
    /// SHA-256 of the file (hex).
    pub sha256: String,
    /// File size.
    pub size: u64,
    /// Bytes of header, model table and tile table: `bytes=0-(tables_len-1)` fetches them.
    pub tables_len: u64,
}

/// One instance tile: the pack's tile record, as the manifest repeats it.
pub use crate::pack::Tile as ManifestTile;

/// The version's terrain: the `.cterrain` file and its tables, repeated so that a client fetches
/// only the tiles it needs, by range, with no table read first.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ManifestTerrain {
    /// URL path of the `.cterrain`.
    pub url: String,
    /// SHA-256 of the file (hex).
    pub sha256: String,
    /// File size.
    pub size: u64,
    /// The grid its samples lie on.
    pub grid: crate::terrain::TerrainGrid,
    /// Its tiles, row by row (the file's tile table).
    pub tiles: Vec<crate::terrain::TerrainTile>,
}

/// Scene bounds on the ground plane.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct ManifestBounds {
    /// min x, min z.
    pub min: [f64; 2],
    /// max x, max z.
    pub max: [f64; 2],
}

impl ManifestBounds {
    /// `[min x, min z, max x, max z]` in single precision, as the client's cameras use them.
    pub fn as_f32(&self) -> [f32; 4] {
        [
            self.min[0] as f32,
            self.min[1] as f32,
            self.max[0] as f32,
            self.max[1] as f32,
        ]
    }
}

/// A scene version's manifest.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Manifest {
    /// Must be [`MANIFEST_FORMAT`].
    pub format: String,
    /// Must be [`MANIFEST_VERSION`].
    pub format_version: u32,
    /// Scene id.
    pub scene: String,
    /// Scene name.
    pub name: String,
    /// Scene version.
    pub version: u64,
    /// Bounds.
    pub bounds: ManifestBounds,
    /// Instances in the version.
    pub instance_count: u64,
    /// Models, sorted by name; instance model indices point here.
    pub models: Vec<ManifestModel>,
    /// The instance pack.
    pub pack: ManifestPack,
    /// Tiles (the pack's tile table).
    pub tiles: Vec<ManifestTile>,
    /// The terrain the instances stand on; none: the ground is the plane y = 0.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub terrain: Option<ManifestTerrain>,
}

/// Why a manifest is refused.
#[derive(Debug, thiserror::Error)]
pub enum ManifestError {
    /// Not JSON of the expected shape.
    #[error("manifest is not valid JSON of the expected shape: {0}")]
    Json(#[from] serde_json::Error),
    /// Another format or version.
    #[error("manifest format {format:?} version {version} is not {MANIFEST_FORMAT:?} {MANIFEST_VERSION}")]
    Version {
        /// Format name found.
        format: String,
        /// Version found.
        version: u32,
    },
    /// Inconsistent contents.
    #[error("manifest is inconsistent: {0}")]
    Invalid(String),
}

impl Manifest {
    /// The manifest as the server publishes it (compact JSON).
    pub fn to_json(&self) -> Result<String, serde_json::Error> {
        serde_json::to_string(self)
    }

    /// Parses and checks a manifest: format, finite bounds, tiles inside the pack, asset paths
    /// under `/assets/`.
    pub fn parse(bytes: &[u8]) -> Result<Self, ManifestError> {
        let m: Self = serde_json::from_slice(bytes)?;
        if m.format != MANIFEST_FORMAT || m.format_version != MANIFEST_VERSION {
            return Err(ManifestError::Version {
                format: m.format,
                version: m.format_version,
            });
        }
        let bad = |s: String| Err(ManifestError::Invalid(s));
        let b = m.bounds;
        if !(b.min.iter().chain(&b.max).all(|v| v.is_finite()) && b.min[0] <= b.max[0] && b.min[1] <= b.max[1]) {
            return bad(format!("bounds {b:?}"));
        }
        for path in m
            .models
            .iter()
            .flat_map(|x| std::iter::once(&x.url).chain(x.levels.iter().map(|l| &l.url)))
            .chain([&m.pack.url])
            .chain(m.terrain.as_ref().map(|t| &t.url))
        {
            if !path.starts_with("/assets/") || path.contains("..") {
                return bad(format!("asset path {path:?} is not under /assets/"));
            }
        }
        for t in &m.tiles {
            let end = t.offset.checked_add(t.length);
            if t.offset < m.pack.tables_len || end.is_none_or(|e| e > m.pack.size) {
                return bad(format!("tile {}/{}/{} lies outside the pack", t.level, t.x, t.z));
            }
            if t.length != u64::from(t.count) * crate::pack::INSTANCE_RECORD_LEN as u64 {
                return bad(format!(
                    "tile {}/{}/{} length disagrees with its count",
                    t.level, t.x, t.z
                ));
            }
        }
        if let Some(t) = &m.terrain {
            t.grid
                .check()
                .map_err(|e| ManifestError::Invalid(format!("terrain: {e}")))?;
            let [nx, nz] = t.grid.tiles();
            if t.tiles.len() as u64 != u64::from(nx) * u64::from(nz) {
                return bad(format!(
                    "terrain has {} tiles for a {nx} × {nz} tile grid",
                    t.tiles.len()
                ));
            }
            for (k, tile) in t.tiles.iter().enumerate() {
                let (_, size) = t.grid.tile_samples(k as u32 % nx, k as u32 / nx);
                let end = tile.offset.checked_add(tile.length);
                if (u32::from(tile.x), u32::from(tile.z)) != (k as u32 % nx, k as u32 / nx)
                    || tile.offset < crate::terrain::tables_len(t.tiles.len())
                    || end.is_none_or(|e| e > t.size)
                    || tile.length != 2 * u64::from(size[0] * size[1])
                {
                    return bad(format!("terrain tile {}/{} lies outside the terrain", tile.x, tile.z));
                }
            }
        }
        Ok(m)
    }

    /// Indices of the tiles whose rectangle comes within `radius` of `(x, z)`.
    pub fn tiles_near(&self, x: f32, z: f32, radius: f32) -> Vec<usize> {
        self.tiles
            .iter()
            .enumerate()
            .filter(|(_, t)| {
                let dx = (t.bounds[0] - x).max(0.0).max(x - t.bounds[2]);
                let dz = (t.bounds[1] - z).max(0.0).max(z - t.bounds[3]);
                dx * dx + dz * dz <= radius * radius
            })
            .map(|(i, _)| i)
            .collect()
    }

    /// Bytes a client without LOD downloads: every model file whole, plus the whole pack.
    pub fn full_download_bytes(&self) -> u64 {
        self.models.iter().map(|m| m.size).sum::<u64>() + self.pack.size + self.terrain.as_ref().map_or(0, |t| t.size)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> serde_json::Value {
        serde_json::json!({
            "format": "canopy-scene", "format_version": 1, "scene": "s", "name": "S", "version": 2,
            "bounds": {"min": [-10.0, -10.0], "max": [10.0, 10.0]},
            "instance_count": 3,
            "models": [{"name": "a", "url": "/assets/trees/a.0.ctree", "sha256": "00", "size": 1000}],
            "pack": {"url": "/assets/scenes/s/v2.0.cpack", "sha256": "00", "size": 64 + 100 + 84, "tables_len": 164},
            "tiles": [{"level": 0, "x": 0, "z": 0, "count": 3, "offset": 164, "length": 84, "crc32": 0,
                       "bounds": [-10.0, -10.0, 10.0, 10.0]}]
        })
    }

    #[test]
    fn parses_and_selects_tiles() {
        let m = Manifest::parse(sample().to_string().as_bytes()).expect("valid");
        assert_eq!(m.tiles_near(0.0, 0.0, 1.0), vec![0]);
        assert_eq!(m.tiles_near(20.0, 0.0, 9.9), Vec::<usize>::new());
        assert_eq!(m.tiles_near(20.0, 0.0, 10.0), vec![0]);
        assert_eq!(m.full_download_bytes(), 1000 + 248);
    }

    #[test]
    fn a_terrain_is_checked_against_its_grid() {
        let h = crate::terrain::Heightfield::new([-10.0, -10.0], 0.5, [41, 41], &[3.0; 41 * 41]).expect("valid");
        let bytes = h.encode();
        let mut v = sample();
        v["terrain"] = serde_json::json!({
            "url": "/assets/terrain/t.cterrain", "sha256": "00", "size": bytes.len(),
            "grid": h.grid, "tiles": h.tiles(),
        });
        let m = Manifest::parse(v.to_string().as_bytes()).expect("valid");
        assert_eq!(m.terrain.as_ref().map(|t| t.tiles.len()), Some(1));
        assert_eq!(m.full_download_bytes(), 1000 + 248 + bytes.len() as u64);
        // Absent: a flat scene, and the field is not written.
        assert!(
            !Manifest::parse(sample().to_string().as_bytes())
                .expect("valid")
                .to_json()
                .expect("json")
                .contains("terrain")
        );
        let mut bad = v.clone();
        bad["terrain"]["url"] = "/etc/t".into();
        assert!(Manifest::parse(bad.to_string().as_bytes()).is_err());
        let mut bad = v.clone();
        bad["terrain"]["size"] = 10.into();
        assert!(
            Manifest::parse(bad.to_string().as_bytes()).is_err(),
            "tiles past the file"
        );
        let mut bad = v.clone();
        bad["terrain"]["grid"]["samples"] = serde_json::json!([1, 41]);
        assert!(
            Manifest::parse(bad.to_string().as_bytes()).is_err(),
            "a degenerate grid"
        );
        let mut bad = v.clone();
        bad["terrain"]["tiles"] = serde_json::json!([]);
        assert!(Manifest::parse(bad.to_string().as_bytes()).is_err(), "tiles missing");
        let mut bad = v;
        bad["terrain"]["tiles"][0]["length"] = 8.into();
        assert!(
            Manifest::parse(bad.to_string().as_bytes()).is_err(),
            "a tile of the wrong length"
        );
    }

    #[test]
    fn rejects_bad_manifests() {
        assert!(matches!(Manifest::parse(b"{"), Err(ManifestError::Json(_))));
        let mut v = sample();
        v["format_version"] = 2.into();
        assert!(matches!(
            Manifest::parse(v.to_string().as_bytes()),
            Err(ManifestError::Version { .. })
        ));
        let mut v = sample();
        v["models"][0]["url"] = "/etc/passwd".into();
        assert!(matches!(
            Manifest::parse(v.to_string().as_bytes()),
            Err(ManifestError::Invalid(_))
        ));
        // Level files are assets too, and a manifest without them still parses.
        let mut v = sample();
        v["models"][0]["levels"] = serde_json::json!([{"url": "/assets/../x.glb", "sha256": "00", "size": 1}]);
        assert!(matches!(
            Manifest::parse(v.to_string().as_bytes()),
            Err(ManifestError::Invalid(_))
        ));
        v["models"][0]["levels"][0]["url"] = "/assets/trees/a-lod0-0123456789abcdef.0.glb".into();
        let m = Manifest::parse(v.to_string().as_bytes()).expect("levels under /assets/");
        assert_eq!(m.models[0].levels.len(), 1);
        assert!(
            Manifest::parse(sample().to_string().as_bytes())
                .expect("no levels")
                .models[0]
                .levels
                .is_empty()
        );
        let mut v = sample();
        v["tiles"][0]["length"] = 1_000_000.into();
        assert!(Manifest::parse(v.to_string().as_bytes()).is_err());
        let mut v = sample();
        v["bounds"]["min"][0] = 50.0.into();
        assert!(Manifest::parse(v.to_string().as_bytes()).is_err());
    }
}
