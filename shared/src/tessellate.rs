//! Tessellation of skeletons and leaves into triangles.
//!
//! - [`branch_tubes`] / [`branch_tubes_with`] / [`append_branch_tube`]: a generalised cylinder
//!   ("tube") along each branch centre line, with the radius of each skeleton point, using
//!   parallel-transport frames so that tubes do not twist along curved branches.
//! - [`leaf_quads`] / [`leaf_quads_scaled`]: two triangles per leaf, with uvs.
//!
//! All output is in tree space (Y up, metres), triangles counter-clockwise seen from the outside
//! (the side the normals point to), indices `u32`.

use glam::{Quat, Vec3};

use crate::model::{Branch, Leaf, TreeModel, TriangleMesh};

/// Smallest number of sides a tube can have; fewer requested sides are raised to this.
pub const MIN_TUBE_SIDES: u32 = 3;

/// Largest number of sides a tube can have; more requested sides are lowered to this.
pub const MAX_TUBE_SIDES: u32 = 256;

/// Consecutive skeleton points closer than this (metres) are merged when tessellating.
const MIN_SEGMENT: f32 = 1e-6;

/// Options for [`branch_tubes_with`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct TubeOptions {
    /// Vertices per ring, clamped to `MIN_TUBE_SIDES..=MAX_TUBE_SIDES`. Callers may pass fewer
    /// sides for coarser levels of detail (3 is a triangular prism).
    pub sides: u32,
    /// Close both ends of each tube with a triangle fan (base cap facing backwards along the
    /// branch, tip cap facing forwards). Skipped at an end whose radius is zero.
    pub caps: bool,
}

impl Default for TubeOptions {
    fn default() -> Self {
        Self { sides: 8, caps: false }
    }
}

/// Tubes along every branch of `model`, `sides` vertices per ring, no caps.
///
/// Contract:
/// - Each branch with at least two distinct, finite skeleton points yields one tube; other
///   branches (degenerate, non-finite) are skipped silently. Consecutive points closer than
///   1 µm are merged.
/// - Every skeleton point yields one ring of `sides` vertices (clamped to
///   [`MIN_TUBE_SIDES`]`..=`[`MAX_TUBE_SIDES`]) at distance `radius` (negative radii count as 0)
///   from the centre line, in the plane perpendicular to the local tangent (the bisector of the
///   adjacent segment directions at interior points).
/// - Ring frames are propagated by parallel transport (minimal rotation from one tangent to the
///   next), so a straight or planar-curved branch does not twist.
/// - Between consecutive rings: `2 * sides` triangles. So a branch with `n` points gives
///   `n * sides` vertices and `2 * (n - 1) * sides` triangles.
/// - `normals` has one unit normal per position (the radial direction); triangles are
///   counter-clockwise seen from outside the tube.
/// - Branch order and point order are preserved in the vertex order.
pub fn branch_tubes(model: &TreeModel, sides: u32) -> TriangleMesh {
    branch_tubes_with(model, TubeOptions { sides, caps: false })
}

/// Like [`branch_tubes`], with [`TubeOptions`] (caps).
///
/// With `caps`, each end with a positive radius gets one extra centre vertex (normal along the
/// outward tangent) and `sides` more triangles; the cap shares no vertices with the ring so that
/// its normals stay flat.
pub fn branch_tubes_with(model: &TreeModel, options: TubeOptions) -> TriangleMesh {
    let mut mesh = TriangleMesh::default();
    for branch in &model.branches {
        append_branch_tube(branch, options, &mut mesh);
    }
    mesh
}

/// Like [`branch_tubes_with`], keeping only the branches with at least one point of radius
/// `min_radius` or more (metres): a far view drops twigs thinner than a fraction of a pixel.
pub fn branch_tubes_thicker_than(model: &TreeModel, options: TubeOptions, min_radius: f32) -> TriangleMesh {
    let mut mesh = TriangleMesh::default();
    for b in &model.branches {
        if b.points.iter().any(|p| p.radius >= min_radius) {
            append_branch_tube(b, options, &mut mesh);
        }
    }
    mesh
}

/// Appends the tube of one branch to `out` (same contract as [`branch_tubes_with`] for a single
/// branch). Returns the number of triangles appended (0 for a skipped branch).
///
/// `out.normals` must be either empty with `out.positions` empty, or one per position; normals
/// are appended alongside the positions.
pub fn append_branch_tube(branch: &Branch, options: TubeOptions, out: &mut TriangleMesh) -> usize {
    let sides = options.sides.clamp(MIN_TUBE_SIDES, MAX_TUBE_SIDES);
    // Merge coincident points, drop non-finite ones.
    let mut pts: Vec<(Vec3, f32)> = Vec::with_capacity(branch.points.len());
    for p in &branch.points {
        if !p.position.is_finite() || !p.radius.is_finite() {
            return 0;
        }
        let r = p.radius.max(0.0);
        match pts.last_mut() {
            Some(last) if last.0.distance(p.position) < MIN_SEGMENT => last.1 = last.1.max(r),
            _ => pts.push((p.position, r)),
        }
    }
    if pts.len() < 2 {
        return 0;
    }
    let Ok(base) = u32::try_from(out.positions.len()) else {
        return 0;
    };
    let n = pts.len();
    let tangents: Vec<Vec3> = (0..n)
        .map(|i| {
            let prev = (i > 0).then(|| (pts[i].0 - pts[i - 1].0).normalize_or_zero());
            let next = (i + 1 < n).then(|| (pts[i + 1].0 - pts[i].0).normalize_or_zero());
            match (prev, next) {
                (Some(a), Some(b)) => (a + b).try_normalize().unwrap_or(b),
                (Some(a), None) => a,
                (None, Some(b)) => b,
                (None, None) => Vec3::Y,
            }
        })
        .collect();

    // Initial frame: a normal perpendicular to the first tangent.
    let mut normal = initial_normal(tangents[0]);
    let mut prev_t = tangents[0];
    let step = std::f32::consts::TAU / sides as f32;
    let sin_cos: Vec<(f32, f32)> = (0..sides).map(|j| (j as f32 * step).sin_cos()).collect();

    let mut tri_count = 0usize;
    for (i, &(p, r)) in pts.iter().enumerate() {
        let t = tangents[i];
        if i > 0 {
            // Parallel transport: rotate the previous normal by the minimal rotation prev_t -> t.
            let q = Quat::from_rotation_arc(prev_t, t);
            normal = q * normal;
            normal = (normal - t * normal.dot(t))
                .try_normalize()
                .unwrap_or_else(|| initial_normal(t));
        }
        prev_t = t;
        let binormal = t.cross(normal);
        for &(s, c) in &sin_cos {
            let dir = normal * c + binormal * s;
            out.positions.push(p + dir * r);
            out.normals.push(dir);
        }
    }
    for i in 0..(n as u32 - 1) {
        let ring0 = base + i * sides;
        let ring1 = ring0 + sides;
        for j in 0..sides {
            let k = (j + 1) % sides;
            let (a, b, c, d) = (ring0 + j, ring0 + k, ring1 + j, ring1 + k);
            out.indices.extend_from_slice(&[a, b, d, a, d, c]);
            tri_count += 2;
        }
    }
    if options.caps {
        for (end, outward) in [(0usize, -tangents[0]), (n - 1, tangents[n - 1])] {
            let (p, r) = pts[end];
            if r <= 0.0 {
                continue;
            }
            let ring = base + end as u32 * sides;
            let Ok(start) = u32::try_from(out.positions.len()) else {
                break;
            };
            // Copy the ring with flat normals, then the centre vertex.
            for j in 0..sides {
                out.positions.push(out.positions[(ring + j) as usize]);
                out.normals.push(outward);
            }
            out.positions.push(p);
            out.normals.push(outward);
            let centre = start + sides;
            for j in 0..sides {
                let k = (j + 1) % sides;
                if end == 0 {
                    // Facing -tangent: the ring runs clockwise seen from that side.
                    out.indices.extend_from_slice(&[centre, start + k, start + j]);
                } else {
                    out.indices.extend_from_slice(&[centre, start + j, start + k]);
                }
                tri_count += 1;
            }
        }
    }
    tri_count
}

/// A unit vector perpendicular to the unit vector `t`, chosen stably.
fn initial_normal(t: Vec3) -> Vec3 {
    let helper = if t.x.abs() < 0.9 { Vec3::X } else { Vec3::Z };
    (helper - t * helper.dot(t)).try_normalize().unwrap_or(Vec3::Z)
}

/// Vertex buffers of leaf quads: `(positions, normals, uvs, indices)`.
pub type LeafQuadBuffers = (Vec<Vec3>, Vec<Vec3>, Vec<[f32; 2]>, Vec<u32>);

/// Two triangles per leaf, at the leaf's own size. See [`leaf_quads_scaled`].
pub fn leaf_quads(leaves: &[Leaf]) -> LeafQuadBuffers {
    leaf_quads_scaled(leaves, 1.0)
}

/// Two triangles per leaf, each leaf enlarged uniformly by `scale` about its centre (seed 004's
/// leaf enlargement `s`: coarser levels draw fewer, larger leaves).
///
/// Contract:
/// - Leaf `i` owns vertices `4 i .. 4 i + 4`, which are [`Leaf::corners`] of the leaf with
///   `width` and `length` multiplied by `scale` (`scale` is used as given; pass a positive
///   finite value), and indices `6 i .. 6 i + 6` = `[4i, 4i+1, 4i+2, 4i, 4i+2, 4i+3]`:
///   counter-clockwise seen from the side `normal` points to.
/// - Normals: the leaf's `normal` at all four vertices.
/// - Uvs: `u` across the blade (0 at `-side`, 1 at `+side`), `v` along the leaf axis (0 at the
///   petiole end, 1 at the tip): corners get `(0,0) (1,0) (1,1) (0,1)`. Note that glTF and most
///   image APIs put `v = 0` at the top row of the image, so a leaf texture for these uvs has its
///   petiole at the top.
/// - Output lengths: `4 n` positions, normals and uvs, `6 n` indices for `n` leaves.
pub fn leaf_quads_scaled(leaves: &[Leaf], scale: f32) -> LeafQuadBuffers {
    let n = leaves.len();
    let mut positions = Vec::with_capacity(4 * n);
    let mut normals = Vec::with_capacity(4 * n);
    let mut uvs = Vec::with_capacity(4 * n);
    let mut indices = Vec::with_capacity(6 * n);
    for (i, leaf) in leaves.iter().enumerate() {
        let scaled = Leaf {
            width: leaf.width * scale,
            length: leaf.length * scale,
            ..*leaf
        };
        positions.extend_from_slice(&scaled.corners());
        normals.extend_from_slice(&[leaf.normal; 4]);
        uvs.extend_from_slice(&[[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]);
        let b = (4 * i) as u32;
        indices.extend_from_slice(&[b, b + 1, b + 2, b, b + 2, b + 3]);
    }
    (positions, normals, uvs, indices)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::model::{Materials, ModelSource, SkeletonPoint};

    fn model(branches: Vec<Branch>) -> TreeModel {
        TreeModel {
            name: "t".into(),
            branches,
            leaves: vec![],
            bark_mesh: TriangleMesh::default(),
            materials: Materials::default(),
            iterations: 0,
            source: ModelSource::LSystem,
        }
    }

    fn branch(points: &[(Vec3, f32)]) -> Branch {
        Branch {
            points: points
                .iter()
                .map(|&(position, radius)| SkeletonPoint { position, radius })
                .collect(),
            parent: None,
            level: 1,
            iteration: 0,
        }
    }

    fn tri_normal(m: &TriangleMesh, t: usize) -> Vec3 {
        let [a, b, c] = [0, 1, 2].map(|k| m.positions[m.indices[3 * t + k] as usize]);
        (b - a).cross(c - a)
    }

    #[test]
    fn straight_tube_counts_radii_and_outward_winding() {
        let m = model(vec![branch(&[
            (Vec3::ZERO, 0.5),
            (Vec3::new(0.0, 1.0, 0.0), 0.3),
            (Vec3::new(0.0, 2.0, 0.0), 0.1),
        ])]);
        let mesh = branch_tubes(&m, 6);
        assert_eq!(mesh.positions.len(), 18);
        assert_eq!(mesh.normals.len(), 18);
        assert_eq!(mesh.triangle_count(), 2 * 2 * 6);
        for (k, p) in mesh.positions.iter().enumerate() {
            let want = [0.5, 0.3, 0.1][k / 6];
            let radial = Vec3::new(p.x, 0.0, p.z).length();
            assert!((radial - want).abs() < 1e-5, "{k}: {radial} vs {want}");
            assert!((mesh.normals[k].length() - 1.0).abs() < 1e-5);
        }
        for t in 0..mesh.triangle_count() {
            let n = tri_normal(&mesh, t);
            let a = mesh.positions[mesh.indices[3 * t] as usize];
            assert!(n.dot(Vec3::new(a.x, 0.0, a.z)) > 0.0, "triangle {t} faces inwards");
        }
        assert!(mesh.indices.iter().all(|&i| (i as usize) < mesh.positions.len()));
    }

    #[test]
    fn bent_tube_does_not_twist() {
        // A planar curve in the XY plane: the transported frame must stay symmetric to that
        // plane, so the ring vertex that starts on +Z stays exactly on +Z.
        let pts: Vec<(Vec3, f32)> = (0..20)
            .map(|i| {
                let a = i as f32 * 0.08;
                (Vec3::new(1.0 - a.cos(), a.sin(), 0.0), 0.05)
            })
            .collect();
        let m = model(vec![branch(&pts)]);
        let sides = 8;
        let mesh = branch_tubes(&m, sides);
        // Find the side index on +Z at the first ring.
        let j = (0..sides as usize)
            .max_by(|&a, &b| mesh.normals[a].z.total_cmp(&mesh.normals[b].z))
            .unwrap();
        for ring in 0..pts.len() {
            let nrm = mesh.normals[ring * sides as usize + j];
            assert!(nrm.z > 0.99, "ring {ring} twisted: {nrm}");
        }
    }

    #[test]
    fn sides_are_clamped_and_degenerate_branches_skipped() {
        let m = model(vec![
            branch(&[(Vec3::ZERO, 0.1), (Vec3::Y, 0.1)]),
            branch(&[(Vec3::ZERO, 0.1)]),
            branch(&[(Vec3::ZERO, 0.1), (Vec3::ZERO, 0.2)]),
            branch(&[(Vec3::ZERO, 0.1), (Vec3::new(f32::NAN, 0.0, 0.0), 0.1)]),
        ]);
        let mesh = branch_tubes(&m, 1);
        assert_eq!(mesh.positions.len(), 2 * MIN_TUBE_SIDES as usize);
        assert_eq!(mesh.triangle_count(), 2 * MIN_TUBE_SIDES as usize);
        assert!(mesh.positions.iter().all(|p| p.is_finite()));
    }

    #[test]
    fn caps_close_the_tube_facing_outwards() {
        let m = model(vec![branch(&[(Vec3::ZERO, 0.2), (Vec3::Y, 0.1)])]);
        let mesh = branch_tubes_with(&m, TubeOptions { sides: 5, caps: true });
        assert_eq!(mesh.triangle_count(), 10 + 5 + 5);
        assert_eq!(mesh.positions.len(), mesh.normals.len());
        // Cap triangles are the last 10: first 5 face -Y, last 5 face +Y.
        for t in 10..15 {
            assert!(tri_normal(&mesh, t).normalize().dot(-Vec3::Y) > 0.99);
        }
        for t in 15..20 {
            assert!(tri_normal(&mesh, t).normalize().dot(Vec3::Y) > 0.99);
        }
        // A zero tip radius gets no tip cap.
        let m = model(vec![branch(&[(Vec3::ZERO, 0.2), (Vec3::Y, 0.0)])]);
        let mesh = branch_tubes_with(&m, TubeOptions { sides: 5, caps: true });
        assert_eq!(mesh.triangle_count(), 15);
    }

    fn leaf() -> Leaf {
        Leaf {
            center: Vec3::new(1.0, 2.0, 3.0),
            normal: Vec3::Z,
            axis: Vec3::Y,
            width: 0.2,
            length: 0.4,
            branch: None,
            iteration: 0,
            material: 0,
        }
    }

    #[test]
    fn leaf_quad_layout_uvs_and_winding() {
        let (p, n, uv, idx) = leaf_quads(&[leaf(), leaf()]);
        assert_eq!((p.len(), n.len(), uv.len(), idx.len()), (8, 8, 8, 12));
        assert_eq!(&idx[6..], &[4, 5, 6, 4, 6, 7]);
        for t in 0..4 {
            let [a, b, c] = [0, 1, 2].map(|k| p[idx[3 * t + k] as usize]);
            assert!((b - a).cross(c - a).normalize().dot(Vec3::Z) > 0.999);
        }
        // v grows along the axis, u along the side.
        let l = leaf();
        for k in 0..4 {
            let d = p[k] - l.center;
            assert!((d.dot(l.axis) / l.length + 0.5 - uv[k][1]).abs() < 1e-5);
            assert!((d.dot(l.side()) / l.width + 0.5 - uv[k][0]).abs() < 1e-5);
        }
    }

    #[test]
    fn leaf_scale_about_centre() {
        let (p1, ..) = leaf_quads(&[leaf()]);
        let (p2, ..) = leaf_quads_scaled(&[leaf()], 2.5);
        let c = leaf().center;
        for k in 0..4 {
            assert!(((p2[k] - c) - (p1[k] - c) * 2.5).length() < 1e-5);
        }
        let (p, n, uv, idx) = leaf_quads(&[]);
        assert!(p.is_empty() && n.is_empty() && uv.is_empty() && idx.is_empty());
    }
}
