//! Leaf fitting: a leaf primitive becomes [`Leaf`] records. A component that is a quad (two
//! triangles, four corners) gives one leaf: centre of its bounding rectangle, normal from the
//! winding (oriented like the vertex normals), axis along uv `v` when uvs exist, else along the
//! longest side. Anything else gives one leaf per triangle (centroid, face normal, axis along
//! the longest edge; the rectangle has twice the triangle's area). Details in the parent
//! module's docs.

use std::collections::HashMap;

use canopy_shared::model::Leaf;
use glam::{Vec2, Vec3};

use super::ImportStats;
use super::primitives::Placed;
use super::topology::{components, quad_outline, weld};

/// Unit 3-D direction of increasing uv `v` over the given vertices: the `v` column of the
/// least-squares affine map from uv to position. `None` without uvs or with degenerate uvs.
fn uv_v_direction(placed: &Placed, verts: &[u32]) -> Option<Vec3> {
    let uvs = placed.uvs.as_ref()?;
    let k = verts.len() as f32;
    let p_mean = verts.iter().map(|&i| placed.positions[i as usize]).sum::<Vec3>() / k;
    let q_mean = verts.iter().map(|&i| uvs[i as usize]).sum::<Vec2>() / k;
    let (mut suu, mut svv, mut suv) = (0.0f32, 0.0f32, 0.0f32);
    let (mut sup, mut svp) = (Vec3::ZERO, Vec3::ZERO);
    for &i in verts {
        let d = uvs[i as usize] - q_mean;
        let p = placed.positions[i as usize] - p_mean;
        suu += d.x * d.x;
        svv += d.y * d.y;
        suv += d.x * d.y;
        sup += p * d.x;
        svp += p * d.y;
    }
    let det = suu * svv - suv * suv;
    if !det.is_finite() || det.abs() <= 1e-12 * (suu * svv).max(f32::MIN_POSITIVE) {
        return None;
    }
    ((svp * suu - sup * suv) / det).try_normalize()
}

/// Builds a leaf from a plane frame and the points to cover.
fn leaf_from_points(points: &[Vec3], normal: Vec3, axis: Vec3, material: u8) -> Option<Leaf> {
    let axis = (axis - normal * axis.dot(normal)).try_normalize()?;
    let side = axis.cross(normal);
    let mean = points.iter().copied().sum::<Vec3>() / points.len() as f32;
    let (mut a_lo, mut a_hi, mut s_lo, mut s_hi) = (f32::MAX, f32::MIN, f32::MAX, f32::MIN);
    for &p in points {
        let d = p - mean;
        a_lo = a_lo.min(d.dot(axis));
        a_hi = a_hi.max(d.dot(axis));
        s_lo = s_lo.min(d.dot(side));
        s_hi = s_hi.max(d.dot(side));
    }
    let (length, width) = (a_hi - a_lo, s_hi - s_lo);
    if !(length > 0.0 && width > 0.0 && length.is_finite() && width.is_finite()) {
        return None;
    }
    Some(Leaf {
        center: mean + axis * (0.5 * (a_lo + a_hi)) + side * (0.5 * (s_lo + s_hi)),
        normal,
        axis,
        width,
        length,
        branch: None,
        iteration: 0,
        material,
    })
}

/// Orients a face normal like the vertex normals, when the primitive has them.
fn orient(placed: &Placed, face: Vec3, verts: &[u32]) -> Vec3 {
    let Some(ns) = &placed.normals else {
        return face;
    };
    let sum: Vec3 = verts.iter().map(|&k| ns[k as usize]).sum();
    if sum.dot(face) < 0.0 { -face } else { face }
}

fn quad_leaf(placed: &Placed, tris: &[usize], outline: [u32; 4], material: u8) -> Option<Leaf> {
    let p = |k: u32| placed.positions[k as usize];
    let corners = outline.map(p);
    let mut normal = Vec3::ZERO;
    for &t in tris {
        let [a, b, c] = placed.triangles[t].map(p);
        normal += (b - a).cross(c - a);
    }
    let normal = orient(placed, normal.try_normalize()?, &outline);
    let uv_axis = uv_v_direction(placed, &outline).filter(|d| d.dot(normal).abs() < 0.9);
    let axis = uv_axis.unwrap_or_else(|| {
        let mut best = Vec3::ZERO;
        for i in 0..4 {
            let e = corners[(i + 1) % 4] - corners[i];
            if e.length_squared() > best.length_squared() {
                best = e;
            }
        }
        best
    });
    leaf_from_points(&corners, normal, axis, material)
}

fn triangle_leaf(placed: &Placed, t: [u32; 3], material: u8) -> Option<Leaf> {
    let [a, b, c] = t.map(|k| placed.positions[k as usize]);
    let face = (b - a).cross(c - a).try_normalize()?;
    let normal = orient(placed, face, &t);
    let edges = [b - a, c - b, a - c];
    let longest = edges
        .into_iter()
        .max_by(|x, y| x.length_squared().total_cmp(&y.length_squared()))?;
    let mut leaf = leaf_from_points(&[a, b, c], normal, longest, material)?;
    leaf.center = (a + b + c) / 3.0;
    Some(leaf)
}

/// Turns a leaf primitive into leaves (see the module docs).
pub(super) fn leaves_from_primitive(placed: &Placed, material: u8, out: &mut Vec<Leaf>, stats: &mut ImportStats) {
    let welded = weld(&placed.positions);
    let all: Vec<usize> = (0..placed.triangles.len()).collect();
    let n = placed.positions.len();
    let per_triangle = |tris: &[usize], out: &mut Vec<Leaf>, stats: &mut ImportStats| {
        for &t in tris {
            match triangle_leaf(placed, placed.triangles[t], material) {
                Some(leaf) => {
                    out.push(leaf);
                    stats.leaf_triangles += 1;
                }
                None => stats.degenerate_leaf_triangles += 1,
            }
        }
    };
    for comp in components(n, &placed.triangles, &all, Some(&welded)) {
        if comp.len() == 2 {
            if let Some(leaf) =
                quad_outline(placed, &welded, &comp).and_then(|outline| quad_leaf(placed, &comp, outline, material))
            {
                out.push(leaf);
                stats.leaf_quads += 1;
            } else {
                per_triangle(&comp, out, stats);
            }
            continue;
        }
        // Split back by shared vertex index. A quad in there stays a leaf if it touches the
        // rest along at most one edge (leaves that merely touch); quads of a flat-shaded blob
        // share most of their edges with neighbouring faces and go per triangle.
        let subs = components(n, &placed.triangles, &comp, None);
        let outlines: Vec<Option<[u32; 4]>> = subs.iter().map(|sub| quad_outline(placed, &welded, sub)).collect();
        let corner_sets: Vec<Option<[u32; 4]>> = outlines
            .iter()
            .map(|o| {
                o.map(|o| {
                    let mut w = o.map(|k| welded[k as usize]);
                    w.sort_unstable();
                    w
                })
            })
            .collect();
        let mut edge_owners: HashMap<(u32, u32), Vec<usize>> = HashMap::new();
        for (si, sub) in subs.iter().enumerate() {
            for &t in sub {
                let w = placed.triangles[t].map(|k| welded[k as usize]);
                for (a, b) in [(w[0], w[1]), (w[1], w[2]), (w[2], w[0])] {
                    let owners = edge_owners.entry((a.min(b), a.max(b))).or_default();
                    if owners.last() != Some(&si) {
                        owners.push(si);
                    }
                }
            }
        }
        for (si, sub) in subs.iter().enumerate() {
            if let Some(outline) = outlines[si] {
                let w = outline.map(|k| welded[k as usize]);
                let shared = (0..4)
                    .filter(|&e| {
                        let (a, b) = (w[e], w[(e + 1) % 4]);
                        edge_owners
                            .get(&(a.min(b), a.max(b)))
                            .is_some_and(|owners| owners.iter().any(|&o| o != si && corner_sets[o] != corner_sets[si]))
                    })
                    .count();
                if shared <= 1
                    && let Some(leaf) = quad_leaf(placed, sub, outline, material)
                {
                    out.push(leaf);
                    stats.leaf_quads += 1;
                    continue;
                }
            }
            per_triangle(sub, out, stats);
        }
    }
}
