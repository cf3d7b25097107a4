//! The in-memory tree model: a branch skeleton, leaves and materials.
//!
//! Conventions: Y up, right-handed, metres. The tree's root (base of the trunk) sits at the
//! origin. Every branch and leaf records the L-system iteration that created it, so that the
//! model at `k` iterations is the subset with `iteration <= k` (iteration-level LOD, seed 000).

use glam::Vec3;

/// One point of a branch's centre line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SkeletonPoint {
    /// Position in metres, tree space.
    pub position: Vec3,
    /// Branch radius at this point, metres.
    pub radius: f32,
}

/// A branch: a polyline from its base (first point) to its tip (last point).
#[derive(Debug, Clone, PartialEq)]
pub struct Branch {
    /// Centre line, base first. At least two points for a drawable branch.
    pub points: Vec<SkeletonPoint>,
    /// Index of the parent branch in [`TreeModel::branches`]; `None` for the trunk.
    pub parent: Option<u32>,
    /// Branch order: trunk = 1, +1 per branching.
    pub level: u8,
    /// L-system iteration that created this branch (0 = axiom).
    pub iteration: u8,
}

impl Branch {
    /// Length of the centre line in metres.
    pub fn length(&self) -> f32 {
        self.points
            .windows(2)
            .map(|w| w[0].position.distance(w[1].position))
            .sum()
    }

    /// Unit direction from base to tip (`Vec3::Y` for a degenerate branch).
    pub fn growth_direction(&self) -> Vec3 {
        match (self.points.first(), self.points.last()) {
            (Some(a), Some(b)) => (b.position - a.position).try_normalize().unwrap_or(Vec3::Y),
            _ => Vec3::Y,
        }
    }
}

/// A leaf: a quad centred at `center`, spanning `width` along `side` and `length` along `axis`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Leaf {
    /// Centre of the leaf quad, metres.
    pub center: Vec3,
    /// Unit normal of the leaf blade.
    pub normal: Vec3,
    /// Unit vector along the leaf's length (petiole to tip), perpendicular to `normal`.
    pub axis: Vec3,
    /// Blade width, metres.
    pub width: f32,
    /// Blade length, metres.
    pub length: f32,
    /// Branch that carries this leaf (index into [`TreeModel::branches`]), if known.
    pub branch: Option<u32>,
    /// L-system iteration that created this leaf.
    pub iteration: u8,
    /// Index into [`Materials::leaf`].
    pub material: u8,
}

impl Leaf {
    /// The unit vector across the blade: `axis × normal`.
    pub fn side(&self) -> Vec3 {
        self.axis.cross(self.normal)
    }

    /// Corners of the quad, counter-clockwise seen from the normal side.
    pub fn corners(&self) -> [Vec3; 4] {
        let s = self.side() * (0.5 * self.width);
        let a = self.axis * (0.5 * self.length);
        let c = self.center;
        [c - s - a, c + s - a, c + s + a, c - s + a]
    }

    /// Blade area in square metres.
    pub fn area(&self) -> f32 {
        self.width * self.length
    }
}

/// A leaf material: colour and optional texture (a path relative to `assets/textures/`).
#[derive(Debug, Clone, PartialEq)]
pub struct LeafMaterial {
    /// Linear RGBA base colour.
    pub color: [f32; 4],
    /// Texture file name, if any.
    pub texture: Option<String>,
}

/// Bark and leaf materials of one tree.
#[derive(Debug, Clone, PartialEq)]
pub struct Materials {
    /// Linear RGBA bark colour.
    pub bark_color: [f32; 4],
    /// Bark texture file name, if any.
    pub bark_texture: Option<String>,
    /// Leaf materials, indexed by [`Leaf::material`]. At least one.
    pub leaf: Vec<LeafMaterial>,
}

impl Default for Materials {
    fn default() -> Self {
        Self {
            bark_color: [0.35, 0.25, 0.17, 1.0],
            bark_texture: None,
            leaf: vec![LeafMaterial {
                color: [0.22, 0.45, 0.12, 1.0],
                texture: None,
            }],
        }
    }
}

/// A triangle mesh for bark geometry that has no skeleton (imported models).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriangleMesh {
    /// Vertex positions, metres.
    pub positions: Vec<Vec3>,
    /// Unit vertex normals, one per position (may be empty).
    pub normals: Vec<Vec3>,
    /// Triangle list, three indices per triangle.
    pub indices: Vec<u32>,
}

impl TriangleMesh {
    /// Number of triangles.
    pub fn triangle_count(&self) -> usize {
        self.indices.len() / 3
    }
}

/// Where a model came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelSource {
    /// Grown by the L-system engine from a species spec.
    LSystem,
    /// Imported from a glTF file (no real skeleton; leaves grouped by geometry).
    Gltf,
}

/// A complete tree model.
#[derive(Debug, Clone, PartialEq)]
pub struct TreeModel {
    /// Model name (file stem or species name).
    pub name: String,
    /// Branches, ordered so that a parent always precedes its children and
    /// `iteration` never decreases (so any iteration count is a prefix).
    pub branches: Vec<Branch>,
    /// Leaves, ordered by non-decreasing `iteration`.
    pub leaves: Vec<Leaf>,
    /// Bark geometry without skeleton (imported models); empty for L-system trees.
    pub bark_mesh: TriangleMesh,
    /// Materials.
    pub materials: Materials,
    /// Number of L-system iterations that grew the model (0 for imports).
    pub iterations: u8,
    /// Provenance.
    pub source: ModelSource,
}

impl TreeModel {
    /// Axis-aligned bounds of every skeleton point (inflated by radius), leaf corner and bark
    /// vertex. Returns `None` for an empty model.
    pub fn bounds(&self) -> Option<(Vec3, Vec3)> {
        let mut lo = Vec3::splat(f32::INFINITY);
        let mut hi = Vec3::splat(f32::NEG_INFINITY);
        let mut any = false;
        for b in &self.branches {
            for p in &b.points {
                lo = lo.min(p.position - Vec3::splat(p.radius));
                hi = hi.max(p.position + Vec3::splat(p.radius));
                any = true;
            }
        }
        for l in &self.leaves {
            for c in l.corners() {
                lo = lo.min(c);
                hi = hi.max(c);
                any = true;
            }
        }
        for &p in &self.bark_mesh.positions {
            lo = lo.min(p);
            hi = hi.max(p);
            any = true;
        }
        any.then_some((lo, hi))
    }

    /// The model as it stood after `k` iterations: the prefix of branches and leaves with
    /// `iteration <= k` (seed 000's iteration-level LOD).
    #[must_use]
    pub fn at_iteration(&self, k: u8) -> TreeModel {
        let nb = self.branches.partition_point(|b| b.iteration <= k);
        let nl = self.leaves.partition_point(|l| l.iteration <= k);
        TreeModel {
            name: self.name.clone(),
            branches: self.branches[..nb].to_vec(),
            leaves: self.leaves[..nl].to_vec(),
            bark_mesh: self.bark_mesh.clone(),
            materials: self.materials.clone(),
            iterations: k.min(self.iterations),
            source: self.source,
        }
    }

    /// Checks the ordering invariants documented on the fields.
    pub fn check_invariants(&self) -> Result<(), String> {
        for (i, b) in self.branches.iter().enumerate() {
            if let Some(p) = b.parent
                && p as usize >= i
            {
                return Err(format!("branch {i} has parent {p} that does not precede it"));
            }
            if i > 0 && self.branches[i - 1].iteration > b.iteration {
                return Err(format!("branch {i} breaks iteration order"));
            }
            if b.points
                .iter()
                .any(|p| !p.position.is_finite() || !p.radius.is_finite())
            {
                return Err(format!("branch {i} has a non-finite point"));
            }
        }
        for (i, l) in self.leaves.iter().enumerate() {
            if i > 0 && self.leaves[i - 1].iteration > l.iteration {
                return Err(format!("leaf {i} breaks iteration order"));
            }
            if let Some(b) = l.branch
                && b as usize >= self.branches.len()
            {
                return Err(format!("leaf {i} names branch {b}, which does not exist"));
            }
            if !(l.center.is_finite() && l.width.is_finite() && l.length.is_finite()) {
                return Err(format!("leaf {i} is not finite"));
            }
            if l.material as usize >= self.materials.leaf.len() {
                return Err(format!("leaf {i} names a missing material {}", l.material));
            }
        }
        Ok(())
    }
}
