//! glTF 2.0 import (`.glb` and `.gltf`) into a [`TreeModel`].
//!
//! Real tree assets carry no branch skeleton, so the importer splits geometry into bark and
//! leaves and turns leaf geometry into [`Leaf`] records (see `docs/import.md`):
//!
//! - **Leaf detection, per primitive**, first rule that applies wins:
//!   1. the material name contains a leaf word (`leaf`, `leaves`, `foliage`, `needle`,
//!      `canopy`, `crown`, `frond`, `blossom`, `petal`) → leaf;
//!   2. the material name contains a bark word (`bark`, `trunk`, `wood`, `stem`, `branch`,
//!      `twig`) → bark;
//!   3. the material's `alphaMode` is `MASK` or `BLEND` → leaf;
//!   4. the mesh or node name contains a leaf word → leaf, a bark word → bark;
//!   5. shape: at least [`SHAPE_MIN_QUADS`] connected components and at least 80 % of the
//!      triangles in small (under 1/8 of the primitive's diagonal) quads → leaf;
//!   6. otherwise bark.
//! - **Leaf records**: a leaf primitive is split into connected components, joining
//!   triangles that share a vertex index or a vertex position (welding bit-equal positions).
//!   A component of two triangles over four distinct positions, folded by at most ~75 degrees
//!   (real leaf cards are folded), is one leaf quad: centre of its bounding rectangle, normal
//!   from the winding, axis along the uv `v` direction when uvs exist (else the longest side),
//!   width and length its extents. Other
//!   components are first split back by shared vertex index only, and a quad in there that
//!   shares at most one edge with the rest stays a leaf (leaves that merely touch); everything
//!   else (low-poly blobs like Kenney's) becomes **one leaf per triangle**:
//!   centre at the centroid, the face normal, axis along the longest edge, length = that edge,
//!   width = the triangle's height over it. That rectangle has twice the triangle's area; it is
//!   an approximation for low-poly leaf blobs, which have no individual leaves.
//! - **Bark**: every other triangle goes to [`TreeModel::bark_mesh`] in world space, with unit
//!   normals (missing normals are computed, non-unit ones renormalised).
//! - **Transforms**: nodes are walked from the chosen scene's nodes (default scene, else the
//!   first scene, else every root node); each node is visited once even if a scene lists a node
//!   that is not a root (Kenney files do), and its world transform is the product along its
//!   parent chain (matrix or TRS).
//! - **Placement**: the model is translated so that the centre of the bark's xz bounds at the
//!   bark's lowest y (or of all geometry, without bark) is the origin. glTF is Y up, metres.
//!
//! Nothing here panics on malformed input: every index, offset and length read from the file is
//! checked, and errors are typed ([`ImportError`]).
//!
//! Layout: this file holds the public entry points, the error and report types, and the pass
//! that assembles the model (`Importer::run`); the steps live in submodules:
//!
//! - `container`: GLB/JSON container, buffers (BIN chunk, data URIs, external files), the asset
//!   check;
//! - `accessors`: bounds-checked accessor reads (strides, normalised integers, sparse values);
//! - `scene`: the node walk and world transforms;
//! - `primitives`: one primitive read into world space (`Placed`), strips and fans, bark;
//! - `classify`: leaf or bark, per primitive (names, alpha mode, the shape rule);
//! - `topology`: welding, connected components, two-triangle quads;
//! - `leaves`: fitting leaf records to quads and triangles.
//!
//! Conventions: glTF is Y up, metres; positions are in world space (node transforms applied)
//! from `Placed` on.

mod accessors;
mod classify;
mod container;
mod leaves;
mod primitives;
mod scene;
mod topology;

use std::borrow::Cow;
use std::path::{Path, PathBuf};

use canopy_shared::model::{Leaf, LeafMaterial, Materials, ModelSource, TreeModel, TriangleMesh};
use glam::Vec3;
use gltf::json;

use container::{load_buffers, percent_decode, split_container};
use leaves::leaves_from_primitive;
use primitives::append_bark;

pub use accessors::MAX_UNBACKED_ELEMENTS;
pub use classify::{BARK_WORDS, LEAF_WORDS, SHAPE_MIN_QUADS};
pub use container::base64_decode;
pub use topology::QUAD_MIN_FOLD_COS;

/// Why an import failed.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// The bytes are neither a GLB container nor glTF JSON.
    #[error("not glTF: {0}")]
    NotGltf(String),
    /// The GLB container ends before its header, a chunk, or its declared length.
    #[error("truncated GLB: {0}")]
    TruncatedGlb(String),
    /// The GLB container is structurally invalid (bad version, chunk order, lengths).
    #[error("malformed GLB: {0}")]
    MalformedGlb(String),
    /// The JSON part does not parse as a glTF 2.0 document.
    #[error("invalid glTF JSON: {0}")]
    Json(String),
    /// The asset requires something this importer cannot read (glTF 1.0, Draco, meshopt).
    #[error("unsupported glTF: {0}")]
    Unsupported(String),
    /// A JSON index points at an object that does not exist.
    #[error("{from} refers to {kind} {index}, which does not exist")]
    InvalidReference {
        /// Kind of the missing object (`"accessor"`, `"bufferView"`, ...).
        kind: &'static str,
        /// The dangling index.
        index: usize,
        /// Where the reference was found.
        from: String,
    },
    /// A buffer's bytes are unavailable (missing BIN chunk, bad data URI, missing file).
    #[error("buffer {index}: {reason}")]
    Buffer {
        /// Buffer index.
        index: usize,
        /// What went wrong.
        reason: String,
    },
    /// An accessor or buffer view reaches outside its buffer, or is otherwise unreadable.
    #[error("accessor {accessor} out of bounds: {reason}")]
    AccessorOutOfBounds {
        /// Accessor index.
        accessor: usize,
        /// What went wrong.
        reason: String,
    },
    /// An accessor has a type or component type that does not fit its use.
    #[error("accessor {accessor} has the wrong type: {reason}")]
    BadAccessor {
        /// Accessor index.
        accessor: usize,
        /// What went wrong.
        reason: String,
    },
    /// A vertex index is not below the primitive's vertex count.
    #[error("mesh {mesh} primitive {primitive}: index {index} out of range for {vertex_count} vertices")]
    IndexOutOfRange {
        /// Mesh index.
        mesh: usize,
        /// Primitive index within the mesh.
        primitive: usize,
        /// The offending vertex index.
        index: u32,
        /// Number of vertices of the primitive.
        vertex_count: usize,
    },
    /// A vertex position is NaN or infinite (in the file, or after the node transforms).
    #[error("mesh {mesh} primitive {primitive}: non-finite vertex position")]
    NonFinitePosition {
        /// Mesh index.
        mesh: usize,
        /// Primitive index within the mesh.
        primitive: usize,
    },
    /// The file holds no triangles at all in the imported scene.
    #[error("no triangle geometry in the scene")]
    NoGeometry,
}

/// Counters describing what an import found.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct ImportStats {
    /// Primitives imported as bark.
    pub bark_primitives: usize,
    /// Primitives imported as leaves.
    pub leaf_primitives: usize,
    /// Primitives skipped (points, lines, no POSITION).
    pub skipped_primitives: usize,
    /// Leaves made from quads (two triangles, four corners).
    pub leaf_quads: usize,
    /// Leaves made from single triangles (the per-triangle approximation).
    pub leaf_triangles: usize,
    /// Degenerate leaf triangles dropped.
    pub degenerate_leaf_triangles: usize,
    /// Bark normals that were renormalised because they were not unit length.
    pub renormalized_normals: usize,
    /// Bark normals computed because they were missing, zero or non-finite.
    pub computed_normals: usize,
}

/// Result of [`import_gltf_report`]: the model plus diagnostics.
#[derive(Debug, Clone)]
pub struct ImportReport {
    /// The imported model.
    pub model: TreeModel,
    /// Non-fatal problems (skipped primitives, fallbacks taken), human readable.
    pub warnings: Vec<String>,
    /// Counters.
    pub stats: ImportStats,
}

/// Imports a `.glb` or `.gltf` file. External buffers are resolved relative to the file's
/// folder. The model is named after the file stem.
///
/// Contract: see the module docs. Returns a model with `source = ModelSource::Gltf`,
/// `iterations = 0`, no branches, every leaf with `branch = None` and `iteration = 0`, at least
/// one leaf material, and bark normals one per bark position. Never panics.
pub fn import_gltf(path: &Path) -> Result<TreeModel, ImportError> {
    let bytes = std::fs::read(path).map_err(|source| ImportError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let name = path
        .file_stem()
        .map_or_else(|| "tree".to_owned(), |s| s.to_string_lossy().into_owned());
    import_gltf_slice(&bytes, &name, path.parent())
}

/// Imports glTF from memory (GLB container or JSON). `base_dir` resolves external buffer URIs;
/// without it, a file that needs an external buffer fails with [`ImportError::Buffer`].
///
/// Contract as for [`import_gltf`].
pub fn import_gltf_slice(bytes: &[u8], name: &str, base_dir: Option<&Path>) -> Result<TreeModel, ImportError> {
    import_gltf_report(bytes, name, base_dir).map(|r| r.model)
}

/// Like [`import_gltf_slice`], also returning warnings and counters.
pub fn import_gltf_report(bytes: &[u8], name: &str, base_dir: Option<&Path>) -> Result<ImportReport, ImportError> {
    let (json_bytes, bin) = split_container(bytes)?;
    let root = json::Root::from_slice(json_bytes).map_err(|e| ImportError::Json(e.to_string()))?;
    let mut importer = Importer {
        root: &root,
        buffers: load_buffers(&root, bin, base_dir),
        warnings: Vec::new(),
        stats: ImportStats::default(),
    };
    importer.check_asset()?;
    let model = importer.run(name)?;
    Ok(ImportReport {
        model,
        warnings: importer.warnings,
        stats: importer.stats,
    })
}

/// One import in progress: the document, its buffers, and what was found so far.
struct Importer<'r, 'b> {
    root: &'r json::Root,
    buffers: Vec<Result<Cow<'b, [u8]>, String>>,
    warnings: Vec<String>,
    stats: ImportStats,
}

impl Importer<'_, '_> {
    fn material(&self, m: Option<usize>) -> Option<&json::Material> {
        m.and_then(|m| self.root.materials.get(m))
    }

    fn texture_name(&self, m: Option<usize>) -> Option<String> {
        let info = self.material(m)?.pbr_metallic_roughness.base_color_texture.as_ref()?;
        let texture = self.root.get(info.index)?;
        let image = self.root.get(texture.source)?;
        if let Some(uri) = image.uri.as_deref().filter(|u| !u.starts_with("data:")) {
            let decoded = percent_decode(uri);
            let file = decoded.rsplit(['/', '\\']).next().unwrap_or(&decoded);
            if !file.is_empty() {
                return Some(file.to_owned());
            }
        }
        image.name.clone().or_else(|| texture.name.clone())
    }

    fn base_color(&self, m: Option<usize>) -> Option<[f32; 4]> {
        let c = self.material(m)?.pbr_metallic_roughness.base_color_factor.0;
        c.iter().all(|v| v.is_finite()).then_some(c)
    }

    /// Reads every primitive of the scene, sorts it into bark or leaves, picks the materials and
    /// re-centres the model (see the module docs).
    fn run(&mut self, name: &str) -> Result<TreeModel, ImportError> {
        let root = self.root;
        let instances = self.instances();
        let mut bark = TriangleMesh::default();
        let mut bark_by_material: Vec<(Option<usize>, usize)> = Vec::new();
        let mut leaf_materials: Vec<Option<usize>> = Vec::new();
        let mut leaves: Vec<Leaf> = Vec::new();
        for (node, mesh, world) in instances {
            for p in 0..root.meshes[mesh].primitives.len() {
                let Some(placed) = self.read_primitive(mesh, p, world)? else {
                    continue;
                };
                if placed.triangles.is_empty() {
                    continue;
                }
                if self.is_leaf(mesh, node, &placed) {
                    self.stats.leaf_primitives += 1;
                    let slot = if let Some(k) = leaf_materials.iter().position(|&m| m == placed.material) {
                        k
                    } else if leaf_materials.len() < 256 {
                        leaf_materials.push(placed.material);
                        leaf_materials.len() - 1
                    } else {
                        self.warnings
                            .push("more than 256 leaf materials; extra ones merged".into());
                        255
                    };
                    let before = leaves.len();
                    leaves_from_primitive(&placed, slot as u8, &mut leaves, &mut self.stats);
                    if leaves.len() == before {
                        self.warnings
                            .push(format!("mesh {mesh} primitive {p}: leaf primitive yielded no leaves"));
                    }
                } else {
                    self.stats.bark_primitives += 1;
                    let tris = placed.triangles.len();
                    match bark_by_material.iter_mut().find(|(m, _)| *m == placed.material) {
                        Some(entry) => entry.1 += tris,
                        None => bark_by_material.push((placed.material, tris)),
                    }
                    append_bark(&placed, &mut bark, &mut self.stats)?;
                }
            }
        }
        if bark.indices.is_empty() && leaves.is_empty() {
            return Err(ImportError::NoGeometry);
        }

        // Materials.
        let defaults = Materials::default();
        let bark_material = bark_by_material.iter().max_by_key(|(_, n)| *n).and_then(|(m, _)| *m);
        let leaf = if leaf_materials.is_empty() {
            defaults.leaf.clone()
        } else {
            leaf_materials
                .iter()
                .map(|&m| LeafMaterial {
                    color: self.base_color(m).unwrap_or(defaults.leaf[0].color),
                    texture: self.texture_name(m),
                })
                .collect()
        };
        let materials = Materials {
            bark_color: self.base_color(bark_material).unwrap_or(defaults.bark_color),
            bark_texture: self.texture_name(bark_material),
            leaf,
        };

        // Re-centre: base of the bark (or of everything) at the origin.
        let mut model = TreeModel {
            name: name.to_owned(),
            branches: Vec::new(),
            leaves,
            bark_mesh: bark,
            materials,
            iterations: 0,
            source: ModelSource::Gltf,
        };
        let bounds = if model.bark_mesh.positions.is_empty() {
            model.bounds()
        } else {
            let lo = model
                .bark_mesh
                .positions
                .iter()
                .fold(Vec3::splat(f32::INFINITY), |a, &p| a.min(p));
            let hi = model
                .bark_mesh
                .positions
                .iter()
                .fold(Vec3::splat(f32::NEG_INFINITY), |a, &p| a.max(p));
            Some((lo, hi))
        };
        if let Some((lo, hi)) = bounds {
            let origin = Vec3::new(0.5 * (lo.x + hi.x), lo.y, 0.5 * (lo.z + hi.z));
            if origin.is_finite() {
                for p in &mut model.bark_mesh.positions {
                    *p -= origin;
                }
                for l in &mut model.leaves {
                    l.center -= origin;
                }
            }
        }
        if model
            .bounds()
            .is_some_and(|(lo, hi)| !(lo.is_finite() && hi.is_finite()))
        {
            return Err(ImportError::NonFinitePosition { mesh: 0, primitive: 0 });
        }
        Ok(model)
    }
}
