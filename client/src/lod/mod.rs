//! Level-of-detail policy: what to draw of each tree and each node, and hence what to fetch.
//!
//! # Conventions
//!
//! - **Axes.** Y up, right-handed, metres; angles in radians unless a name says `_deg`.
//! - **Simplification rate** `Rs ∈ [0, 1]` (seed 004): 0 = every leaf of a node drawn, 1 = none.
//!   A node of `n` leaves draws its first `n·(1 − Rs)` leaves in importance order (see
//!   [`canopy_shared::format::leaf::keep_count`]). Every rate this module returns is clamped to
//!   [0, 1] and is never NaN.
//! - **Distance.** Unless stated otherwise, "distance" is the Euclidean distance from the eye to
//!   the *nearest point of the bounding sphere* of the tree or node: `max(0, |c − eye| − r)`. It is
//!   0 when the camera is inside the sphere (e.g. inside a crown), and every formula here is
//!   defined (no NaN, no infinity leaking into a rate) at distance 0. Using the sphere surface
//!   rather than the centre is conservative: objects are never judged farther (coarser) than
//!   they are.
//! - **Line of sight** of a node: the unit vector from the eye to the node's sphere centre; when
//!   the eye is at the centre it is undefined and the direction factor is 0.
//! - **Screen size.** `screen_px` is the viewport height in pixels and `fov_y` the vertical field
//!   of view, so seed 000's `L` and `α` are the vertical ones.
//!
//! # Modules
//!
//! - [`projection`]: seed 000 projected height and level distances; per-tree representation.
//! - [`rate`]: seed 004 per-node rate `Rs = Σ α_k f_k` and leaf enlargement.
//! - [`pixel`]: pixel-scale leaf budget for far trees (keep fraction and enlargement cap).
//! - [`switch`]: seed 004 eq. 13 switch control (per-node state).
//! - [`bark`]: bark variants by distance (twigs left out, tube sides).
//! - [`flight`]: seed 002 low-altitude flight policy (`LOD_DVT` and the redundancy table).
//! - [`frustum`]: conservative bounding-sphere frustum culling.
//! - [`occlusion`]: conservative occlusion culling by the terrain (a horizon map per eye).
//! - [`tree`]: per-instance glue (subtree culling, representation, per-node rates → keep counts).

pub mod bark;
pub mod flight;
pub mod frustum;
pub mod occlusion;
pub mod pixel;
pub mod projection;
pub mod rate;
pub mod switch;
pub mod tree;

use glam::Vec3;

pub use flight::{FlightParams, FlightView};
pub use frustum::{DepthRange, Frustum};
pub use pixel::{PixelBudget, budget_keep, pixel_budget};
pub use projection::{
    BillboardKind, LadderStep, Representation, choose_representation, projected_height, threshold_distance,
};
pub use rate::{RateConsts, RateFactors, TreeStats, leaf_enlargement, node_rate};
pub use switch::SwitchState;
pub use tree::{
    LeafTable, TreeLodState, leaves_before, subtree_reach, tree_representation, visible_leaves_world, visible_nodes,
    visible_nodes_world, world_spheres,
};

/// Every parameter of the per-node rate (seed 004), leaf enlargement and switch control.
#[derive(Debug, Clone, PartialEq)]
pub struct LodParams {
    /// Distance at or below which a node is at full detail (f2 = f4 = 0), metres, ≥ 0.
    pub near: f32,
    /// Distance at or beyond which f2 = 0.5 and f4 = 1, metres, > `near` and > 1.
    pub far: f32,
    /// Weights `α1..α5` of f1..f5. Defaults α1 = 0.2, α2 = 0.1, α3 = 0.2, α4 = 0.3, α5 = 0.2.
    pub weights: [f32; 5],
    /// f1 per bounding-sphere layer 1 (outermost), 2, 3 (inner): 0.0, 0.4, 0.8.
    pub layer_values: [f32; 3],
    /// Base `h` of f2's `log_h(dist)`, > 1. Default 10.
    pub log_base: f32,
    /// Deepest branch level `BL_max` used to scale f2's `k1` so that f2 ≤ 0.5. Default 6; use
    /// [`TreeStats::max_branch_level`] for a specific tree.
    pub max_branch_level: u8,
    /// Cap of the leaf enlargement factor (≥ 1). Default 2.
    pub max_enlargement: f32,
    /// Switch control exponent `k1` of the rate-step threshold. Default 1.
    pub switch_k1: f32,
    /// Switch control exponent `k2` of the hold-time threshold. Default 1.
    pub switch_k2: f32,
    /// Upper bound of the rate-step threshold (a deviation from eq. 13, which reaches 1 at
    /// `far`: without a bound a far node whose rate is strictly inside (0, 1) could never move).
    /// Default 0.25.
    pub switch_max_step: f32,
    /// Whether switch control holds proposed changes back at all (`false`: every proposal
    /// applies at once, the baseline of seed 004's switch-control experiment). Default true.
    pub switch_control: bool,
    /// Target on-screen size of a kept leaf, pixels, for the pixel-scale leaf budget
    /// ([`pixel`]); `None` turns it off (seed 004's rate alone).
    pub leaf_pixels: Option<f32>,
    /// Whether the leaves the pixel budget keeps are enlarged up to `leaf_pixels` (keeping the
    /// node's leaf area: higher recall and SSIM) or drawn at their own size (a subset of the
    /// full tree's pixels: coverage precision 1). Default true.
    pub leaf_pixels_enlarge: bool,
}

impl Default for LodParams {
    fn default() -> Self {
        Self {
            near: 5.0,
            far: 500.0,
            weights: [0.2, 0.1, 0.2, 0.3, 0.2],
            layer_values: [0.0, 0.4, 0.8],
            log_base: 10.0,
            max_branch_level: 6,
            max_enlargement: 2.0,
            switch_k1: 1.0,
            switch_k2: 1.0,
            switch_max_step: 0.25,
            switch_control: true,
            leaf_pixels: None,
            leaf_pixels_enlarge: true,
        }
    }
}

/// Distance from `eye` to the nearest point of the sphere (`center`, `radius`): 0 inside.
/// Non-finite inputs give 0 (treated as "at the eye", the conservative choice).
pub fn sphere_distance(eye: Vec3, center: Vec3, radius: f32) -> f32 {
    surface_distance((center - eye).length(), radius)
}

/// [`sphere_distance`] from the distance `to_center` between the eye and the sphere's centre.
#[inline]
pub(crate) fn surface_distance(to_center: f32, radius: f32) -> f32 {
    let d = to_center - radius.max(0.0);
    if d.is_finite() { d.max(0.0) } else { 0.0 }
}

/// Clamps to [0, 1], mapping NaN to 0.
pub(crate) fn clamp01(x: f32) -> f32 {
    if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sphere_distance_outside_inside_and_degenerate() {
        assert_eq!(sphere_distance(Vec3::ZERO, Vec3::new(0.0, 0.0, -10.0), 2.0), 8.0);
        assert_eq!(sphere_distance(Vec3::ZERO, Vec3::new(1.0, 0.0, 0.0), 2.0), 0.0);
        assert_eq!(sphere_distance(Vec3::ZERO, Vec3::ZERO, 0.0), 0.0);
        assert_eq!(sphere_distance(Vec3::ZERO, Vec3::new(f32::NAN, 0.0, 0.0), 1.0), 0.0);
    }

    #[test]
    fn default_weights_sum_to_one() {
        let p = LodParams::default();
        assert!((p.weights.iter().sum::<f32>() - 1.0).abs() < 1e-6);
        assert_eq!(p.weights[3], 0.3);
        assert_eq!(p.weights[1], 0.1);
    }

    #[test]
    fn clamp01_handles_nan() {
        assert_eq!(clamp01(f32::NAN), 0.0);
        assert_eq!(clamp01(2.0), 1.0);
        assert_eq!(clamp01(-1.0), 0.0);
    }
}
