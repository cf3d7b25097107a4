//! Seed 004: the per-node simplification rate `Rs = Σ α_k f_k` and leaf enlargement.
//!
//! Factors, exactly as the seed gives them (parameters in [`LodParams`]):
//!
//! - `f1(BSL)`: 0.0 / 0.4 / 0.8 for bounding-sphere layer 1 (outermost) / 2 / 3 (inner). Layer 0
//!   reads as 1 and layers above 3 as 3.
//! - `f2(BL, dist)`: 0 for `dist ≤ near`; `k1·BL·log_h(dist)` for `near < dist < far`; 0.5 for
//!   `dist ≥ far`. Reading: `k1 = 0.5 / (BL_max·log_h(far))`, the largest constant keeping
//!   `f2 ≤ 0.5` for every branch level up to `BL_max` inside `far`; the value is also clamped to
//!   [0, 0.5] (a `near < 1` makes `log_h` negative, read as 0).
//! - `f3(LD)`: `k2·(LD − ld0)` with `ld0 = min(ld1, 0.5·ld2)` (ld1 = lowest, ld2 = mean initial
//!   density over the tree's leaf nodes), `k2 = 1/ld0`, so `f3 = LD/ld0 − 1`. Reading of "LD =
//!   initial density × current rate": the *current keep fraction* `1 − Rs_current` of the node
//!   (the rate in force, i.e. last frame's), so that a node already thinned has a lower density
//!   and is not thinned further by this factor. Clamped to [0, 1]; `ld0 ≤ 0` gives 0.
//! - `f4(dist)`: 0 for `dist ≤ near`; `k3·log10(dist)` with `k3 = 1/log10(far)` between; 1 for
//!   `dist ≥ far`. As printed this jumps from 0 to `log10(near)/log10(far)` at `near`; kept as is.
//! - `f5(dir)`: `cos(dir)` for `dir ∈ [0, π/2]`, 0 for `(π/2, π]`, `dir` = angle between the line
//!   of sight (eye → node centre) and the growth direction (a leaf node carries its parent's).
//!   A degenerate line of sight (eye at the centre) or growth direction gives 0.
//!
//! The sum is clamped to [0, 1]. With the default weights its maximum is
//! `0.2·0.8 + 0.1·0.5 + 0.2 + 0.3 + 0.2 = 0.91`.

use canopy_shared::format::NodeRecord;
use canopy_shared::format::node::NodeKind;
use glam::Vec3;

use super::{LodParams, clamp01, sphere_distance};

/// Per-tree statistics some factors need.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TreeStats {
    /// `ld1`: lowest positive initial leaf density over leaf nodes (0 if none).
    pub min_density: f32,
    /// `ld2`: mean initial leaf density over leaf nodes (0 if none).
    pub mean_density: f32,
    /// Deepest branch level in the node table.
    pub max_branch_level: u8,
}

impl TreeStats {
    /// Computes the statistics from a node table.
    pub fn from_nodes(nodes: &[NodeRecord]) -> Self {
        let mut min = f32::INFINITY;
        let mut sum = 0.0f64;
        let mut n = 0u32;
        let mut max_level = 0u8;
        for node in nodes {
            max_level = max_level.max(node.branch_level);
            if node.kind == NodeKind::Leaf && node.leaf_density.is_finite() {
                sum += f64::from(node.leaf_density);
                n += 1;
                if node.leaf_density > 0.0 {
                    min = min.min(node.leaf_density);
                }
            }
        }
        Self {
            min_density: if min.is_finite() { min } else { 0.0 },
            mean_density: if n == 0 { 0.0 } else { (sum / f64::from(n)) as f32 },
            max_branch_level: max_level,
        }
    }

    /// `ld0 = min(ld1, 0.5·ld2)`.
    pub fn ld0(&self) -> f32 {
        self.min_density.min(0.5 * self.mean_density)
    }
}

/// f1: bounding-sphere layer value.
pub fn f1_layer(p: &LodParams, layer: u8) -> f32 {
    p.layer_values[usize::from(layer.clamp(1, 3) - 1)]
}

/// The constants of f2 and f4 for one parameter set, computed once instead of per node (the
/// factors evaluate exactly the same expressions).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RateConsts {
    /// `ln h`.
    pub ln_h: f32,
    /// `BL_max` (at least 1).
    pub bl_max: f32,
    /// f2's `k1 = 0.5 / (BL_max·log_h(far))`.
    pub k1: f32,
    /// f4's `k3 = 1 / log10(far)`.
    pub k3: f32,
}

impl RateConsts {
    /// Constants of `p`.
    pub fn new(p: &LodParams) -> Self {
        let ln_h = p.log_base.ln();
        let log_far = p.far.ln() / ln_h;
        let bl_max = f32::from(p.max_branch_level.max(1));
        Self {
            ln_h,
            bl_max,
            k1: 0.5 / (bl_max * log_far),
            k3: 1.0 / p.far.log10(),
        }
    }

    /// f2 (see [`f2_branch_distance`]).
    #[inline]
    pub fn f2(&self, p: &LodParams, branch_level: u8, dist: f32) -> f32 {
        if dist.is_nan() || dist <= p.near {
            return 0.0;
        }
        if dist >= p.far {
            return 0.5;
        }
        let bl = f32::from(branch_level).min(self.bl_max);
        let v = self.k1 * bl * (dist.ln() / self.ln_h);
        if v.is_finite() { v.clamp(0.0, 0.5) } else { 0.0 }
    }

    /// f4 (see [`f4_distance`]).
    #[inline]
    pub fn f4(&self, p: &LodParams, dist: f32) -> f32 {
        if dist.is_nan() || dist <= p.near {
            return 0.0;
        }
        if dist >= p.far {
            return 1.0;
        }
        let v = self.k3 * dist.log10();
        if v.is_finite() { clamp01(v) } else { 0.0 }
    }
}

/// f2: branch level and distance.
pub fn f2_branch_distance(p: &LodParams, branch_level: u8, dist: f32) -> f32 {
    RateConsts::new(p).f2(p, branch_level, dist)
}

/// f3: leaf density. `initial_density` is the node's `ld`, `current_rate` the rate in force.
pub fn f3_density(stats: &TreeStats, initial_density: f32, current_rate: f32) -> f32 {
    let ld0 = stats.ld0();
    if ld0.is_nan() || ld0 <= 0.0 {
        return 0.0;
    }
    let ld = initial_density * (1.0 - clamp01(current_rate));
    clamp01((ld - ld0) / ld0)
}

/// f4: distance.
pub fn f4_distance(p: &LodParams, dist: f32) -> f32 {
    RateConsts::new(p).f4(p, dist)
}

/// f5: `cos(dir)` clipped at π/2, from the line of sight and the growth direction (any length).
pub fn f5_direction(line_of_sight: Vec3, growth: Vec3) -> f32 {
    f5_from_cosine(growth_cosine(
        line_of_sight,
        line_of_sight.length(),
        growth.try_normalize(),
    ))
}

/// `cos(dir)` unclipped: the cosine of the angle between the line of sight `line_of_sight`
/// (eye → node centre, of length `sight`) and the unit growth direction. NaN when either
/// direction is degenerate (eye at the centre, no growth direction). The line of sight is
/// normalised as `try_normalize` does (times `1/sight`, refused unless that is finite and > 0).
#[inline]
pub fn growth_cosine(line_of_sight: Vec3, sight: f32, unit_growth: Option<Vec3>) -> f32 {
    let rcp = sight.recip();
    match unit_growth {
        Some(g) if rcp.is_finite() && rcp > 0.0 => (line_of_sight * rcp).dot(g),
        _ => f32::NAN,
    }
}

/// f5 from [`growth_cosine`]: clipped to [0, 1], NaN (a degenerate direction) read as 0.
#[inline]
pub fn f5_from_cosine(cos_growth: f32) -> f32 {
    clamp01(cos_growth)
}

/// A node's factors and the resulting rate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RateFactors {
    /// f1..f5.
    pub f: [f32; 5],
    /// `clamp(Σ α_k f_k, 0, 1)`.
    pub rate: f32,
    /// The distance used (sphere surface, 0 inside).
    pub distance: f32,
}

/// `clamp(Σ α_k f_k, 0, 1)`.
pub fn combine(p: &LodParams, f: [f32; 5]) -> f32 {
    clamp01(p.weights.iter().zip(f).map(|(a, f)| a * f).sum())
}

/// Seed 004's rate for one node seen from `eye`, given the rate currently in force for it.
pub fn node_rate(p: &LodParams, stats: &TreeStats, node: &NodeRecord, eye: Vec3, current_rate: f32) -> RateFactors {
    let distance = sphere_distance(eye, node.sphere_center, node.sphere_radius);
    let f = [
        f1_layer(p, node.sphere_layer),
        f2_branch_distance(p, node.branch_level, distance),
        f3_density(stats, node.leaf_density, current_rate),
        f4_distance(p, distance),
        f5_direction(node.sphere_center - eye, node.growth_direction),
    ];
    RateFactors {
        f,
        rate: combine(p, f),
        distance,
    }
}

/// Leaf enlargement when a node goes from rate `r_last` to `r_cur`: `s = √((1 − R_l)/(1 − R_c))`,
/// so that the kept leaves' total area stays about constant (`S_cur = S_last·s²`). Clamped to
/// `[1/cap, cap]` (`cap ≥ 1`); `R_c = 1` (nothing drawn) gives `cap`, or 1 if `R_l = 1` too.
pub fn leaf_enlargement(r_last: f32, r_cur: f32, cap: f32) -> f32 {
    let cap = if cap.is_nan() { 1.0 } else { cap.max(1.0) };
    let num = 1.0 - clamp01(r_last);
    let den = 1.0 - clamp01(r_cur);
    if den <= 0.0 {
        return if num <= 0.0 { 1.0 } else { cap };
    }
    (num / den).sqrt().clamp(1.0 / cap, cap)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f32::consts::{FRAC_PI_2, FRAC_PI_3, PI};

    fn params_1000() -> LodParams {
        LodParams {
            near: 5.0,
            far: 1000.0,
            ..LodParams::default()
        }
    }

    fn close(a: f32, b: f32) -> bool {
        (a - b).abs() < 1e-5
    }

    #[test]
    fn f1_values() {
        let p = LodParams::default();
        assert_eq!(f1_layer(&p, 1), 0.0);
        assert_eq!(f1_layer(&p, 2), 0.4);
        assert_eq!(f1_layer(&p, 3), 0.8);
        assert_eq!(f1_layer(&p, 0), 0.0);
        assert_eq!(f1_layer(&p, 9), 0.8);
    }

    #[test]
    fn f2_hand_values_and_edges() {
        let p = params_1000();
        // k1 = 0.5/(6·log10 1000) = 1/36; BL 3 at 100 m: 3·2/36 = 1/6.
        assert!(close(f2_branch_distance(&p, 3, 100.0), 1.0 / 6.0));
        assert_eq!(f2_branch_distance(&p, 3, 5.0), 0.0);
        assert_eq!(f2_branch_distance(&p, 3, 0.0), 0.0);
        assert_eq!(f2_branch_distance(&p, 3, 1000.0), 0.5);
        assert_eq!(f2_branch_distance(&p, 3, 1e9), 0.5);
        // Deepest level just inside far stays ≤ 0.5.
        assert!(f2_branch_distance(&p, 6, 999.9) <= 0.5);
        assert!(f2_branch_distance(&p, 20, 999.9) <= 0.5);
        // Base 2: log2(100)/ (6·log2(1000)) · 3 is the same ratio.
        let p2 = LodParams { log_base: 2.0, ..p };
        assert!(close(f2_branch_distance(&p2, 3, 100.0), 1.0 / 6.0));
    }

    #[test]
    fn f3_hand_values() {
        let s = TreeStats {
            min_density: 4.0,
            mean_density: 10.0,
            max_branch_level: 4,
        };
        assert_eq!(s.ld0(), 4.0);
        assert_eq!(f3_density(&s, 6.0, 0.0), 0.5);
        assert_eq!(f3_density(&s, 10.0, 0.0), 1.0);
        // Thinned to half: LD = 3 < ld0.
        assert_eq!(f3_density(&s, 6.0, 0.5), 0.0);
        // ld0 = 0.5·ld2 when smaller.
        let s2 = TreeStats {
            min_density: 8.0,
            mean_density: 10.0,
            max_branch_level: 4,
        };
        assert_eq!(s2.ld0(), 5.0);
        assert!(close(f3_density(&s2, 8.0, 0.0), 0.6));
        let empty = TreeStats {
            min_density: 0.0,
            mean_density: 0.0,
            max_branch_level: 0,
        };
        assert_eq!(f3_density(&empty, 8.0, 0.0), 0.0);
        assert_eq!(f3_density(&s, 6.0, f32::NAN), 0.5);
    }

    #[test]
    fn f4_hand_values_and_edges() {
        let p = params_1000();
        assert!(close(f4_distance(&p, 100.0), 2.0 / 3.0));
        assert_eq!(f4_distance(&p, 5.0), 0.0);
        assert_eq!(f4_distance(&p, 0.0), 0.0);
        assert!(close(f4_distance(&p, 5.0001), 5.0001f32.log10() / 3.0));
        assert_eq!(f4_distance(&p, 1000.0), 1.0);
        assert_eq!(f4_distance(&p, f32::INFINITY), 1.0);
        // near < 1: log10 negative inside, read as 0.
        let low = LodParams { near: 0.0, ..p };
        assert_eq!(f4_distance(&low, 0.5), 0.0);
    }

    #[test]
    fn f5_angles() {
        let g = Vec3::Y;
        assert!(close(f5_direction(Vec3::Y, g), 1.0));
        assert!(f5_direction(Vec3::X, g).abs() < 1e-6);
        assert_eq!(f5_direction(-Vec3::Y, g), 0.0);
        let at = |a: f32| Vec3::new(a.sin(), a.cos(), 0.0);
        assert!(close(f5_direction(at(FRAC_PI_3), g), 0.5));
        assert!(f5_direction(at(FRAC_PI_2), g).abs() < 1e-6);
        assert_eq!(f5_direction(at(PI), g), 0.0);
        assert_eq!(f5_direction(Vec3::ZERO, g), 0.0);
        assert_eq!(f5_direction(Vec3::Y, Vec3::ZERO), 0.0);
    }

    fn node(center: Vec3, radius: f32) -> NodeRecord {
        NodeRecord {
            parent: 0,
            subtree_end: 2,
            kind: NodeKind::Leaf,
            branch_level: 3,
            sphere_layer: 2,
            branch: 0,
            leaf_count: 100,
            growth_direction: Vec3::NEG_Z,
            length: 1.0,
            sphere_center: center,
            sphere_radius: radius,
            leaf_density: 6.0,
        }
    }

    #[test]
    fn node_rate_combines_with_default_weights() {
        let p = params_1000();
        let s = TreeStats {
            min_density: 4.0,
            mean_density: 10.0,
            max_branch_level: 6,
        };
        // Node 101 m down −Z, radius 1: distance 100; growth along the line of sight (f5 = 1).
        let r = node_rate(&p, &s, &node(Vec3::new(0.0, 0.0, -101.0), 1.0), Vec3::ZERO, 0.0);
        assert!(close(r.distance, 100.0));
        let want = 0.2 * 0.4 + 0.1 / 6.0 + 0.2 * 0.5 + 0.3 * (2.0 / 3.0) + 0.2 * 1.0;
        assert!(close(r.rate, want), "{} vs {want}", r.rate);
    }

    #[test]
    fn node_rate_camera_inside_crown_is_finite() {
        let p = LodParams::default();
        let s = TreeStats {
            min_density: 4.0,
            mean_density: 10.0,
            max_branch_level: 6,
        };
        let n = node(Vec3::new(0.0, 1.0, 0.0), 3.0);
        let r = node_rate(&p, &s, &n, Vec3::new(0.0, 1.0, 0.0), 0.0);
        assert_eq!(r.distance, 0.0);
        assert!(r.rate.is_finite());
        // f2 = f4 = f5 = 0: only layer and density.
        assert!(close(r.rate, 0.2 * 0.4 + 0.2 * 0.5));
        // Far away with every factor maximal: 0.91 ≤ 1.
        let mut far = node(Vec3::new(0.0, 0.0, -1e6), 1.0);
        far.sphere_layer = 3;
        far.leaf_density = 100.0;
        let r = node_rate(&p, &s, &far, Vec3::ZERO, 0.0);
        assert!(close(r.rate, 0.91));
        // Weights summing above 1 are clamped.
        let heavy = LodParams { weights: [1.0; 5], ..p };
        assert_eq!(node_rate(&heavy, &s, &far, Vec3::ZERO, 0.0).rate, 1.0);
    }

    #[test]
    fn stats_from_nodes() {
        let mut a = node(Vec3::ZERO, 1.0);
        a.leaf_density = 2.0;
        let mut b = a;
        b.leaf_density = 6.0;
        let mut trunk = a;
        trunk.kind = NodeKind::Branch;
        trunk.leaf_density = 0.0;
        trunk.branch_level = 1;
        let s = TreeStats::from_nodes(&[trunk, a, b]);
        assert_eq!(s.min_density, 2.0);
        assert_eq!(s.mean_density, 4.0);
        assert_eq!(s.max_branch_level, 3);
        assert_eq!(s.ld0(), 2.0);
        let e = TreeStats::from_nodes(&[]);
        assert_eq!(e.ld0(), 0.0);
    }

    proptest::proptest! {
        /// Every rate is finite and in [0, 1], wherever the eye is (inside the sphere included).
        #[test]
        fn rate_is_always_in_unit_interval(
            ex in -200.0f32..200.0, ey in -200.0f32..200.0, ez in -200.0f32..200.0,
            radius in 0.0f32..50.0, layer in 0u8..5, level in 0u8..12, density in 0.0f32..100.0,
            current in -0.5f32..1.5, gx in -1.0f32..1.0, gy in -1.0f32..1.0,
        ) {
            let mut n = node(Vec3::new(1.0, 2.0, 3.0), radius);
            n.sphere_layer = layer;
            n.branch_level = level;
            n.leaf_density = density;
            n.growth_direction = Vec3::new(gx, gy, 0.0);
            let s = TreeStats { min_density: 0.5, mean_density: 4.0, max_branch_level: 6 };
            let r = node_rate(&LodParams::default(), &s, &n, Vec3::new(ex, ey, ez), current);
            proptest::prop_assert!(r.rate.is_finite() && (0.0..=1.0).contains(&r.rate));
            proptest::prop_assert!(r.f.iter().all(|f| f.is_finite() && (0.0..=1.0).contains(f)));
            let e = leaf_enlargement(current, r.rate, 2.0);
            proptest::prop_assert!(e.is_finite() && (0.5..=2.0).contains(&e));
        }
    }

    #[test]
    fn enlargement() {
        // R_l = 0 → R_c = 0.75: √(1/0.25) = 2.
        assert!(close(leaf_enlargement(0.0, 0.75, 4.0), 2.0));
        // Reverse shrinks.
        assert!(close(leaf_enlargement(0.75, 0.0, 4.0), 0.5));
        assert_eq!(leaf_enlargement(0.3, 0.3, 4.0), 1.0);
        // Capped near 1 and at 1.
        assert_eq!(leaf_enlargement(0.0, 0.9999, 2.0), 2.0);
        assert_eq!(leaf_enlargement(0.0, 1.0, 2.0), 2.0);
        assert_eq!(leaf_enlargement(1.0, 1.0, 2.0), 1.0);
        assert_eq!(leaf_enlargement(1.0, 0.0, 2.0), 0.5);
        assert!(leaf_enlargement(f32::NAN, 0.5, f32::NAN).is_finite());
    }

    proptest::proptest! {
        /// f5 through [`growth_cosine`] (what the per-tree proposal calls with the growth
        /// direction normalised once) is bit for bit the clipped cosine of the two
        /// `try_normalize`d directions, degenerate and non-finite ones included.
        #[test]
        fn f5_through_the_cosine_is_the_clipped_normalised_dot(
            los in proptest::array::uniform3(proptest::prop_oneof![
                -1e3f32..1e3, proptest::strategy::Just(0.0f32), proptest::strategy::Just(f32::NAN),
                proptest::strategy::Just(f32::INFINITY), proptest::strategy::Just(1e-30f32),
            ]),
            growth in proptest::array::uniform3(proptest::prop_oneof![
                -2.0f32..2.0, proptest::strategy::Just(0.0f32), proptest::strategy::Just(f32::NAN),
            ]),
        ) {
            let (los, growth) = (Vec3::from_array(los), Vec3::from_array(growth));
            let direct = match (los.try_normalize(), growth.try_normalize()) {
                (Some(a), Some(b)) => clamp01(a.dot(b)),
                _ => 0.0,
            };
            let via = f5_from_cosine(growth_cosine(los, los.length(), growth.try_normalize()));
            proptest::prop_assert_eq!(via.to_bits(), direct.to_bits());
            proptest::prop_assert_eq!(f5_direction(los, growth).to_bits(), direct.to_bits());
        }
    }
}
