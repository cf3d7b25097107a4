//! Mesh topology for leaf detection: welding vertices with bit-equal positions, connected
//! components of triangles (by shared vertex index, optionally also by shared position), and
//! recognising a two-triangle component as a (possibly folded) quad.

use std::collections::HashMap;

use glam::Vec3;

use super::primitives::Placed;

/// Cosine of the largest fold between the two triangles of a leaf quad (about 75 degrees).
pub const QUAD_MIN_FOLD_COS: f32 = 0.25;

/// Disjoint sets over vertex indices (path halving; the smaller root wins, so roots are the
/// lowest index of their set).
struct UnionFind(Vec<u32>);

impl UnionFind {
    fn new(n: usize) -> Self {
        Self((0..n as u32).collect())
    }
    fn find(&mut self, mut x: u32) -> u32 {
        while self.0[x as usize] != x {
            let p = self.0[x as usize];
            self.0[x as usize] = self.0[p as usize];
            x = p;
        }
        x
    }
    fn union(&mut self, a: u32, b: u32) {
        let (a, b) = (self.find(a), self.find(b));
        if a != b {
            self.0[a.max(b) as usize] = a.min(b);
        }
    }
}

fn position_key(p: Vec3) -> [u32; 3] {
    // +0.0 for -0.0 so that both weld.
    (p + Vec3::ZERO)
        .to_array()
        .map(|c| if c == 0.0 { 0 } else { c.to_bits() })
}

/// For every vertex, the first vertex with a bit-equal position.
pub(super) fn weld(positions: &[Vec3]) -> Vec<u32> {
    let mut first: HashMap<[u32; 3], u32> = HashMap::with_capacity(positions.len());
    positions
        .iter()
        .enumerate()
        .map(|(i, &p)| *first.entry(position_key(p)).or_insert(i as u32))
        .collect()
}

/// Groups triangles into connected components (by shared index and, with `welded`, by shared
/// position). Components are ordered by their first triangle.
pub(super) fn components(
    vertex_count: usize,
    triangles: &[[u32; 3]],
    tri_ids: &[usize],
    welded: Option<&[u32]>,
) -> Vec<Vec<usize>> {
    let mut uf = UnionFind::new(vertex_count);
    let map = |k: u32| welded.map_or(k, |w| w[k as usize]);
    for &t in tri_ids {
        let [a, b, c] = triangles[t].map(map);
        uf.union(a, b);
        uf.union(a, c);
    }
    let mut slot: HashMap<u32, usize> = HashMap::new();
    let mut out: Vec<Vec<usize>> = Vec::new();
    for &t in tri_ids {
        let r = uf.find(map(triangles[t][0]));
        let k = *slot.entry(r).or_insert_with(|| {
            out.push(Vec::new());
            out.len() - 1
        });
        out[k].push(t);
    }
    out
}

/// The four corners of a two-triangle component, in outline order, if it is a planar quad.
pub(super) fn quad_outline(placed: &Placed, welded: &[u32], tris: &[usize]) -> Option<[u32; 4]> {
    let [t0, t1] = *tris else { return None };
    let a = placed.triangles[t0];
    let b = placed.triangles[t1];
    let wa = a.map(|k| welded[k as usize]);
    let wb = b.map(|k| welded[k as usize]);
    if wa[0] == wa[1] || wa[1] == wa[2] || wa[0] == wa[2] {
        return None;
    }
    let shared: Vec<usize> = (0..3).filter(|&i| wb.contains(&wa[i])).collect();
    if shared.len() != 2 {
        return None;
    }
    let lone_a = (0..3).find(|i| !shared.contains(i))?;
    let lone_b = (0..3).find(|&i| !wa.contains(&wb[i]))?;
    if wb[lone_b] == wa[lone_a] {
        return None;
    }
    // Nearly planar: real leaf cards are often folded along a diagonal (tfs_detailedTree's by
    // exactly 60 degrees), so accept folds up to ~75 degrees.
    let p = |k: u32| placed.positions[k as usize];
    let na = (p(a[1]) - p(a[0])).cross(p(a[2]) - p(a[0]));
    let nb = (p(b[1]) - p(b[0])).cross(p(b[2]) - p(b[0]));
    let (Some(na), Some(nb)) = (na.try_normalize(), nb.try_normalize()) else {
        return None;
    };
    if na.dot(nb).abs() < QUAD_MIN_FOLD_COS {
        return None;
    }
    // Outline: lone_a, next shared, lone_b, other shared.
    let s1 = a[(lone_a + 1) % 3];
    let s2 = a[(lone_a + 2) % 3];
    Some([a[lone_a], s1, b[lone_b], s2])
}
