//! Leaf or bark, per primitive: the first rule that applies wins (material name, material
//! alpha mode, mesh or node name, then the shape rule: many small, disconnected, planar quads);
//! the full list is in the parent module's docs.

use glam::Vec3;
use gltf::json::material::AlphaMode;
use gltf::json::validation::Checked;

use super::Importer;
use super::primitives::Placed;
use super::topology::{components, quad_outline, weld};

/// Minimum number of leaf-like quads for the shape rule to call a primitive foliage.
pub const SHAPE_MIN_QUADS: usize = 16;

/// Words that mark leaf geometry in material, mesh or node names (lower case, substring match).
pub const LEAF_WORDS: &[&str] = &[
    "leaf", "leaves", "foliage", "needle", "canopy", "crown", "frond", "blossom", "petal",
];

/// Words that mark bark geometry in material, mesh or node names (lower case, substring match).
pub const BARK_WORDS: &[&str] = &["bark", "trunk", "wood", "stem", "branch", "twig"];

impl Importer<'_, '_> {
    /// Decides whether a primitive is foliage (the rules in the module docs).
    pub(super) fn is_leaf(&self, mesh: usize, node: Option<usize>, placed: &Placed) -> bool {
        let has = |name: Option<&str>, words: &[&str]| {
            name.is_some_and(|n| {
                let n = n.to_lowercase();
                words.iter().any(|w| n.contains(w))
            })
        };
        let mat = self.material(placed.material);
        let mat_name = mat.and_then(|m| m.name.as_deref());
        if has(mat_name, LEAF_WORDS) {
            return true;
        }
        if has(mat_name, BARK_WORDS) {
            return false;
        }
        if mat.is_some_and(|m| matches!(m.alpha_mode, Checked::Valid(AlphaMode::Mask | AlphaMode::Blend))) {
            return true;
        }
        let mesh_name = self.root.meshes[mesh].name.as_deref();
        let node_name = node.and_then(|n| self.root.nodes[n].name.as_deref());
        for name in [mesh_name, node_name] {
            if has(name, LEAF_WORDS) {
                return true;
            }
            if has(name, BARK_WORDS) {
                return false;
            }
        }
        looks_like_foliage(&placed.positions, &placed.triangles)
    }
}

/// The shape rule: many small, disconnected, planar quads.
fn looks_like_foliage(positions: &[Vec3], triangles: &[[u32; 3]]) -> bool {
    if triangles.len() < 2 * SHAPE_MIN_QUADS {
        return false;
    }
    let (lo, hi) = triangles.iter().flatten().fold(
        (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY)),
        |(lo, hi), &k| (lo.min(positions[k as usize]), hi.max(positions[k as usize])),
    );
    let diag = (hi - lo).length();
    if !(diag > 0.0 && diag.is_finite()) {
        return false;
    }
    let placed = Placed {
        positions: positions.to_vec(),
        normals: None,
        uvs: None,
        triangles: triangles.to_vec(),
        material: None,
    };
    let welded = weld(positions);
    let all: Vec<usize> = (0..triangles.len()).collect();
    let mut quad_tris = 0usize;
    let mut quads = 0usize;
    for comp in components(positions.len(), triangles, &all, Some(&welded)) {
        if let Some(outline) = quad_outline(&placed, &welded, &comp) {
            let c = outline.map(|k| positions[k as usize]);
            let size = c[0].distance(c[2]).max(c[1].distance(c[3]));
            if size < diag / 8.0 {
                quads += 1;
                quad_tris += 2;
            }
        }
    }
    quads >= SHAPE_MIN_QUADS && quad_tris * 5 >= triangles.len() * 4
}
