//! Irregular view sets (seed 001's photographs): the spherical Delaunay triangulation of the
//! frames' view directions, and the lookup of the frame(s) to show for a view direction.
//!
//! Conventions: directions are unit vectors, tree → camera, Y up (as the rest of the atlas);
//! vertex `k` is the view set's `k`-th direction (layout-local frame `k`). Triangles are stored
//! counter-clockwise seen from outside the sphere: `det(a, b, c) > 0`.
//!
//! **Contract.** [`ViewSphere::new`] accepts any list (empty, duplicates, non-finite entries,
//! all on one great circle) and never panics; [`ViewSphere::locate`] returns a triangle only
//! if it contains the direction (`det(a, b, q) ≥ 0` on its three edges, up to rounding) and
//! [`ViewSphere::nearest`] returns the view of largest `dot(view, q)` (the nearest by angle)
//! among the finite ones.
//!
//! **Method.** The spherical Delaunay triangulation is the convex hull of the unit vectors; it
//! is computed as the planar Delaunay triangulation (`delaunator`) of their stereographic
//! projection from the pole opposite the set's mean direction. The projection maps circles to
//! circles, so a planar Delaunay triangle is a spherical one; the spherical triangles whose
//! empty cap holds the pole (only in the unsampled region opposite the views) are missing,
//! and a direction there is *outside* (nearest view only). Location walks from a hint triangle
//! across the edge the direction lies beyond (exact orientation tests on the sphere, `f64`),
//! with a step cap and a scan as fallback. The nearest view: seed 001 takes the nearest of the
//! located triangle's three vertices, which is not always the nearest view (a view across a
//! long edge can be nearer); from it a greedy walk over Delaunay neighbours reaches the true
//! nearest (on a Delaunay graph a vertex that is not the nearest has a neighbour nearer to
//! `q`: shrink the cap through it toward `q` until it meets another view).

use glam::{DVec3, Vec3};

/// Where a direction falls in the triangulation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ViewLocation {
    /// Inside triangle `index`, vertices `views` (view-set indices), barycentric `weights`
    /// (≥ 0, summing to 1) in the same order.
    Triangle {
        /// Triangle index (a hint for the next lookup).
        index: u32,
        /// The three views.
        views: [u32; 3],
        /// Their weights.
        weights: [f32; 3],
    },
    /// In no triangle: outside the views' coverage, or the set has no triangle at all.
    Outside,
}

/// The spherical Delaunay triangulation of a view set, ready for lookups.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ViewSphere {
    dirs: Vec<DVec3>,
    /// Triangles, `det > 0`.
    tris: Vec<[u32; 3]>,
    /// Per triangle and edge (`ab`, `bc`, `ca`): the triangle across it.
    across: Vec<[Option<u32>; 3]>,
    /// Delaunay neighbours of every view, CSR: `adjacency[start[k]..start[k + 1]]`.
    start: Vec<u32>,
    adjacency: Vec<u32>,
    /// Finite views in no edge (duplicates, the projection pole, a set without triangles): the
    /// nearest-view search checks them one by one.
    loose: Vec<u32>,
}

/// `det(a, b, c) = (a × b) · c`: > 0 when `c` is left of the great circle from `a` to `b`
/// seen from outside.
fn det(a: DVec3, b: DVec3, c: DVec3) -> f64 {
    a.cross(b).dot(c)
}

/// Largest planar hull whose vertices are linked pairwise (see [`ViewSphere::new`]).
const MAX_LINKED_HULL: usize = 256;

/// Rounding allowance of the orientation tests on unit vectors.
const ORIENT_EPS: f64 = 1e-12;

impl ViewSphere {
    /// Triangulates `dirs` (normalised here; a zero or non-finite entry is kept as a view that
    /// is never returned).
    pub fn new(dirs: &[Vec3]) -> Self {
        let dirs: Vec<DVec3> = dirs
            .iter()
            .map(|d| {
                let d = d.as_dvec3();
                let n = d.length();
                if n.is_finite() && n > 0.0 { d / n } else { DVec3::NAN }
            })
            .collect();
        let finite = |k: usize| dirs[k].is_finite();
        let mean: DVec3 = dirs.iter().filter(|d| d.is_finite()).sum();
        // Projection from the pole `-centre`; `centre` the mean direction when it has one.
        let centre = mean
            .try_normalize()
            .filter(|_| mean.length() > 1e-3)
            .unwrap_or(DVec3::Y);
        let e1 = centre.any_orthonormal_vector();
        let e2 = centre.cross(e1);
        let mut points = Vec::new();
        let mut index_of = Vec::new();
        for (k, d) in dirs.iter().enumerate() {
            let denom = 1.0 + d.dot(centre);
            if finite(k) && denom > 1e-9 {
                points.push(delaunator::Point {
                    x: d.dot(e1) / denom,
                    y: d.dot(e2) / denom,
                });
                index_of.push(k as u32);
            }
        }
        let t = delaunator::triangulate(&points);
        let mut edges: Vec<(u32, u32)> = Vec::new();
        let mut tris = Vec::new();
        for tri in t.triangles.chunks_exact(3) {
            let [a, b, c] = [index_of[tri[0]], index_of[tri[1]], index_of[tri[2]]];
            edges.extend([(a, b), (b, c), (c, a)]);
            let (pa, pb, pc) = (dirs[a as usize], dirs[b as usize], dirs[c as usize]);
            let o = det(pa, pb, pc);
            // All views of a triangle on one great circle: no area on the sphere.
            if o > 1e-9 {
                tris.push([a, b, c]);
            } else if o < -1e-9 {
                tris.push([a, c, b]);
            }
        }
        // Triangles across each edge: the one holding the reversed directed edge.
        let mut directed: Vec<((u32, u32), u32)> = Vec::with_capacity(tris.len() * 3);
        for (i, t) in tris.iter().enumerate() {
            for e in 0..3 {
                directed.push(((t[e], t[(e + 1) % 3]), i as u32));
            }
        }
        directed.sort_unstable();
        let across = tris
            .iter()
            .map(|t| {
                std::array::from_fn(|e| {
                    let key = (t[(e + 1) % 3], t[e]);
                    directed
                        .binary_search_by(|probe| probe.0.cmp(&key))
                        .ok()
                        .map(|i| directed[i].1)
                })
            })
            .collect();
        // Neighbours: every edge of the planar triangulation (also of triangles dropped as
        // flat, and the hull of a collinear set, which delaunator returns without triangles).
        // The spherical triangles missing from it (their cap holds the pole) have all their
        // vertices on the planar hull (a circle with every other point inside): linking the
        // hull vertices to each other makes a graph holding every spherical Delaunay edge, on
        // which the greedy walk is exact. A hull too large to link goes to the loose views.
        let hull: Vec<u32> = t.hull.iter().map(|&i| index_of[i]).collect();
        let mut loose_hull = Vec::new();
        if hull.len() <= MAX_LINKED_HULL {
            for (i, &a) in hull.iter().enumerate() {
                edges.extend(hull[i + 1..].iter().map(|&b| (a, b)));
            }
        } else {
            loose_hull = hull;
        }
        let mut pairs: Vec<(u32, u32)> = edges.iter().flat_map(|&(a, b)| [(a, b), (b, a)]).collect();
        pairs.sort_unstable();
        pairs.dedup();
        let mut start = vec![0u32; dirs.len() + 1];
        for &(a, _) in &pairs {
            start[a as usize + 1] += 1;
        }
        for k in 0..dirs.len() {
            start[k + 1] += start[k];
        }
        let adjacency = pairs.iter().map(|&(_, b)| b).collect();
        let mut loose: Vec<u32> = (0..dirs.len())
            .filter(|&k| finite(k) && start[k] == start[k + 1])
            .map(|k| k as u32)
            .collect();
        loose.extend(loose_hull);
        Self {
            dirs,
            tris,
            across,
            start,
            adjacency,
            loose,
        }
    }

    /// Views in the set.
    pub fn len(&self) -> usize {
        self.dirs.len()
    }

    /// Whether the set has no view.
    pub fn is_empty(&self) -> bool {
        self.dirs.is_empty()
    }

    /// Triangles of the triangulation.
    pub fn triangles(&self) -> &[[u32; 3]] {
        &self.tris
    }

    /// Unit direction of view `k` (NaN for a zero or non-finite input).
    pub fn direction(&self, k: u32) -> Option<Vec3> {
        self.dirs.get(k as usize).map(DVec3::as_vec3)
    }

    fn contains(&self, t: usize, q: DVec3) -> Option<[f64; 3]> {
        let [a, b, c] = self.tris[t].map(|k| self.dirs[k as usize]);
        let o = [det(a, b, q), det(b, c, q), det(c, a, q)];
        o.iter().all(|&x| x >= -ORIENT_EPS).then_some(o)
    }

    fn location(&self, t: usize, o: [f64; 3]) -> ViewLocation {
        // Weight of a vertex: the orientation of the opposite edge.
        let w = [o[1].max(0.0), o[2].max(0.0), o[0].max(0.0)];
        let sum = w[0] + w[1] + w[2];
        let weights = if sum > 0.0 {
            w.map(|x| (x / sum) as f32)
        } else {
            [1.0, 0.0, 0.0]
        };
        ViewLocation::Triangle {
            index: t as u32,
            views: self.tris[t],
            weights,
        }
    }

    /// The triangle holding direction `q`, walking from triangle `hint` (any value; the last
    /// answer's index makes coherent lookups a step or two).
    pub fn locate(&self, q: Vec3, hint: u32) -> ViewLocation {
        let Some(q) = q.as_dvec3().try_normalize() else {
            return ViewLocation::Outside;
        };
        if self.tris.is_empty() {
            return ViewLocation::Outside;
        }
        let mut t = if (hint as usize) < self.tris.len() {
            hint as usize
        } else {
            0
        };
        let mut prev = usize::MAX;
        for _ in 0..self.tris.len() + 8 {
            let [a, b, c] = self.tris[t].map(|k| self.dirs[k as usize]);
            let o = [det(a, b, q), det(b, c, q), det(c, a, q)];
            if o.iter().all(|&x| x >= -ORIENT_EPS) {
                return self.location(t, o);
            }
            // Cross the edge `q` lies furthest beyond (not back where the walk came from).
            let mut order = [0usize, 1, 2];
            order.sort_by(|&i, &j| o[i].total_cmp(&o[j]));
            let next = order
                .iter()
                .filter(|&&e| o[e] < -ORIENT_EPS)
                .find_map(|&e| self.across[t][e].filter(|&n| n as usize != prev))
                .or_else(|| {
                    order
                        .iter()
                        .filter(|&&e| o[e] < -ORIENT_EPS)
                        .find_map(|&e| self.across[t][e])
                });
            match next {
                Some(n) => {
                    prev = t;
                    t = n as usize;
                }
                // Beyond a boundary edge: outside, unless the walk was misled (flat triangles
                // dropped leave holes); the scan settles it.
                None => break,
            }
        }
        (0..self.tris.len())
            .find_map(|t| self.contains(t, q).map(|o| self.location(t, o)))
            .unwrap_or(ViewLocation::Outside)
    }

    /// The view nearest to `q` by angle (`None` for an empty set or a zero `q`), and the
    /// location found on the way. `hint` as in [`ViewSphere::locate`].
    pub fn nearest(&self, q: Vec3, hint: u32) -> Option<(u32, ViewLocation)> {
        let qd = q.as_dvec3().try_normalize()?;
        let loc = self.locate(q, hint);
        let dot = |k: u32| {
            let d = self.dirs[k as usize].dot(qd);
            if d.is_nan() { f64::NEG_INFINITY } else { d }
        };
        // Seed 001: the nearest vertex of the located triangle; else any view with neighbours.
        let first = match loc {
            ViewLocation::Triangle { views, .. } => views.into_iter().max_by(|&a, &b| dot(a).total_cmp(&dot(b))),
            ViewLocation::Outside => {
                (0..self.dirs.len() as u32).find(|&k| self.start[k as usize] < self.start[k as usize + 1])
            }
        };
        let mut best = first;
        if let Some(mut cur) = first {
            // Greedy descent over Delaunay neighbours; each step strictly nearer, so it ends.
            loop {
                let (s, e) = (self.start[cur as usize] as usize, self.start[cur as usize + 1] as usize);
                let next = self.adjacency[s..e]
                    .iter()
                    .copied()
                    .max_by(|&a, &b| dot(a).total_cmp(&dot(b)))
                    .filter(|&n| dot(n) > dot(cur));
                match next {
                    Some(n) => cur = n,
                    None => break,
                }
            }
            best = Some(cur);
        }
        for &k in &self.loose {
            if best.is_none_or(|b| dot(k) > dot(b)) {
                best = Some(k);
            }
        }
        best.filter(|&b| dot(b).is_finite()).map(|b| (b, loc))
    }

    /// Seed 001's rule alone: the nearest vertex of the located triangle (`None` outside).
    pub fn nearest_of_triangle(&self, q: Vec3, hint: u32) -> Option<u32> {
        let qd = q.as_dvec3().try_normalize()?;
        match self.locate(q, hint) {
            ViewLocation::Triangle { views, .. } => views
                .into_iter()
                .max_by(|&a, &b| self.dirs[a as usize].dot(qd).total_cmp(&self.dirs[b as usize].dot(qd))),
            ViewLocation::Outside => None,
        }
    }

    /// The views to blend for `q`: the located triangle's three with barycentric weights, or
    /// the nearest view alone (weight 1) outside the triangulation. Empty for an empty set.
    pub fn blend(&self, q: Vec3, hint: u32) -> ViewBlend {
        let Some(qd) = q.as_dvec3().try_normalize() else {
            return ViewBlend::default();
        };
        match self.locate(q, hint) {
            ViewLocation::Triangle { index, views, weights } => ViewBlend {
                frames: [(views[0], weights[0]), (views[1], weights[1]), (views[2], weights[2])],
                len: 3,
                triangle: Some(index),
            },
            ViewLocation::Outside => match self.nearest(qd.as_vec3(), hint) {
                Some((n, _)) => ViewBlend {
                    frames: [(n, 1.0), (n, 0.0), (n, 0.0)],
                    len: 1,
                    triangle: None,
                },
                None => ViewBlend::default(),
            },
        }
    }
}

/// What [`ViewSphere::blend`] returns: `frames[..len]` with weights summing to 1, and the
/// triangle located (a hint for the next lookup).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ViewBlend {
    /// View-set indices and weights.
    pub frames: [(u32, f32); 3],
    /// How many of `frames` count.
    pub len: usize,
    /// The triangle holding the direction, if any.
    pub triangle: Option<u32>,
}

impl ViewBlend {
    /// The views that count.
    pub fn as_slice(&self) -> &[(u32, f32)] {
        &self.frames[..self.len]
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64 as Rng;

    fn r(rng: &mut Rng, lo: f64, hi: f64) -> f32 {
        rng.uniform(lo, hi) as f32
    }

    fn brute_nearest(dirs: &[Vec3], q: Vec3) -> f32 {
        let q = q.normalize();
        dirs.iter()
            .map(|d| d.normalize().dot(q))
            .fold(f32::NEG_INFINITY, f32::max)
    }

    /// A photographer's set: walks around the tree at eye level and up a slope, never behind
    /// the tree's west side (a gap of 100° in azimuth), a few from a drone above.
    fn photo_set(rng: &mut Rng, n: usize) -> Vec<Vec3> {
        (0..n)
            .map(|i| {
                let (az, el) = if i % 7 == 0 {
                    (r(rng, 0.0, 360.0), r(rng, 50.0, 85.0))
                } else {
                    (r(rng, -130.0, 130.0), r(rng, -5.0, 35.0))
                };
                super::super::lat_long_direction(az.to_radians(), el.to_radians())
            })
            .collect()
    }

    fn random_dir(rng: &mut Rng) -> Vec3 {
        loop {
            let v = Vec3::new(r(rng, -1.0, 1.0), r(rng, -1.0, 1.0), r(rng, -1.0, 1.0));
            if v.length() > 0.1 && v.length() <= 1.0 {
                return v.normalize();
            }
        }
    }

    proptest::proptest! {
        /// The located triangle holds the direction; outside only when no triangle does; the
        /// nearest view is the brute-force nearest, whatever the set.
        #[test]
        fn locate_and_nearest_agree_with_brute_force(seed in 0u64..10_000, n in 1usize..120, photo in proptest::bool::ANY) {
            let mut rng = Rng::new(seed);
            let dirs = if photo { photo_set(&mut rng, n) } else { (0..n).map(|_| random_dir(&mut rng)).collect() };
            let s = ViewSphere::new(&dirs);
            let mut hint = 0;
            for _ in 0..40 {
                let q = random_dir(&mut rng);
                let qd = q.as_dvec3();
                match s.locate(q, hint) {
                    ViewLocation::Triangle { index, views, weights } => {
                        let [a, b, c] = views.map(|k| dirs[k as usize].as_dvec3().normalize());
                        for o in [det(a, b, qd), det(b, c, qd), det(c, a, qd)] {
                            proptest::prop_assert!(o >= -1e-9, "orientation {o}");
                        }
                        proptest::prop_assert!((weights.iter().sum::<f32>() - 1.0).abs() < 1e-4);
                        hint = index;
                    }
                    ViewLocation::Outside => {
                        for t in 0..s.tris.len() {
                            proptest::prop_assert!(s.contains(t, qd).is_none(), "missed triangle {t}");
                        }
                    }
                }
                let (k, _) = s.nearest(q, hint).unwrap();
                let got = dirs[k as usize].normalize().dot(q);
                proptest::prop_assert!(got >= brute_nearest(&dirs, q) - 1e-5, "view {k}: {got}");
            }
        }
    }

    #[test]
    fn a_gappy_photo_set_returns_the_nearest_frame() {
        let mut rng = Rng::new(7);
        let dirs = photo_set(&mut rng, 60);
        let s = ViewSphere::new(&dirs);
        assert!(s.triangles().len() > 40, "{}", s.triangles().len());
        // Directions in the gap (the west side), and below everything.
        let mut outside = 0;
        let mut misses = 0;
        for k in 0..400 {
            let q =
                super::super::lat_long_direction((k as f32 * 0.9).to_radians(), ((k % 90) as f32 - 20.0).to_radians());
            let (n, loc) = s.nearest(q, 0).unwrap();
            assert!((dirs[n as usize].normalize().dot(q) - brute_nearest(&dirs, q)).abs() < 1e-5);
            outside += usize::from(loc == ViewLocation::Outside);
            misses += usize::from(s.nearest_of_triangle(q, 0).is_some_and(|t| t != n));
        }
        assert!(outside > 0, "the gap is outside the triangulation");
        // Seed 001's rule (nearest of the triangle's three) is right most of the time only.
        assert!(misses < 200, "{misses}");
    }

    #[test]
    fn degenerate_sets_never_panic() {
        let q = Vec3::new(0.3, 0.5, -0.2);
        assert_eq!(ViewSphere::new(&[]).nearest(q, 0), None);
        assert_eq!(ViewSphere::new(&[]).blend(q, 0).len, 0);
        let one = ViewSphere::new(&[Vec3::X]);
        assert_eq!(one.nearest(q, 0).map(|x| x.0), Some(0));
        assert_eq!(one.blend(q, 0).as_slice(), &[(0, 1.0)]);
        // Duplicates, zero and non-finite entries: never returned.
        let dup = ViewSphere::new(&[Vec3::X, Vec3::X, Vec3::ZERO, Vec3::NAN, Vec3::Y, Vec3::Z]);
        for _ in 0..3 {
            let (k, _) = dup.nearest(Vec3::new(0.1, 0.2, -1.0), 99).unwrap();
            assert!(matches!(k, 0 | 1 | 4 | 5));
        }
        // A ring at eye level (a photographer circling the tree): every triangle is flat, the
        // ring's neighbours still lead to the nearest view.
        let ring: Vec<Vec3> = (0..24)
            .map(|i| super::super::lat_long_direction((i as f32 * 15.0).to_radians(), 0.0))
            .collect();
        let r = ViewSphere::new(&ring);
        assert!(r.triangles().is_empty());
        for k in 0..100 {
            let q = super::super::lat_long_direction((k as f32 * 3.7).to_radians(), 0.4);
            let (n, loc) = r.nearest(q, 0).unwrap();
            assert_eq!(loc, ViewLocation::Outside);
            assert!((ring[n as usize].dot(q.normalize()) - brute_nearest(&ring, q)).abs() < 1e-5);
        }
        assert_eq!(r.nearest(Vec3::ZERO, 0), None);
        assert_eq!(r.locate(Vec3::NAN, 0), ViewLocation::Outside);
    }

    #[test]
    fn exactly_at_a_view_the_weight_is_one() {
        let dirs: Vec<Vec3> = crate::raster::fibonacci_sphere(40)
            .into_iter()
            .filter(|d| d.y > -0.2)
            .collect();
        let s = ViewSphere::new(&dirs);
        for (k, d) in dirs.iter().enumerate() {
            let b = s.blend(*d, 0);
            let best = b.as_slice().iter().max_by(|a, b| a.1.total_cmp(&b.1)).unwrap();
            assert_eq!(best.0, k as u32);
            assert!(best.1 > 0.999, "{b:?}");
        }
    }
}
