//! Rasterizer input: triangle soups with per-triangle items and materials, instances, and
//! builders from a [`TreeModel`].

use glam::{Mat4, Vec3};

use super::texture::{Texture, TextureId};
use super::{BARK_ITEM, RasterError};
use crate::model::{Leaf, TreeModel, TriangleMesh};
use crate::tessellate::{branch_tubes, leaf_quads};

/// A material: base colour, optional texture (multiplied) and alpha test.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RasterMaterial {
    /// Linear RGBA base colour (alpha unused for shading).
    pub color: [f32; 4],
    /// Texture multiplied with `color`, if any.
    pub texture: Option<TextureId>,
    /// Fragments whose texture alpha is below this are discarded (only with a texture;
    /// 0 disables the test).
    pub alpha_cutoff: f32,
    /// Draw back faces too (leaves). Single-sided materials cull back faces.
    pub double_sided: bool,
    /// Screen-door coverage `[lo, hi)`: a fragment is kept only where the pixel's ordered-dither
    /// threshold ([`dither_threshold`]) lies in it. [`FULL_COVERAGE`] keeps every fragment;
    /// materials with adjacent ranges (`[0, w)`, `[w, 1)`) on the same surface cover each pixel
    /// exactly once, which is how a renderer without blending cross-fades two images.
    pub coverage: [f32; 2],
}

/// [`RasterMaterial::coverage`] that keeps every fragment.
pub const FULL_COVERAGE: [f32; 2] = [0.0, 1.0];

/// The 4 × 4 Bayer ordered-dither threshold of pixel `(x, y)`, in (0, 1): `(b + ½) / 16`.
pub fn dither_threshold(x: u32, y: u32) -> f32 {
    const BAYER: [u8; 16] = [0, 8, 2, 10, 12, 4, 14, 6, 3, 11, 1, 9, 15, 7, 13, 5];
    (f32::from(BAYER[((y % 4) * 4 + x % 4) as usize]) + 0.5) / 16.0
}

impl Default for RasterMaterial {
    fn default() -> Self {
        Self {
            color: [1.0; 4],
            texture: None,
            alpha_cutoff: 0.5,
            double_sided: true,
            coverage: FULL_COVERAGE,
        }
    }
}

/// A triangle soup with per-triangle item and material.
///
/// Invariants checked by [`RasterMesh::validate`]: `indices.len()` is a multiple of 3, every
/// index `< positions.len()`; `normals` and `uvs` are empty or one per position;
/// `item_of_triangle` has one entry per triangle; `material_of_triangle` is empty (all
/// material 0) or one per triangle.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RasterMesh {
    /// Vertex positions, mesh space.
    pub positions: Vec<Vec3>,
    /// Vertex normals (empty: the geometric normal of each triangle is used).
    pub normals: Vec<Vec3>,
    /// Vertex uvs (empty: all zero).
    pub uvs: Vec<[f32; 2]>,
    /// Three indices per triangle.
    pub indices: Vec<u32>,
    /// Item id of each triangle (see [`super::EMPTY_ITEM`], [`super::BARK_ITEM`]).
    pub item_of_triangle: Vec<u32>,
    /// Material index (into [`Scene::materials`]) of each triangle; empty = all 0.
    pub material_of_triangle: Vec<u16>,
}

impl RasterMesh {
    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }

    /// Checks the invariants above; `materials` is the number of scene materials.
    pub fn validate(&self, materials: usize) -> Result<(), RasterError> {
        let bad = |m: String| Err(RasterError::InvalidMesh(m));
        let n = self.positions.len();
        let t = self.triangle_count();
        if !self.indices.len().is_multiple_of(3) {
            return bad(format!("{} indices is not a multiple of 3", self.indices.len()));
        }
        if let Some(i) = self.indices.iter().find(|&&i| i as usize >= n) {
            return bad(format!("index {i} out of range for {n} positions"));
        }
        if !self.normals.is_empty() && self.normals.len() != n {
            return bad(format!("{} normals for {n} positions", self.normals.len()));
        }
        if !self.uvs.is_empty() && self.uvs.len() != n {
            return bad(format!("{} uvs for {n} positions", self.uvs.len()));
        }
        if self.item_of_triangle.len() != t {
            return bad(format!("{} items for {t} triangles", self.item_of_triangle.len()));
        }
        if !self.material_of_triangle.is_empty() && self.material_of_triangle.len() != t {
            return bad(format!(
                "{} materials for {t} triangles",
                self.material_of_triangle.len()
            ));
        }
        let max_mat = self.material_of_triangle.iter().copied().max().unwrap_or(0) as usize;
        if t > 0 && max_mat >= materials {
            return bad(format!("material {max_mat} missing ({materials} materials)"));
        }
        Ok(())
    }

    /// Appends `other`, offsetting its indices.
    pub fn append(&mut self, other: &RasterMesh) -> Result<(), RasterError> {
        let base = u32::try_from(self.positions.len())
            .map_err(|_| RasterError::InvalidMesh("more than 2^32 vertices".into()))?;
        // Keep per-vertex arrays aligned when one side lacks them.
        let pad = |dst_len: usize, src_len: usize, own: usize| dst_len == 0 && src_len > 0 && own > 0;
        if pad(self.normals.len(), other.normals.len(), self.positions.len()) {
            self.normals.resize(self.positions.len(), Vec3::ZERO);
        }
        if pad(self.uvs.len(), other.uvs.len(), self.positions.len()) {
            self.uvs.resize(self.positions.len(), [0.0; 2]);
        }
        if self.material_of_triangle.is_empty() && !other.material_of_triangle.is_empty() {
            self.material_of_triangle.resize(self.triangle_count(), 0);
        }
        let had_normals = !self.normals.is_empty();
        let had_uvs = !self.uvs.is_empty();
        let had_mats = !self.material_of_triangle.is_empty();
        self.positions.extend_from_slice(&other.positions);
        if had_normals {
            if other.normals.is_empty() {
                self.normals.resize(self.positions.len(), Vec3::ZERO);
            } else {
                self.normals.extend_from_slice(&other.normals);
            }
        }
        if had_uvs {
            if other.uvs.is_empty() {
                self.uvs.resize(self.positions.len(), [0.0; 2]);
            } else {
                self.uvs.extend_from_slice(&other.uvs);
            }
        }
        self.indices.extend(other.indices.iter().map(|&i| i + base));
        self.item_of_triangle.extend_from_slice(&other.item_of_triangle);
        if had_mats {
            if other.material_of_triangle.is_empty() {
                self.material_of_triangle.resize(self.item_of_triangle.len(), 0);
            } else {
                self.material_of_triangle.extend_from_slice(&other.material_of_triangle);
            }
        }
        Ok(())
    }

    /// Bark meshes (branch tubes, imported bark) merged into one raster mesh: item
    /// [`BARK_ITEM`], material `material`, zero uvs; a mesh without one normal per position gets
    /// zero normals (shaded with the geometric normal).
    pub fn from_bark(parts: &[&TriangleMesh], material: u16) -> RasterMesh {
        let mut mesh = RasterMesh::default();
        for m in parts {
            let base = mesh.positions.len() as u32;
            mesh.positions.extend_from_slice(&m.positions);
            if m.normals.len() == m.positions.len() {
                mesh.normals.extend_from_slice(&m.normals);
            } else {
                mesh.normals.resize(mesh.positions.len(), Vec3::ZERO);
            }
            mesh.indices.extend(m.indices.iter().map(|&i| i + base));
        }
        let t = mesh.triangle_count();
        mesh.item_of_triangle.resize(t, BARK_ITEM);
        mesh.material_of_triangle.resize(t, material);
        mesh.uvs.resize(mesh.positions.len(), [0.0; 2]);
        mesh
    }

    /// A mesh of a tree for rendering with [`tree_materials`]:
    ///
    /// - leaves as quads ([`leaf_quads`] uvs and winding): leaf `i` of `model.leaves` gets item
    ///   id `i` (also when a subset is drawn) and material `1 + leaf.material`;
    /// - bark: [`branch_tubes`] with `options.tube_sides` plus `model.bark_mesh`, item
    ///   [`BARK_ITEM`], material 0.
    ///
    /// Bark comes first in triangle order, then leaves in the order of `options.leaf_subset`
    /// (or model order). Subset indices out of range are skipped.
    pub fn from_tree(model: &TreeModel, options: &TreeMeshOptions<'_>) -> RasterMesh {
        let mut mesh = if options.bark {
            Self::from_bark(&[&branch_tubes(model, options.tube_sides), &model.bark_mesh], 0)
        } else {
            RasterMesh::default()
        };
        if options.leaves {
            let all: Vec<u32>;
            let ids: &[u32] = if let Some(s) = options.leaf_subset {
                s
            } else {
                all = (0..model.leaves.len() as u32).collect();
                &all
            };
            let mut chosen: Vec<Leaf> = Vec::with_capacity(ids.len());
            let mut items = Vec::with_capacity(ids.len());
            for &id in ids {
                let Some(l) = model.leaves.get(id as usize) else {
                    continue;
                };
                let s = options.leaf_scale
                    * options
                        .per_leaf_scale
                        .and_then(|v| v.get(id as usize).copied())
                        .unwrap_or(1.0);
                chosen.push(Leaf {
                    width: l.width * s,
                    length: l.length * s,
                    ..*l
                });
                items.push(id);
            }
            let (p, n, uv, idx) = leaf_quads(&chosen);
            let base = mesh.positions.len() as u32;
            mesh.positions.extend_from_slice(&p);
            mesh.normals.extend_from_slice(&n);
            mesh.uvs.extend_from_slice(&uv);
            mesh.indices.extend(idx.iter().map(|&i| i + base));
            for (leaf, &id) in chosen.iter().zip(&items) {
                let mat = 1 + u16::from(leaf.material);
                mesh.item_of_triangle.extend_from_slice(&[id, id]);
                mesh.material_of_triangle.extend_from_slice(&[mat, mat]);
            }
        }
        mesh
    }
}

/// What [`RasterMesh::from_tree`] builds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TreeMeshOptions<'a> {
    /// Include leaves.
    pub leaves: bool,
    /// Include bark (branch tubes and the bark mesh).
    pub bark: bool,
    /// Only these leaf indices (None = all leaves).
    pub leaf_subset: Option<&'a [u32]>,
    /// Uniform scale of every leaf about its centre.
    pub leaf_scale: f32,
    /// Extra per-leaf scale, indexed by leaf index (missing entries = 1).
    pub per_leaf_scale: Option<&'a [f32]>,
    /// Sides of the branch tubes.
    pub tube_sides: u32,
}

impl Default for TreeMeshOptions<'_> {
    fn default() -> Self {
        Self {
            leaves: true,
            bark: true,
            leaf_subset: None,
            leaf_scale: 1.0,
            per_leaf_scale: None,
            tube_sides: 6,
        }
    }
}

/// Materials for a mesh from [`RasterMesh::from_tree`]: index 0 = bark (single-sided, the
/// model's bark colour), `1 + k` = leaf material `k` (double-sided, alpha-tested with
/// `leaf_textures[k]` when given, else an opaque quad).
pub fn tree_materials(model: &TreeModel, leaf_textures: &[Option<TextureId>]) -> Vec<RasterMaterial> {
    let mut mats = vec![RasterMaterial {
        color: model.materials.bark_color,
        texture: None,
        alpha_cutoff: 0.0,
        double_sided: false,
        coverage: FULL_COVERAGE,
    }];
    for (k, m) in model.materials.leaf.iter().enumerate() {
        mats.push(RasterMaterial {
            color: m.color,
            texture: leaf_textures.get(k).copied().flatten(),
            alpha_cutoff: 0.5,
            double_sided: true,
            coverage: FULL_COVERAGE,
        });
    }
    mats
}

/// How an instance maps its mesh's item ids.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ItemMap {
    /// Use the mesh's item ids unchanged.
    #[default]
    Keep,
    /// Add this offset to every item id below [`BARK_ITEM`] (wrapping is the caller's concern).
    Offset(u32),
    /// Every triangle of the instance gets this item (e.g. the instance index).
    Constant(u32),
}

impl ItemMap {
    pub(crate) fn apply(self, item: u32) -> u32 {
        match self {
            ItemMap::Offset(o) if item < BARK_ITEM => item.wrapping_add(o),
            ItemMap::Keep | ItemMap::Offset(_) => item,
            ItemMap::Constant(c) => c,
        }
    }
}

/// One placed copy of a mesh.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Instance<'a> {
    /// The mesh.
    pub mesh: &'a RasterMesh,
    /// Mesh → world transform (normals use its inverse transpose).
    pub transform: Mat4,
    /// Item id mapping.
    pub items: ItemMap,
}

/// Everything drawn in one render: instances, materials and textures.
#[derive(Debug, Clone, PartialEq)]
pub struct Scene<'a> {
    /// Instances, drawn in this order (it breaks exact depth-and-item ties).
    pub instances: Vec<Instance<'a>>,
    /// Materials, indexed by [`RasterMesh::material_of_triangle`].
    pub materials: &'a [RasterMaterial],
    /// Textures, indexed by [`RasterMaterial::texture`].
    pub textures: &'a [Texture],
}

/// Textured quads in world space (billboards, billboard-cloud planes), alpha-tested and
/// two-sided: what an unlit stand-in pass draws. Each texture is held once however many quads
/// use it, and each (texture, coverage) pair is one material.
#[derive(Debug, Clone, Default)]
pub struct QuadBatch {
    /// The quads, two triangles each.
    pub mesh: RasterMesh,
    /// One per (texture, coverage) pair in use.
    pub materials: Vec<RasterMaterial>,
    /// Each texture once ([`QuadBatch::add_texture`]).
    pub textures: Vec<Texture>,
    /// Material of each (texture, coverage bits) pair.
    material_of: std::collections::HashMap<(TextureId, [u32; 2]), u16>,
}

impl QuadBatch {
    /// Holds `texture` for quads to use; returns its id.
    pub fn add_texture(&mut self, texture: Texture) -> TextureId {
        self.textures.push(texture);
        (self.textures.len() - 1) as TextureId
    }

    /// Adds the quad `corners[0..4]` (in order around it) textured with `texture` (an id from
    /// [`QuadBatch::add_texture`]) at `uvs`, alpha-tested at 0.5 and drawn from both sides, with
    /// the face normal `normal` and the screen-door `coverage` ([`RasterMaterial::coverage`];
    /// [`FULL_COVERAGE`] for all). Returns `false` (and adds nothing) once the batch holds as
    /// many materials as a triangle can name.
    pub fn push(
        &mut self,
        texture: TextureId,
        corners: [Vec3; 4],
        uvs: [[f32; 2]; 4],
        normal: Vec3,
        coverage: [f32; 2],
    ) -> bool {
        let key = (texture, coverage.map(f32::to_bits));
        let mat = if let Some(&m) = self.material_of.get(&key) {
            m
        } else {
            let Ok(m) = u16::try_from(self.materials.len()) else {
                return false;
            };
            self.materials.push(RasterMaterial {
                color: [1.0; 4],
                texture: Some(texture),
                alpha_cutoff: 0.5,
                double_sided: true,
                coverage,
            });
            self.material_of.insert(key, m);
            m
        };
        let m = &mut self.mesh;
        let b = m.positions.len() as u32;
        m.positions.extend(corners);
        m.uvs.extend(uvs);
        m.normals.extend([normal; 4]);
        m.indices.extend([b, b + 1, b + 2, b, b + 2, b + 3]);
        m.item_of_triangle.extend([0, 0]);
        m.material_of_triangle.extend([mat, mat]);
        true
    }

    /// The batch as a scene (identity transform).
    pub fn scene(&self) -> Scene<'_> {
        Scene::single(&self.mesh, &self.materials, &self.textures)
    }
}

impl<'a> Scene<'a> {
    /// One mesh at the identity transform.
    pub fn single(mesh: &'a RasterMesh, materials: &'a [RasterMaterial], textures: &'a [Texture]) -> Self {
        Self {
            instances: vec![Instance {
                mesh,
                transform: Mat4::IDENTITY,
                items: ItemMap::Keep,
            }],
            materials,
            textures,
        }
    }

    /// Checks every mesh, material and texture reference.
    pub fn validate(&self) -> Result<(), RasterError> {
        for (k, m) in self.materials.iter().enumerate() {
            if let Some(t) = m.texture
                && t as usize >= self.textures.len()
            {
                return Err(RasterError::MissingTexture {
                    material: k,
                    texture: t,
                });
            }
        }
        for inst in &self.instances {
            if !inst.transform.is_finite() {
                return Err(RasterError::InvalidMesh("non-finite instance transform".into()));
            }
            inst.mesh.validate(self.materials.len())?;
        }
        Ok(())
    }

    /// Total triangles over all instances.
    pub fn triangle_count(&self) -> usize {
        self.instances.iter().map(|i| i.mesh.triangle_count()).sum()
    }
}
