//! Conservative occlusion culling by the ground seen from above it (the terrain): a small depth
//! raster whose pixels each hold a depth by which every ray through the whole pixel has gone
//! under the ground; a box is hidden when every pixel its projection touches holds a depth
//! nearer than the box's nearest point.
//!
//! Why it never drops a visible tree: a pixel's rays at view depth `d` form a small quad; when
//! the quad's highest point is no higher than the lowest ground anywhere under the quad
//! ([`LowerBound::lowest_in`]), every ray of the pixel is at or under the ground at depth `d`.
//! The eye is above the ground, so each of those rays has met the ground (opaque) by then, and
//! anything farther along it is hidden. The depths tried are a sequence, not every depth: a
//! depth skipped only makes a pixel's stored depth farther, never nearer. A box with a corner
//! nearer than the near plane is never culled; ground not known (tiles not held) is taken as
//! no ground.
//!
//! Conventions: view space as [`crate::stream::Camera::view`] (looking along −Z), depth is the
//! distance along the view axis, metres; pixel `(0, 0)` is the top-left one and pixel `(x, y)`
//! covers `[x, x+1] × [y, y+1]`; pixels no ray of which is known to be hidden hold +∞.

use glam::{Mat4, Vec3};

/// Width of the occlusion raster, pixels (its height follows the viewport's aspect).
pub const OCCLUSION_WIDTH: u32 = 160;

/// Growth of the view depth between the depths a pixel's rays are tried at (4 %: a pixel's
/// stored depth is at most that much farther than the first depth its rays are all hidden by).
pub const MARCH_STEP: f32 = 0.04;
/// Ratio of the spans a ray skips at once when it stays above the ground under them.
const SKIP: f32 = 1.5;

/// The ground as occlusion reads it: a lower bound of its height over a rectangle.
pub trait LowerBound {
    /// A height no higher than the ground anywhere in the rectangle `[min x, min z, max x,
    /// max z]`; −∞ where the ground there is not known.
    fn lowest_in(&self, rect: [f32; 4]) -> f32;
    /// A height no lower than the ground anywhere (−∞: no ground known).
    fn highest(&self) -> f32;
    /// A height no lower than the ground anywhere in the rectangle (−∞ where no ground is
    /// drawn); [`LowerBound::highest`] by default. Lets a ray skip spans far above the ground.
    fn highest_in(&self, _rect: [f32; 4]) -> f32 {
        self.highest()
    }
}

/// The occlusion raster of one view.
#[derive(Debug, Clone)]
pub struct OcclusionRaster {
    width: u32,
    height: u32,
    view: Mat4,
    /// Projection scales: `sx = (x/d·fx + 1)·W/2`, `sy = (1 − y/d·fy)·H/2`.
    fx: f32,
    fy: f32,
    near: f32,
    depth: Vec<f32>,
    claimed: usize,
}

/// A view-space point projected: screen x, y.
#[derive(Debug, Clone, Copy)]
struct Screen {
    x: f32,
    y: f32,
}

impl OcclusionRaster {
    /// An empty raster for a camera with world → view matrix `view`, vertical field of view
    /// `fov_y` (radians), aspect `width/height` and near plane `near`.
    pub fn new(view: Mat4, fov_y: f32, aspect: f32, near: f32, width: u32) -> Self {
        let width = width.max(1);
        let height = ((width as f32 / aspect.max(1e-3)).round() as u32).max(1);
        let fy = 1.0 / (fov_y * 0.5).tan();
        let fx = fy / aspect.max(1e-3);
        Self {
            width,
            height,
            view,
            fx,
            fy,
            near: near.max(1e-3),
            depth: vec![f32::INFINITY; (width * height) as usize],
            claimed: 0,
        }
    }

    /// Raster size, pixels.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// Pixels claimed by some occluder.
    pub fn claimed_pixels(&self) -> usize {
        self.claimed
    }

    fn project(&self, v: Vec3) -> Screen {
        let d = -v.z;
        Screen {
            x: (v.x / d * self.fx + 1.0) * 0.5 * self.width as f32,
            y: (1.0 - v.y / d * self.fy) * 0.5 * self.height as f32,
        }
    }

    /// Marches every pixel's rays from the near plane out to view depth `far` against `ground`,
    /// storing the first depth tried at which all of them are under it.
    pub fn march(&mut self, ground: &impl LowerBound, far: f32) {
        let inv = self.view.inverse();
        let eye = inv.transform_point3(Vec3::ZERO);
        let top = ground.highest();
        if !(eye.is_finite() && top.is_finite()) {
            return;
        }
        let (w, h) = (self.width as usize, self.height as usize);
        // World direction of the ray through screen corner (x, y), with view depth 1.
        let dir = |x: usize, y: usize| {
            let nx = 2.0 * x as f32 / w as f32 - 1.0;
            let ny = 1.0 - 2.0 * y as f32 / h as f32;
            inv.transform_vector3(Vec3::new(nx / self.fx, ny / self.fy, -1.0))
        };
        let corners: Vec<Vec3> = (0..=h)
            .flat_map(|y| (0..=w).map(move |x| (x, y)))
            .map(|(x, y)| dir(x, y))
            .collect();
        let mut claimed = 0usize;
        for py in 0..h {
            for px in 0..w {
                let c = [
                    corners[py * (w + 1) + px],
                    corners[py * (w + 1) + px + 1],
                    corners[(py + 1) * (w + 1) + px],
                    corners[(py + 1) * (w + 1) + px + 1],
                ];
                let rising = c.iter().map(|v| v.y).fold(f32::INFINITY, f32::min);
                let mut d = self.near.max(0.25);
                'spans: while d <= far {
                    // A span [d, d·SKIP] whose rays stay above the highest ground under them
                    // cannot hide them: skip it (x, y, z are linear in d along each ray).
                    let d2 = (d * SKIP).min(far);
                    let (pa, pb) = (c.map(|v| eye + v * d), c.map(|v| eye + v * d2));
                    let both = || pa.iter().chain(&pb);
                    let low_span = both().map(|q| q.y).fold(f32::INFINITY, f32::min);
                    let span = [
                        both().map(|q| q.x).fold(f32::INFINITY, f32::min),
                        both().map(|q| q.z).fold(f32::INFINITY, f32::min),
                        both().map(|q| q.x).fold(f32::NEG_INFINITY, f32::max),
                        both().map(|q| q.z).fold(f32::NEG_INFINITY, f32::max),
                    ];
                    if low_span > ground.highest_in(span) {
                        if low_span > top && rising >= 0.0 {
                            break; // Above every ground and climbing: sky.
                        }
                        if d2 >= far {
                            break;
                        }
                        d = d2;
                        continue;
                    }
                    // Through the span in fine steps.
                    while d <= d2 {
                        let p = c.map(|v| eye + v * d);
                        let high = p.iter().map(|q| q.y).fold(f32::NEG_INFINITY, f32::max);
                        if high <= top {
                            let x0 = p.iter().map(|q| q.x).fold(f32::INFINITY, f32::min);
                            let x1 = p.iter().map(|q| q.x).fold(f32::NEG_INFINITY, f32::max);
                            let z0 = p.iter().map(|q| q.z).fold(f32::INFINITY, f32::min);
                            let z1 = p.iter().map(|q| q.z).fold(f32::NEG_INFINITY, f32::max);
                            if high <= ground.lowest_in([x0, z0, x1, z1]) {
                                self.depth[py * w + px] = d;
                                claimed += 1;
                                break 'spans;
                            }
                        }
                        d *= 1.0 + MARCH_STEP;
                    }
                    if d2 >= far {
                        break;
                    }
                    d = d2;
                }
            }
        }
        self.claimed = claimed;
    }

    /// Whether the axis-aligned box `lo..hi` (world) is hidden: every pixel its projection
    /// touches is claimed nearer than the box's nearest point. `false` when any corner is
    /// nearer than the near plane, or the projection misses the raster (left to frustum culling).
    pub fn hides_box(&self, lo: Vec3, hi: Vec3) -> bool {
        let mut near = f32::INFINITY;
        let (mut x0, mut x1, mut y0, mut y1) = (f32::INFINITY, f32::NEG_INFINITY, f32::INFINITY, f32::NEG_INFINITY);
        for k in 0..8 {
            let p = Vec3::new(
                if k & 1 == 0 { lo.x } else { hi.x },
                if k & 2 == 0 { lo.y } else { hi.y },
                if k & 4 == 0 { lo.z } else { hi.z },
            );
            let v = self.view.transform_point3(p);
            let d = -v.z;
            if !(d.is_finite() && d >= self.near) {
                return false;
            }
            near = near.min(d);
            let s = self.project(v);
            (x0, x1, y0, y1) = (x0.min(s.x), x1.max(s.x), y0.min(s.y), y1.max(s.y));
        }
        let (w, h) = (self.width as f32, self.height as f32);
        if !(x0.is_finite() && x1.is_finite() && y0.is_finite() && y1.is_finite()) {
            return false;
        }
        let px0 = x0.floor().clamp(0.0, w) as u32;
        let px1 = x1.ceil().clamp(0.0, w) as u32;
        let py0 = y0.floor().clamp(0.0, h) as u32;
        let py1 = y1.ceil().clamp(0.0, h) as u32;
        if px0 >= px1 || py0 >= py1 {
            return false;
        }
        // Top rows first: a tree standing behind a ridge shows its top first.
        for py in py0..py1 {
            let row = &self.depth[(py * self.width) as usize..((py + 1) * self.width) as usize];
            if row[px0 as usize..px1 as usize].iter().any(|&d| d >= near) {
                return false;
            }
        }
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stream::Camera;
    use canopy_shared::terrain::Heightfield;

    /// The ground of a whole heightfield, by brute force: the lowest sample of the cells the
    /// rectangle touches.
    struct Field(Heightfield);

    impl LowerBound for Field {
        fn lowest_in(&self, r: [f32; 4]) -> f32 {
            let g = &self.0.grid;
            let b = g.bounds();
            if r[0] < b[0] || r[1] < b[1] || r[2] > b[2] || r[3] > b[3] {
                return f32::NEG_INFINITY;
            }
            let (_, [u0, w0]) = g.locate(r[0], r[1]);
            let (_, [u1, w1]) = g.locate(r[2], r[3]);
            let mut lo = f32::INFINITY;
            for j in w0.floor() as u32..=(w1.ceil() as u32) {
                for i in u0.floor() as u32..=(u1.ceil() as u32) {
                    lo = lo.min(self.0.at(i, j));
                }
            }
            lo
        }
        fn highest(&self) -> f32 {
            self.0.heights.iter().copied().fold(f32::NEG_INFINITY, f32::max)
        }
        fn highest_in(&self, r: [f32; 4]) -> f32 {
            let g = &self.0.grid;
            let b = g.bounds();
            let r = [r[0].max(b[0]), r[1].max(b[1]), r[2].min(b[2]), r[3].min(b[3])];
            if r[0] > r[2] || r[1] > r[3] {
                return f32::NEG_INFINITY;
            }
            let (_, [u0, w0]) = g.locate(r[0], r[1]);
            let (_, [u1, w1]) = g.locate(r[2], r[3]);
            let mut hi = f32::NEG_INFINITY;
            for j in w0.floor() as u32..=(w1.ceil() as u32) {
                for i in u0.floor() as u32..=(u1.ceil() as u32) {
                    hi = hi.max(self.0.at(i, j));
                }
            }
            hi
        }
    }

    fn field(seed: u64, relief: f32) -> Field {
        let mut rng = canopy_shared::rng::SplitMix64::new(seed);
        let waves: Vec<[f32; 4]> = (0..6)
            .map(|_| {
                let a = rng.next_f64() as f32 * std::f32::consts::TAU;
                let k = 0.005 + 0.03 * rng.next_f64() as f32;
                [a.cos() * k, a.sin() * k, rng.next_f64() as f32 * 6.0, relief / 6.0]
            })
            .collect();
        let (n, cell) = (101u32, 4.0);
        let h: Vec<f32> = (0..n * n)
            .map(|k| {
                let (x, z) = ((k % n) as f32 * cell - 200.0, (k / n) as f32 * cell - 200.0);
                waves.iter().map(|w| w[3] * (w[0] * x + w[1] * z + w[2]).sin()).sum()
            })
            .collect();
        Field(Heightfield::new([-200.0, -200.0], f64::from(cell), [n, n], &h).expect("valid"))
    }

    fn raster(cam: &Camera, ground: &Field) -> OcclusionRaster {
        let mut r = OcclusionRaster::new(cam.view(), 60f32.to_radians(), 16.0 / 9.0, 0.1, 96);
        r.march(ground, 600.0);
        r
    }

    /// A ridge 30 m high across x at z = −60 on flat ground, seen from 2 m above the ground.
    fn ridge() -> Field {
        let n = 101u32;
        let h: Vec<f32> = (0..n * n)
            .map(|k| {
                let z = (k / n) as f32 * 4.0 - 200.0;
                (30.0 - 3.0 * (z + 60.0).abs()).max(0.0)
            })
            .collect();
        Field(Heightfield::new([-200.0, -200.0], 4.0, [n, n], &h).expect("valid"))
    }

    #[test]
    fn a_tree_behind_a_ridge_is_hidden_and_one_above_it_is_not() {
        let g = ridge();
        let cam = Camera {
            eye: Vec3::new(0.0, 2.0, 0.0),
            yaw: 0.0,
            pitch: 0.0,
        };
        let r = raster(&cam, &g);
        assert!(r.claimed_pixels() > 0);
        // Behind the ridge (top 30 m at 60 m: 28 m above the eye), well below its silhouette.
        assert!(r.hides_box(Vec3::new(-3.0, 0.0, -110.0), Vec3::new(3.0, 20.0, -104.0)));
        // Tall enough to show above it: at 110 m the silhouette is 2 + 28·110/60 ≈ 53 m.
        assert!(!r.hides_box(Vec3::new(-3.0, 0.0, -110.0), Vec3::new(3.0, 60.0, -104.0)));
        // In front of the ridge.
        assert!(!r.hides_box(Vec3::new(-3.0, 0.0, -30.0), Vec3::new(3.0, 6.0, -24.0)));
        // Straddling the near plane.
        assert!(!r.hides_box(Vec3::new(-1.0, 0.0, -1.0), Vec3::new(1.0, 3.0, 1.0)));
        // Behind the eye: left to frustum culling.
        assert!(!r.hides_box(Vec3::new(-3.0, 0.0, 70.0), Vec3::new(3.0, 6.0, 80.0)));
    }

    #[test]
    fn no_ground_hides_nothing() {
        struct None_;
        impl LowerBound for None_ {
            fn lowest_in(&self, _: [f32; 4]) -> f32 {
                f32::NEG_INFINITY
            }
            fn highest(&self) -> f32 {
                f32::NEG_INFINITY
            }
        }
        let cam = Camera {
            eye: Vec3::new(0.0, 2.0, 0.0),
            yaw: 0.0,
            pitch: -0.5,
        };
        let mut r = OcclusionRaster::new(cam.view(), 1.0, 1.5, 0.1, 64);
        r.march(&None_, 500.0);
        assert_eq!(r.claimed_pixels(), 0);
        assert!(!r.hides_box(Vec3::new(-1.0, -50.0, -50.0), Vec3::new(1.0, -40.0, -40.0)));
    }

    /// Property: whatever is reported hidden is hidden along every sampled ray. Random hilly
    /// fields and low cameras above them; for each random box reported hidden, rays from the
    /// eye to points spread over the box go under the ground before the point.
    #[test]
    fn hidden_boxes_are_hidden_along_every_ray() {
        let mut rng = canopy_shared::rng::SplitMix64::new(11);
        let mut hidden = 0;
        for case in 0..12 {
            let g = field(case, 20.0 + 10.0 * (case % 4) as f32);
            let mut u = || rng.next_f64() as f32;
            let (x, z) = (100.0 * (u() - 0.5), 100.0 * (u() - 0.5));
            let cam = Camera {
                eye: Vec3::new(x, g.0.height_at(x, z) + 1.0 + 20.0 * u(), z),
                yaw: u() * std::f32::consts::TAU,
                pitch: (u() - 0.7) * 0.5,
            };
            let r = raster(&cam, &g);
            for _ in 0..600 {
                let (bx, bz) = (cam.eye.x + 300.0 * (u() - 0.5), cam.eye.z + 300.0 * (u() - 0.5));
                let e = Vec3::new(1.0 + 4.0 * u(), 2.0 + 8.0 * u(), 1.0 + 4.0 * u());
                let c = Vec3::new(bx, g.0.height_at(bx, bz) + e.y, bz);
                if !r.hides_box(c - e, c + e) {
                    continue;
                }
                hidden += 1;
                for k in 0..27 {
                    let f = Vec3::new((k % 3) as f32, ((k / 3) % 3) as f32, (k / 9) as f32) * 0.5;
                    let p = c - e + 2.0 * e * f;
                    // Only points in view can be seen.
                    let sp = r.project(r.view.transform_point3(p));
                    if !(0.0..r.width as f32).contains(&sp.x) || !(0.0..r.height as f32).contains(&sp.y) {
                        continue;
                    }
                    let steps = (p.distance(cam.eye) / 0.2).ceil() as usize;
                    let under = (1..steps).any(|s| {
                        let q = cam.eye + (p - cam.eye) * (s as f32 / steps as f32);
                        q.y < g.0.height_at(q.x, q.z)
                    });
                    assert!(
                        under,
                        "case {case}: box {c} ± {e} hidden, but the ray to {p} stays above the ground"
                    );
                }
            }
        }
        assert!(hidden > 100, "the test must see hidden boxes: {hidden}");
    }
}
