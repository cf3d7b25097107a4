//! Conservative occlusion culling by the ground seen from above it (the terrain): a horizon map.
//! Around the eye, azimuth is cut into narrow bins and horizontal distance into steps growing
//! by [`HORIZON_STEP`]; each bin holds, for each distance, the steepest elevation (as a slope,
//! rise over horizontal run) by which the ground is known to block every ray of the bin nearer
//! than that distance. A tree's bounding sphere is hidden when, in every bin its azimuth range
//! touches, that slope nearer than the sphere exceeds the steepest slope from the eye to any
//! point of the sphere.
//!
//! Why it never drops a visible tree: a point at horizontal distance `D` and slope `σ` is seen
//! along the ray whose height at distance `t` is `eye.y + σ·t`. Where the ground at some
//! `t < D` on the ray's azimuth is higher than that, the ray is under the ground there; the eye
//! is above the ground, so the opaque ground has met the ray before `t` and the point is hidden.
//! A bin's slope at a step comes from [`LowerBound::lowest_in`] over a rectangle holding the
//! whole annular sector of the step, divided by the step's distance that makes it smallest, so
//! it holds for every azimuth in the bin and every distance in the step. Ground not known
//! (tiles not held, or outside the grid) is taken as no ground; azimuths outside the view's are
//! never culled (left to frustum culling).
//!
//! The map does not depend on the camera's pitch: it is a function of the eye's position and
//! the range of azimuths the view covers. It costs bins × steps lower-bound queries, about a
//! tenth of a millisecond per bin, where a per-pixel ray march costs a query per pixel and step.
//!
//! Conventions: y up, metres; azimuth `atan2(x − eye.x, z − eye.z)`, radians; slopes are
//! `(y − eye.y) / horizontal distance`; −∞ where no ground is known to block.

use glam::{Mat4, Vec3};

/// Azimuth bins across the view (the whole circle when the view looks straight up or down).
pub const HORIZON_BINS: usize = 256;

/// Growth of the horizontal distance between steps (4 %: a bin's ground is bounded over
/// sectors 4 % deep, which makes the bound that much looser than the ground itself).
pub const HORIZON_STEP: f32 = 0.04;

/// Horizontal distance of the first step, metres: nearer ground is not used.
pub const HORIZON_START: f32 = 0.5;

/// The ground as occlusion reads it: a lower bound of its height over a rectangle.
pub trait LowerBound {
    /// A height no higher than the ground anywhere in the rectangle `[min x, min z, max x,
    /// max z]`; −∞ where the ground there is not known.
    fn lowest_in(&self, rect: [f32; 4]) -> f32;
    /// A height no lower than the ground anywhere (−∞: no ground known).
    fn highest(&self) -> f32;
    /// The rectangle outside which no ground is known (`None`: unbounded).
    fn extent(&self) -> Option<[f32; 4]> {
        None
    }
}

/// The horizon map of one eye and one view's azimuths (empty by default: it hides nothing).
#[derive(Debug, Clone, Default)]
pub struct Horizon {
    eye: Vec3,
    /// Azimuth where bin 0 starts, radians.
    start: f32,
    /// Azimuth width of a bin, radians.
    bin: f32,
    bins: usize,
    /// Whether the bins go round the whole circle.
    whole: bool,
    steps: usize,
    /// `ln(1 + HORIZON_STEP)`.
    ln_step: f32,
    /// Per bin, per step `k`: the steepest slope the ground blocks at some distance in
    /// `[HORIZON_START, t_k]`, `t_k = HORIZON_START·(1 + HORIZON_STEP)^k`; row by bin.
    slope: Vec<f32>,
    /// Bins with some blocking ground.
    blocked: usize,
}

/// Wraps an angle into `[0, 2π)`.
fn wrap(a: f32) -> f32 {
    a.rem_euclid(std::f32::consts::TAU)
}

impl Horizon {
    /// The bins for a camera with world → view matrix `view`, vertical field of view `fov_y`
    /// (radians) and aspect `width/height`: the view's azimuths with a bin's margin each side.
    pub fn new(view: Mat4, fov_y: f32, aspect: f32) -> Self {
        let mut h = Self::default();
        h.aim(view, fov_y, aspect);
        h
    }

    /// Aims the bins at another view (as [`Horizon::new`]), emptying the map but keeping its
    /// buffer: a streamer re-aims one map every frame.
    pub fn aim(&mut self, view: Mat4, fov_y: f32, aspect: f32) {
        let inv = view.inverse();
        let eye = inv.transform_point3(Vec3::ZERO);
        let ty = (fov_y * 0.5).tan();
        let tx = ty * aspect.max(1e-3);
        // Straight up or down in view: every azimuth is.
        let vertical = [Vec3::Y, Vec3::NEG_Y].iter().any(|&d| {
            let v = view.transform_vector3(d);
            v.z < 0.0 && v.x.abs() <= -v.z * tx && v.y.abs() <= -v.z * ty
        });
        let centre = inv.transform_vector3(Vec3::NEG_Z);
        let corners = [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)]
            .map(|(x, y)| inv.transform_vector3(Vec3::new(x * tx, y * ty, -1.0)));
        let flat = |v: Vec3| glam::Vec2::new(v.x, v.z);
        let c = flat(centre);
        let mut half = 0.0f32;
        let mut whole = vertical || c.length_squared() < 1e-8;
        for v in corners.map(flat) {
            if v.length_squared() < 1e-8 {
                whole = true;
            }
            half = half.max(c.perp_dot(v).atan2(c.dot(v)).abs());
        }
        let whole = whole || half >= std::f32::consts::FRAC_PI_2;
        let (start, span) = if whole {
            (0.0, std::f32::consts::TAU)
        } else {
            let span = 2.0 * half;
            let margin = span / HORIZON_BINS as f32;
            (wrap(c.x.atan2(c.y) - half - margin), span + 2.0 * margin)
        };
        self.eye = eye;
        self.start = start;
        self.bin = span / HORIZON_BINS as f32;
        self.bins = HORIZON_BINS;
        self.whole = whole;
        self.steps = 0;
        self.ln_step = HORIZON_STEP.ln_1p();
        self.slope.clear();
        self.blocked = 0;
    }

    /// Bins with some ground known to block them.
    pub fn blocked_bins(&self) -> usize {
        self.blocked
    }

    /// Bins and steps of the map.
    pub fn size(&self) -> (usize, usize) {
        (self.bins, self.steps)
    }

    /// Bounds every bin's ground out to horizontal distance `far` from `ground`.
    pub fn build(&mut self, ground: &impl LowerBound, far: f32) {
        let top = ground.highest();
        if !(self.eye.is_finite() && top.is_finite() && far > HORIZON_START) {
            return;
        }
        let steps = ((far / HORIZON_START).ln() / self.ln_step).ceil() as usize;
        self.steps = steps;
        self.slope.clear();
        self.slope.resize(self.bins * steps, f32::NEG_INFINITY);
        // A sector's outer arc bulges past the chord between its corners by at most this
        // fraction of its radius.
        let bulge = 1.0 - (self.bin * 0.5).cos();
        let eye = self.eye;
        // A ray from inside the ground's rectangle leaves it once: past that, no ground is
        // known (a lower bound over a rectangle partly outside is −∞).
        let inside = |r: [f32; 4], e: [f32; 4]| r[0] >= e[0] && r[1] >= e[1] && r[2] <= e[2] && r[3] <= e[3];
        let extent = ground.extent().filter(|e| inside([eye.x, eye.z, eye.x, eye.z], *e));
        let mut blocked = 0;
        for b in 0..self.bins {
            let a0 = self.start + b as f32 * self.bin;
            let (s0, c0) = a0.sin_cos();
            let (s1, c1) = (a0 + self.bin).sin_cos();
            let row = &mut self.slope[b * steps..(b + 1) * steps];
            let mut run = f32::NEG_INFINITY;
            let mut t = HORIZON_START;
            for (k, slot) in row.iter_mut().enumerate() {
                let t1 = t * (1.0 + HORIZON_STEP);
                // Ground higher than every blocking height from here on cannot raise the run.
                if top > eye.y && run >= (top - eye.y) / t {
                    row[k..].fill(run);
                    break;
                }
                let xs = [t * s0, t * s1, t1 * s0, t1 * s1];
                let zs = [t * c0, t * c1, t1 * c0, t1 * c1];
                let pad = t1 * bulge;
                let rect = [
                    eye.x + xs.iter().copied().fold(f32::INFINITY, f32::min) - pad,
                    eye.z + zs.iter().copied().fold(f32::INFINITY, f32::min) - pad,
                    eye.x + xs.iter().copied().fold(f32::NEG_INFINITY, f32::max) + pad,
                    eye.z + zs.iter().copied().fold(f32::NEG_INFINITY, f32::max) + pad,
                ];
                // Stopping early only leaves ground unused: still conservative.
                if extent.is_some_and(|e| !inside(rect, e)) {
                    row[k..].fill(run);
                    break;
                }
                let low = ground.lowest_in(rect);
                if low.is_finite() {
                    // The gentlest slope of that height over the step's distances.
                    let rise = low - eye.y;
                    run = run.max(rise / if rise > 0.0 { t1 } else { t });
                }
                *slot = run;
                t = t1;
            }
            if row.last().is_some_and(|s| s.is_finite()) {
                blocked += 1;
            }
        }
        self.blocked = blocked;
    }

    /// Whether the sphere at `centre` with radius `radius` (world) is hidden by the ground.
    /// `false` when the eye is inside its vertical cylinder, nearer than [`HORIZON_START`], or
    /// outside the bins' azimuths.
    pub fn hides_sphere(&self, centre: Vec3, radius: f32) -> bool {
        let Some((b0, b1)) = self.bins_of(centre, radius) else {
            return false;
        };
        let (dx, dz) = (centre.x - self.eye.x, centre.z - self.eye.z);
        let dist = dx.hypot(dz);
        // The steepest slope from the eye to the sphere: the centre's elevation plus the
        // sphere's angular radius (its points' directions form that cone).
        let to = centre - self.eye;
        let elevation = to.y.atan2(dist) + (radius / to.length()).clamp(-1.0, 1.0).asin();
        if elevation.is_nan() || elevation >= std::f32::consts::FRAC_PI_2 - 1e-4 {
            return false;
        }
        let sigma = elevation.tan();
        // The last step nearer than the sphere.
        let near = dist - radius;
        let k = (((near / HORIZON_START).ln() / self.ln_step).floor() as usize).min(self.steps - 1);
        (b0..=b1).all(|b| self.slope[(b % self.bins) * self.steps + k] > sigma)
    }

    /// The bins (first, last; the last may pass `bins` where they wrap) the sphere's azimuths
    /// fall in; `None` when the map is empty, the sphere is nearer than [`HORIZON_START`] or
    /// outside the bins.
    fn bins_of(&self, centre: Vec3, radius: f32) -> Option<(usize, usize)> {
        if self.steps == 0 {
            return None;
        }
        let (dx, dz) = (centre.x - self.eye.x, centre.z - self.eye.z);
        let dist = dx.hypot(dz);
        if !(dist - radius > HORIZON_START && radius >= 0.0) {
            return None;
        }
        let half = (radius / dist).asin();
        let from = wrap(dx.atan2(dz) - half - self.start);
        let to = from + 2.0 * half;
        if !self.whole && to >= self.bin * self.bins as f32 {
            return None;
        }
        Some(((from / self.bin).floor() as usize, (to / self.bin).floor() as usize))
    }

    /// Whether the axis-aligned box `lo..hi` (world) is hidden: its bounding sphere is.
    pub fn hides_box(&self, lo: Vec3, hi: Vec3) -> bool {
        self.hides_sphere((lo + hi) * 0.5, (hi - lo).length() * 0.5)
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

    fn horizon(cam: &Camera, ground: &Field) -> Horizon {
        let mut h = Horizon::new(cam.view(), 60f32.to_radians(), 16.0 / 9.0);
        h.build(ground, 600.0);
        h
    }

    /// A ridge 30 m high across x at z = −60 on flat ground, seen from 2 m above the ground.
    fn ridge() -> Field {
        ridge_at(-60.0)
    }

    /// A ridge 30 m high across x at `z0` on flat ground.
    fn ridge_at(z0: f32) -> Field {
        let n = 101u32;
        let h: Vec<f32> = (0..n * n)
            .map(|k| {
                let z = (k / n) as f32 * 4.0 - 200.0;
                (30.0 - 3.0 * (z - z0).abs()).max(0.0)
            })
            .collect();
        Field(Heightfield::new([-200.0, -200.0], 4.0, [n, n], &h).expect("valid"))
    }

    #[test]
    fn bins_wrap_where_the_view_spans_azimuth_zero() {
        // Looking along +z (yaw π): azimuth 0 is the middle of the view, so its bins wrap.
        let g = ridge_at(60.0);
        let cam = Camera {
            eye: Vec3::new(0.0, 2.0, 0.0),
            yaw: std::f32::consts::PI,
            pitch: 0.0,
        };
        let r = horizon(&cam, &g);
        assert!(!r.whole);
        for x in [-12.0, -3.0, 0.0, 3.0, 12.0] {
            assert!(
                r.hides_sphere(Vec3::new(x, 8.0, 107.0), 4.0),
                "behind the ridge at x = {x}"
            );
            assert!(
                !r.hides_sphere(Vec3::new(x, 4.0, 30.0), 4.0),
                "in front of it at x = {x}"
            );
        }
        // Looking straight down the bins go round the whole circle.
        let down = Camera { pitch: -1.55, ..cam };
        let d = horizon(&down, &g);
        assert!(d.whole);
        assert!(d.hides_sphere(Vec3::new(0.0, 8.0, 107.0), 4.0));
        assert!(!d.hides_sphere(Vec3::new(0.0, 8.0, -107.0), 4.0), "no ridge that way");
    }

    #[test]
    fn a_tree_behind_a_ridge_is_hidden_and_one_above_it_is_not() {
        let g = ridge();
        let cam = Camera {
            eye: Vec3::new(0.0, 2.0, 0.0),
            yaw: 0.0,
            pitch: 0.0,
        };
        let r = horizon(&cam, &g);
        assert!(r.blocked_bins() > 0);
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
        let mut r = Horizon::new(cam.view(), 1.0, 1.5);
        r.build(&None_, 500.0);
        assert_eq!(r.blocked_bins(), 0);
        assert!(!r.hides_box(Vec3::new(-1.0, -50.0, -50.0), Vec3::new(1.0, -40.0, -40.0)));
    }

    /// Points spread over a sphere's surface (a Fibonacci lattice) and its centre.
    fn sphere_points(c: Vec3, r: f32) -> impl Iterator<Item = Vec3> {
        let n = 48;
        (0..n)
            .map(move |k| {
                let y = 1.0 - 2.0 * (k as f32 + 0.5) / n as f32;
                let a = k as f32 * 2.399_963;
                let s = (1.0 - y * y).sqrt();
                c + r * Vec3::new(s * a.cos(), y, s * a.sin())
            })
            .chain(std::iter::once(c))
    }

    /// Whether the ray from `eye` to `p` goes under the ground before `p`, marched in 0.2 m steps.
    fn ray_under(g: &Field, eye: Vec3, p: Vec3) -> bool {
        let steps = (p.distance(eye) / 0.2).ceil() as usize;
        (1..steps).any(|s| {
            let q = eye + (p - eye) * (s as f32 / steps as f32);
            q.y < g.0.height_at(q.x, q.z)
        })
    }

    /// Property: whatever is reported hidden is hidden along every sampled ray, and at least
    /// half of what every sampled ray finds hidden is reported (the rest is mostly hidden by
    /// ground under the sphere's own footprint, which the map does not use). Random hilly fields and low cameras
    /// above them, some looking straight down (the bins go round the whole circle); random
    /// spheres standing on the ground.
    #[test]
    fn hidden_spheres_are_hidden_along_every_ray() {
        let mut rng = canopy_shared::rng::SplitMix64::new(11);
        let (mut hidden, mut hidden_by_rays) = (0, 0);
        for case in 0..12 {
            let g = field(case, 20.0 + 10.0 * (case % 4) as f32);
            let mut u = || rng.next_f64() as f32;
            let (x, z) = (100.0 * (u() - 0.5), 100.0 * (u() - 0.5));
            let cam = Camera {
                eye: Vec3::new(x, g.0.height_at(x, z) + 1.0 + 20.0 * u(), z),
                yaw: u() * std::f32::consts::TAU,
                pitch: if case % 3 == 0 { -1.5 } else { (u() - 0.7) * 0.5 },
            };
            let r = horizon(&cam, &g);
            for _ in 0..1200 {
                let (bx, bz) = (cam.eye.x + 300.0 * (u() - 0.5), cam.eye.z + 300.0 * (u() - 0.5));
                let radius = 1.0 + 8.0 * u();
                let c = Vec3::new(bx, g.0.height_at(bx, bz) + radius, bz);
                let in_view = r.bins_of(c, radius).is_some();
                let by_rays = sphere_points(c, radius).all(|p| ray_under(&g, cam.eye, p));
                if by_rays && in_view {
                    hidden_by_rays += 1;
                }
                if !r.hides_sphere(c, radius) {
                    continue;
                }
                hidden += 1;
                assert!(
                    by_rays,
                    "case {case}: sphere {c} r {radius} hidden, but a ray to it stays above the ground"
                );
            }
        }
        assert!(hidden > 100, "the test must see hidden spheres: {hidden}");
        assert!(
            hidden * 2 >= hidden_by_rays,
            "hidden {hidden} of {hidden_by_rays} found hidden by rays in front of the eye"
        );
    }
}
