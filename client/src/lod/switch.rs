//! Seed 004 eq. 13: LOD switch control, per node.
//!
//! Printed as `Δrate < δ1·(dist − near)^k1`, `Δtime_last > δ2·(dist − near)^k2`,
//! `δ1 = 1/(far − near)^k1`, `δ2 = 1/(far − near)^k2`. Read (per SEEDS.md) as: **apply a proposed
//! change only when `|Δrate| ≥ δ1·(dist − near)^k1` and the rate in force has held for at least
//! `δ2·(dist − near)^k2` seconds**. Near nodes therefore change in small steps at any time, far
//! nodes in large steps and rarely.
//!
//! Details of this reading:
//! - `dist − near` is clamped to `[0, far − near]`, so both thresholds lie in [0, 1] (the time
//!   threshold in seconds); at or inside `near` every change applies at once.
//! - The step threshold is additionally capped at [`LodParams::switch_max_step`]: uncapped it
//!   reaches 1 at `far`, where a node whose rate lies strictly inside (0, 1) could never change.
//! - A proposal equal to the rate in force is not a change (the hold time keeps running).
//! - When a change applies, the new rate is the proposed one (no partial step) and the hold time
//!   restarts at 0.

use super::{LodParams, clamp01};

/// `x^k`; `k = 1` (the default exponents) skips `powf`, whose result for `k = 1` is `x` exactly
/// anyway (it is correctly rounded to within one ulp, and `x` is representable).
#[inline]
fn pow(x: f32, k: f32) -> f32 {
    if k == 1.0 { x } else { x.powf(k) }
}

/// Switch-control state of one node.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SwitchState {
    /// Rate in force.
    pub rate: f32,
    /// Seconds the rate in force has held.
    pub held_s: f32,
}

impl SwitchState {
    /// A node starting at `rate` (counted as having held long enough to change at once).
    pub fn new(rate: f32) -> Self {
        Self {
            rate: clamp01(rate),
            held_s: f32::INFINITY,
        }
    }

    /// `(step, hold)` thresholds at distance `dist`.
    pub fn thresholds(p: &LodParams, dist: f32) -> (f32, f32) {
        let span = (p.far - p.near).max(0.0);
        if !p.switch_control || span.is_nan() || span <= 0.0 {
            return (0.0, 0.0);
        }
        let x = if dist.is_nan() {
            0.0
        } else {
            (dist - p.near).clamp(0.0, span)
        };
        let ratio = x / span;
        // δ·x^k = (x/span)^k; 0^0 reads as 1 only for k = 0, where the threshold is constant.
        let step = clamp01(pow(ratio, p.switch_k1)).min(p.switch_max_step.max(0.0));
        let hold = clamp01(pow(ratio, p.switch_k2));
        (step, hold)
    }

    /// The step threshold alone (`thresholds(p, dist).0`).
    #[inline]
    pub fn step_threshold(p: &LodParams, dist: f32) -> f32 {
        let span = (p.far - p.near).max(0.0);
        if span.is_nan() || span <= 0.0 {
            return 0.0;
        }
        let x = if dist.is_nan() {
            0.0
        } else {
            (dist - p.near).clamp(0.0, span)
        };
        clamp01(pow(x / span, p.switch_k1)).min(p.switch_max_step.max(0.0))
    }

    /// Advances by `dt` seconds and considers `proposed`; returns the rate in force afterwards
    /// and whether it changed.
    pub fn update(&mut self, p: &LodParams, proposed: f32, dist: f32, dt: f32) -> (f32, bool) {
        if dt.is_finite() && dt > 0.0 {
            self.held_s += dt;
        }
        let proposed = clamp01(proposed);
        let delta = (proposed - self.rate).abs();
        if delta == 0.0 {
            return (self.rate, false);
        }
        let (step, hold) = Self::thresholds(p, dist);
        if delta >= step && self.held_s >= hold {
            self.rate = proposed;
            self.held_s = 0.0;
            (self.rate, true)
        } else {
            (self.rate, false)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p() -> LodParams {
        // span 100; k1 = 1, k2 = 2; uncapped step.
        LodParams {
            near: 10.0,
            far: 110.0,
            switch_k1: 1.0,
            switch_k2: 2.0,
            switch_max_step: 1.0,
            ..LodParams::default()
        }
    }

    #[test]
    fn thresholds_hand_values() {
        let p = p();
        // dist 60: x = 50, δ1·x = 50/100 = 0.5, δ2·x² = 2500/10000 = 0.25 s.
        assert_eq!(SwitchState::thresholds(&p, 60.0), (0.5, 0.25));
        assert_eq!(SwitchState::thresholds(&p, 10.0), (0.0, 0.0));
        assert_eq!(SwitchState::thresholds(&p, 0.0), (0.0, 0.0));
        assert_eq!(SwitchState::thresholds(&p, 110.0), (1.0, 1.0));
        assert_eq!(SwitchState::thresholds(&p, 1e9), (1.0, 1.0));
        assert_eq!(SwitchState::thresholds(&p, f32::NAN), (0.0, 0.0));
        let capped = LodParams {
            switch_max_step: 0.25,
            ..p
        };
        assert_eq!(SwitchState::thresholds(&capped, 1e9), (0.25, 1.0));
        let off = LodParams {
            switch_control: false,
            ..capped.clone()
        };
        assert_eq!(SwitchState::thresholds(&off, 1e9), (0.0, 0.0));
        for (q, d) in [(&p, 60.0), (&p, 0.0), (&p, f32::NAN), (&capped, 80.0), (&capped, 1e9)] {
            assert_eq!(
                SwitchState::step_threshold(q, d).to_bits(),
                SwitchState::thresholds(q, d).0.to_bits()
            );
        }
    }

    #[test]
    fn near_nodes_change_at_once() {
        let p = p();
        let mut s = SwitchState::new(0.0);
        assert_eq!(s.update(&p, 0.01, 5.0, 0.0), (0.01, true));
        assert_eq!(s.update(&p, 0.02, 10.0, 0.0), (0.02, true));
    }

    #[test]
    fn step_and_hold_both_required() {
        let p = p();
        let mut s = SwitchState::new(0.2);
        // dist 60: needs |Δ| ≥ 0.5 and 0.25 s held.
        assert_eq!(s.update(&p, 0.6, 60.0, 1.0), (0.2, false)); // step 0.4 too small
        assert_eq!(s.update(&p, 0.7, 60.0, 0.0), (0.7, true)); // step 0.5, held ≥ 0.25
        assert_eq!(s.held_s, 0.0);
        assert_eq!(s.update(&p, 0.1, 60.0, 0.1), (0.7, false)); // held 0.1 < 0.25
        assert_eq!(s.update(&p, 0.1, 60.0, 0.15), (0.1, true)); // held 0.25
    }

    #[test]
    fn far_nodes_with_cap_still_move() {
        let p = LodParams {
            switch_max_step: 0.25,
            ..p()
        };
        let mut s = SwitchState::new(0.5);
        // A fresh state counts as held long enough; the step 0.3 passes the 0.25 cap.
        assert_eq!(s.update(&p, 0.8, 1e4, 0.0), (0.8, true));
        // Next change needs 1 s held at or beyond far.
        assert_eq!(s.update(&p, 0.5, 1e4, 0.5), (0.8, false));
        assert_eq!(s.update(&p, 0.5, 1e4, 0.5), (0.5, true));
        // Same rate is not a change.
        assert_eq!(s.update(&p, 0.5, 1e4, 5.0), (0.5, false));
        assert_eq!(s.held_s, 5.0);
    }
}
