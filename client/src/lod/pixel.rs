//! Pixel-scale leaf budget: how many of a far tree's leaves the screen can resolve, and how far
//! the kept ones may be enlarged.
//!
//! Seed 004's rate keeps at least `1 − 0.91` of a node's leaves (its factors cap `Rs` there),
//! however small the tree is on screen. A leaf whose projected size `ℓ_px` is below a pixel
//! cannot be told from its neighbours, so the pixels a node covers depend on its leaves' total
//! area, not their count. This budget keeps a fraction `(ℓ_px / T)²` of each node's leaves and
//! lets the drawer enlarge them up to `T / ℓ_px`: the kept leaves then reach the target size `T`
//! pixels and their total area is what the full node had (`f · s² = 1`), the same argument as
//! seed 004's enlargement, applied only where the enlarged leaf stays at `T` pixels, so that it
//! cannot spill visibly past the crown's silhouette.
//!
//! Near trees (`ℓ_px ≥ T`) are untouched: fraction 1, no enlargement. The budget only lowers keep
//! counts that seed 004's rate and switch control produced; it never raises them, so a node keeps
//! *at most* the budget's fraction. Drawers scale each node's drawn leaves by
//! `min(√(n / drawn), cap)`: the cap bounds every enlarged leaf at `T` pixels whether the leaves
//! were dropped by the budget, by the rate, or have not arrived yet.

/// What the budget allows one tree this frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PixelBudget {
    /// Largest fraction of each node's leaves worth drawing, in (0, 1].
    pub keep_fraction: f32,
    /// Largest enlargement of a kept leaf, ≥ 1.
    pub enlargement_cap: f32,
}

impl PixelBudget {
    /// No budget: every leaf the rate keeps, no enlargement.
    pub const NONE: Self = Self {
        keep_fraction: 1.0,
        enlargement_cap: 1.0,
    };

    /// Whether the budget lowers any keep count.
    pub fn limits(&self) -> bool {
        self.keep_fraction < 1.0
    }
}

/// The budget for leaves of world size `leaf_size` (metres) at `distance` metres from the eye, on
/// a viewport `screen_px` pixels tall whose half vertical field of view has tangent
/// `tan_half_fov`, for a target kept-leaf size of `target_px` pixels.
///
/// `ℓ_px = leaf_size · screen_px / (2 · tan_half_fov · distance)`; keep fraction
/// `min(1, (ℓ_px / target_px)²)`, enlargement cap `max(1, target_px / ℓ_px)`. Any input that is
/// not finite and positive (a target of 0, the eye at or inside the tree's sphere) gives
/// [`PixelBudget::NONE`]: the budget never coarsens what it cannot measure.
pub fn pixel_budget(leaf_size: f32, distance: f32, screen_px: f32, tan_half_fov: f32, target_px: f32) -> PixelBudget {
    let positive = |x: f32| x.is_finite() && x > 0.0;
    if ![leaf_size, distance, screen_px, tan_half_fov, target_px]
        .into_iter()
        .all(positive)
    {
        return PixelBudget::NONE;
    }
    let leaf_px = leaf_size * screen_px / (2.0 * tan_half_fov * distance);
    if !positive(leaf_px) || leaf_px >= target_px {
        return PixelBudget::NONE;
    }
    let ratio = leaf_px / target_px;
    PixelBudget {
        // A tiny positive floor keeps the fraction in (0, 1] when `ratio²` underflows.
        keep_fraction: (ratio * ratio).max(f32::MIN_POSITIVE),
        // Finite even when `ratio` is subnormal (a drawer reads a non-finite cap as 1).
        enlargement_cap: (1.0 / ratio).min(f32::MAX),
    }
}

/// Leaves of a node of `n` leaves the budget allows: `⌈n · keep_fraction⌉`, at least one leaf
/// of a non-empty node, at most `n`.
pub fn budget_keep(n: u32, keep_fraction: f32) -> u32 {
    if n == 0 || keep_fraction.is_nan() || keep_fraction >= 1.0 {
        return n;
    }
    let k = (f64::from(n) * f64::from(keep_fraction.max(0.0))).ceil();
    // `k ≤ n` here, so the cast cannot truncate.
    (k as u32).clamp(1, n)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 60° vertical field, 270 px tall: a pixel at 1 m spans 2·tan(30°)/270 m.
    fn at(distance: f32) -> PixelBudget {
        pixel_budget(0.09, distance, 270.0, (30f32).to_radians().tan(), 1.0)
    }

    #[test]
    fn near_trees_are_untouched_and_far_ones_keep_area() {
        // 0.09 m leaves are one pixel at about 21 m.
        assert_eq!(at(10.0), PixelBudget::NONE);
        assert_eq!(at(21.0), PixelBudget::NONE);
        let b = at(100.0);
        let leaf_px = 0.09 * 270.0 / (2.0 * (30f32).to_radians().tan() * 100.0);
        assert!((b.keep_fraction - leaf_px * leaf_px).abs() < 1e-6, "{b:?}");
        // Kept leaves enlarged to the cap cover the area of all leaves: f·s² = 1.
        assert!((b.keep_fraction * b.enlargement_cap * b.enlargement_cap - 1.0).abs() < 1e-5);
        assert!(
            (b.enlargement_cap * leaf_px - 1.0).abs() < 1e-5,
            "enlarged leaf is the target size"
        );
    }

    #[test]
    fn farther_keeps_fewer_and_enlarges_more() {
        let mut last = at(22.0);
        for d in [30.0, 60.0, 120.0, 500.0, 5_000.0] {
            let b = at(d);
            assert!(b.keep_fraction < last.keep_fraction && b.enlargement_cap > last.enlargement_cap);
            assert!(b.keep_fraction > 0.0 && b.limits());
            last = b;
        }
    }

    #[test]
    fn what_cannot_be_measured_gives_no_budget() {
        let t = (30f32).to_radians().tan();
        for (leaf, d, h, tan, target) in [
            (0.09, 0.0, 270.0, t, 1.0),
            (0.09, -5.0, 270.0, t, 1.0),
            (0.09, f32::NAN, 270.0, t, 1.0),
            (0.09, f32::INFINITY, 270.0, t, 1.0),
            (0.0, 100.0, 270.0, t, 1.0),
            (0.09, 100.0, 0.0, t, 1.0),
            (0.09, 100.0, 270.0, 0.0, 1.0),
            (0.09, 100.0, 270.0, t, 0.0),
            (0.09, 100.0, 270.0, t, f32::NAN),
        ] {
            assert_eq!(
                pixel_budget(leaf, d, h, tan, target),
                PixelBudget::NONE,
                "{leaf} {d} {h} {tan} {target}"
            );
        }
        // Underflow of the fraction still leaves a positive fraction.
        let b = pixel_budget(1e-10, 1e17, 270.0, t, 1.0);
        assert_eq!(b.keep_fraction, f32::MIN_POSITIVE, "{b:?}");
        assert!(b.enlargement_cap.is_finite() && b.enlargement_cap > 1e20, "{b:?}");
    }

    #[test]
    fn budget_keep_rounds_up_and_keeps_one() {
        assert_eq!(budget_keep(100, 1.0), 100);
        assert_eq!(budget_keep(100, 0.5), 50);
        assert_eq!(budget_keep(100, 0.011), 2);
        assert_eq!(budget_keep(100, 1e-9), 1);
        assert_eq!(budget_keep(100, 0.0), 1);
        assert_eq!(budget_keep(0, 0.5), 0);
        assert_eq!(budget_keep(7, f32::NAN), 7);
        assert_eq!(budget_keep(u32::MAX, 0.5), 2_147_483_648);
        assert_eq!(budget_keep(u32::MAX, 1.0), u32::MAX);
    }
}
